"""Plausibility of a metric hand reconstruction: catch a diverged solve instead of returning it.

A bundle adjustment that settled in a wrong minimum (a depth-reversed hand, a joint run off
to infinity, a scale from the wrong depth readings) can still explain most pixels. What it
cannot do is keep the hand a human hand in front of every camera: bone lengths within human
ranges, every joint in front of every posed camera at a distance a hand-held capture allows,
and a reprojection error near the detector's noise.
"""

from __future__ import annotations

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.hand.model import KEYPOINT_PARENTS
from graspcap.tasks.hand_sfm.solve import rotation_span_deg

BONES: tuple[tuple[int, int], ...] = tuple(
    (p, j) for j, p in enumerate(KEYPOINT_PARENTS) if p >= 0
)
"""(20) parent-child keypoint pairs of the 21-point layout."""


def implausibility(
    joints_w: np.ndarray,
    T_c_w: np.ndarray,
    reproj_rmse_px: float,
    inlier_ratio: float,
    *,
    bone_range_m: tuple[float, float],
    distance_range_m: tuple[float, float],
    max_reproj_rmse_px: float,
    min_inlier_ratio: float,
) -> str:
    """The first reason a reconstruction is not a plausible static hand, or "" if none.

    Parameters
    ----------
    joints_w : (21, 3) float metres, NaN for unreconstructed joints.
    T_c_w : (m, 4, 4) float, world into each posed camera (NaN rows for unposed frames).
    reproj_rmse_px, inlier_ratio : of the final solve.
    bone_range_m : shortest and longest plausible bone (parent to child keypoint).
    distance_range_m : nearest and farthest plausible camera-to-joint distance.
    """
    X = np.asarray(joints_w, dtype=float)
    lo, hi = bone_range_m
    for p, c in BONES:
        length = float(np.linalg.norm(X[c] - X[p]))
        if np.isfinite(length) and not lo <= length <= hi:
            return (
                f"implausible hand: bone {p}-{c} is {1e3 * length:.1f} mm long, outside "
                f"[{1e3 * lo:.0f}, {1e3 * hi:.0f}] mm; the solve diverged or the depth scale "
                "is wrong (check depth_scale_m and the depth alignment)"
            )
    posed = np.all(np.isfinite(T_c_w.reshape(len(T_c_w), -1)), axis=1)
    known = np.all(np.isfinite(X), axis=1)
    Xc = np.einsum("mab,jb->mja", T_c_w[posed][:, :3, :3], X[known]) + T_c_w[posed][:, None, :3, 3]
    near, far = distance_range_m
    if (Xc[..., 2] <= 0).any():
        return "implausible hand: a joint lies behind a camera; the solve diverged"
    dist = np.linalg.norm(Xc, axis=2)
    if dist.size and not (near <= dist.min() and dist.max() <= far):
        return (
            f"implausible hand: joints {1e3 * dist.min():.0f}-{1e3 * dist.max():.0f} mm from the "
            f"camera, outside [{1e3 * near:.0f}, {1e3 * far:.0f}] mm; the solve diverged or "
            "the depth scale is wrong"
        )
    if not reproj_rmse_px <= max_reproj_rmse_px:
        return (
            f"reprojection RMSE {reproj_rmse_px:.1f} px > {max_reproj_rmse_px:.1f} px: the cameras "
            "and joints do not explain the keypoints"
        )
    if not inlier_ratio >= min_inlier_ratio:
        return (
            f"only {inlier_ratio:.0%} of the detections are inliers (< {min_inlier_ratio:.0%}): "
            "the keypoints are not those of one static hand"
        )
    return ""


def check_result(
    cfg, X: np.ndarray, T_c_w: np.ndarray, res: np.ndarray, inlier: np.ndarray, ok: np.ndarray,
    steady_from: int, stage: str = "reconstruct_hand", *, accepted: np.ndarray | None = None,
    rmse_limit_px: float | None = None, rejected: dict[int, str] | None = None,
) -> None:
    """Raise a ``StageError`` naming the reason when a solve of ``reconstruct_hand`` (its
    ``ReconstructConfig`` as ``cfg``) turned too little or is implausible (``implausibility``).

    X : (21, 3) joints; T_c_w : (m, 4, 4) poses (NaN rows unposed); res : (m, 21) pixel
    residuals; inlier, ok : (m, 21) inlier and usable observations. With ``accepted`` (m,)
    bool (frames not rejected whole; ``rejected`` row -> reason) the inlier share is of the
    accepted frames' detections and the rejected share of the frames with
    ``min_points_per_frame`` detections is bounded by ``max_rejected_share``;
    ``rmse_limit_px`` replaces ``max_reproj_rmse_px``.
    """
    m = len(T_c_w)
    if accepted is not None:
        usable = ok.sum(1) >= cfg.min_points_per_frame
        share = float((usable & ~accepted).sum()) / max(int(usable.sum()), 1)
        if share > cfg.max_rejected_share:
            first = next(iter((rejected or {}).values()), "")
            raise StageError(
                stage,
                f"{int((usable & ~accepted).sum())} of {int(usable.sum())} frames rejected whole "
                f"({share:.0%} > {cfg.max_rejected_share:.0%}): one static hand does not explain "
                f"the detections" + (f" (first: {first})" if first else ""),
            )
        ok = ok & accepted[:, None]
    turn_deg = rotation_span_deg(T_c_w)
    little = (
        f"the hand turned only {turn_deg:.1f} deg relative to the camera from frame "
        f"{steady_from} on: too little motion to triangulate the joints from; the participant "
        "should turn the hand and object while holding the grasp"
    )
    if turn_deg < cfg.min_rotation_deg:
        raise StageError(stage, f"{little} (need >= {cfg.min_rotation_deg:g} deg)")
    n_inl = int((inlier & np.all(np.isfinite(T_c_w.reshape(m, -1)), axis=1)[:, None]).sum())
    reason = implausibility(
        X,
        T_c_w,
        float(np.sqrt(np.mean(res[inlier] ** 2))) if inlier.any() else float("inf"),
        n_inl / int(ok.sum()),
        bone_range_m=cfg.bone_range_m,
        distance_range_m=cfg.distance_range_m,
        max_reproj_rmse_px=cfg.max_reproj_rmse_px if rmse_limit_px is None else rmse_limit_px,
        min_inlier_ratio=cfg.min_inlier_ratio,
    )
    if reason:
        raise StageError(
            stage, reason if turn_deg >= cfg.little_rotation_deg else f"{reason}; likely cause: "
            f"{little}",
        )



def check_frames_in_depth(off: np.ndarray, max_share: float, stage: str = "reconstruct_hand"):
    """Raise a ``StageError`` when the first steady frame (the output frame: a camera off in
    depth there shifts the whole hand) or more than ``max_share`` of the frames are off in
    depth (``off`` : (m,) bool, ``hand_sfm.solve.frames_off_in_depth`` of the final solve)."""
    if off[0] or off.mean() > max_share:
        raise StageError(
            stage,
            f"the depth readings of {int(off.sum())} of {len(off)} frames"
            + (" (the first steady frame among them)" if off[0] else "")
            + " agree with each other but not with the solve: the keypoints and the depth "
            "disagree on where those cameras are (check the depth alignment and the keypoints)",
        )
