"""The hand's own depth surface in the joint solve's last step (``JointSolveConfig.depth_refine``).

During the steady window the hand is static in the world (the first steady camera) and the
joint solve's cameras ``T_w_c`` are held: the depth pixels near the solved hand in a few
steady frames, carried into the world, are one cloud of the hand's surface (and of whatever
touches it: the grasped object where the fingers hold it). The palm pose, the metric scale and
the 20 angles are then refined against that cloud (signed distance to the posed model's
capsules) together with the keypoints' reprojections, by scipy's least squares.

The rig's hand is not the model: its fingers are thicker or thinner, its palm wider, its
surface not capsules. So the cloud's distances are measured from the capsules moved out by a
per-session surface offset solved with the rest (under a weak prior), and a Cauchy loss takes
the points that belong to the object, a flying pixel or another part of the hand; points
outside the surface (where the held object lies) under a tighter one than points inside.

``joint_solve`` runs it (``refine_solved_hand``) on its final hand where the detections are
noisy (the staged result did not stand clean); the result keeps the unrefined hand when the
refinement fails (too few points, a non-finite result, an exception of the solver) or when it
makes the keypoints' median reprojection residual over the kept frames grow by more than
``max_reproj_growth`` (the depth pulled the hand off what the detections see). Measured
before wiring on the cached joint solves of the tuning sessions
real-detector ``[82100, i]`` and wild ``[9700, i]``, i < 8, 60 frames (experiment script
/tmp/handdepth/exp.py, outside the repository): the hand in each frame 12.7 -> 10.3 mm (median
of 16; better on 12, worse on wild ``[9700, 2]`` 7.0 -> 10.6 and ``[9700, 3]`` 12.0 -> 14.0),
SfM joints 10.5 -> 8.9 mm, about 5 CPU s per session; short of the 5-7 mm asked for. The
same numbers from the wired stage (joint_solve/7, /tmp/handdepth/wired.py). Tried and not
kept: a free-space term (samples 5/10/20 mm before each cloud point along its ray held outside
the hand, weight 1) moved wild ``[9700, 2]`` 10.6 -> 9.9 mm but ``[9700, 3]`` 14.0 -> 14.2 and
real-detector ``[82100, 0]``, ``[82100, 4]`` not at all, at 2-3x the CPU (4 sessions only).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import from_rotvec, inv_T, transform_points
from graspcap.tasks.hand.model import Capsules, HandModel, HandSide

# scipy: imported where used, so that importing the stage table stays cheap


class HandDepthConfig(StageConfig):
    """The depth-surface refinement at the end of ``joint_solve`` (part of its config)."""

    enabled: bool = True
    """Refine the joint solve's hand against its own fused depth surface (needs the depth
    frames; only where the solve ran from noisy detections, see ``JointSolveConfig``)."""
    frames: int = 12
    """Steady frames whose depth is fused (evenly spread over the kept frames)."""
    stride_px: int = 2
    """Every this many pixels of a frame's depth are read (rows and columns)."""
    margin_share: float = 0.15
    """The window read around the hand's projected keypoints grows by this share of their
    extent on each side."""
    min_height_m: float = 0.015
    """Points less than this above the platter's top plane are the static scene."""
    max_jump_m: float = 0.008
    """A pixel whose depth differs from a neighbour's by more is a flying pixel (silhouette)
    and is dropped."""
    gate_m: float = 0.015
    """The first round reads the points within this of the joint solve's hand surface."""
    gate_sigmas: float = 3.0
    """The second round keeps the points within this many robust sigmas (1.4826 MAD) of the
    first round's surface..."""
    min_gate_m: float = 0.006
    """...but at least this far."""
    max_points: int = 1500
    """At most this many cloud points in a solve (an even subsample)."""
    min_points: int = 200
    """Fewer points than this: no refinement (the joint solve's hand stands)."""
    sigma_m: float = 0.004
    """Sigma of one point's signed distance (depth noise, misalignment, model error)."""
    effective_points: float = 300.0
    """The cloud weighs as much as this many independent points (its errors are correlated:
    one misfit of the model's surface shows in every point of a part)."""
    keypoint_weight: float = 1.0
    """Weight of the reprojection residuals (their errors are correlated over the frames
    too: a real detector's miss of a joint lasts several frames)."""
    cauchy_k: float = 2.0
    """Cauchy loss of the distances and the reprojections, in sigmas."""
    outside_cauchy_k: float = 0.5
    """Cauchy loss of the distances of points outside the surface (the object the hand holds
    lies outside it, never inside), in sigmas."""
    offset_sigma_m: float = 0.0015
    """Sigma of the prior of the per-session surface offset (the rig's skin outside the
    model's capsules) around 0: a wild hand's skin is within a few mm of the model's; a loose
    prior lets the offset take up the object's points around the fingers instead."""
    angle_sigma_rad: float = 0.5
    """Sigma of the pull of every angle towards the joint solve's."""
    scale_sigma: float = 0.1
    """Sigma of the log scale around the joint solve's."""
    max_nfev: int = 40
    """Most residual evaluations (Jacobians by finite differences) of one round."""
    max_reproj_growth: float = 1.25
    """The refined hand is kept only when the median reprojection residual (pixels) of the
    detections in the kept frames grows by at most this factor (else the unrefined hand
    stands)."""


@dataclass(frozen=True)
class DepthRefinement:
    """The refined hand and what the step measured.

    T_w_p : (4, 4) palm; angles_rad : (20,); scale : the metric scale.
    offset_m : the per-session surface offset; points : cloud points of the last round;
    rms_before_m, rms_after_m : robust (1.4826 MAD) spread of the last round's distances
    at the start and at the result.
    """

    T_w_p: np.ndarray
    angles_rad: np.ndarray
    scale: float
    offset_m: float
    points: int
    rms_before_m: float
    rms_after_m: float


@dataclass(frozen=True)
class DepthRefineReport:
    """What the depth refinement did in ``joint_solve`` (``JointSolve.depth_refine``).

    kept : the refined hand is the result's; note : why not (empty when kept).
    cloud_points : fused depth points; points : points in the last round (0 without one).
    offset_m : the per-session surface offset (NaN without a refinement).
    rms_before_m, rms_after_m : robust spread of the last round's distances.
    reproj_before_px, reproj_after_px : median reprojection residual of the kept frames'
        detections before and after (the guard's test; NaN where not measured).
    joints_w_before : (21, 3) the unrefined hand's keypoints (the world of the result).
    """

    kept: bool
    note: str
    cloud_points: int
    points: int
    offset_m: float
    rms_before_m: float
    rms_after_m: float
    reproj_before_px: float
    reproj_after_px: float
    joints_w_before: np.ndarray


def capsule_distance(points: np.ndarray, caps: Capsules) -> np.ndarray:
    """Signed distance (n,) of points (n, 3) to the union of capsules (negative inside)."""
    a, b = caps.start, caps.end
    ab = b - a
    L2 = np.maximum(np.sum(ab**2, axis=1), 1e-12)
    t = np.clip(np.einsum("nkc,kc->nk", points[:, None, :] - a[None], ab) / L2, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(points[:, None, :] - closest, axis=2) - caps.radius[None], 1)


def hand_cloud(
    depth_frame: Callable[[int], np.ndarray], K: np.ndarray, first_frame: int,
    rows: np.ndarray, T_w_c: np.ndarray, joints_w: np.ndarray,
    T_color_turntable: np.ndarray | None, cfg: HandDepthConfig,
) -> np.ndarray:
    """World points (n, 3) of the depth around the hand in solve rows ``rows`` (video frames
    ``first_frame + row``; cameras ``T_w_c`` (m, 4, 4)): each frame's pixels in the window of
    the projected ``joints_w`` (21, 3), without flying pixels and the static scene."""
    out = []
    for i in rows:
        T_c_w = inv_T(T_w_c[i])
        Jc = transform_points(T_c_w, joints_w)
        if np.any(Jc[:, 2] <= 0):
            continue
        uv = Jc[:, :2] / Jc[:, 2:] * np.diag(K)[:2] + K[:2, 2]
        depth = np.asarray(depth_frame(first_frame + int(i)), dtype=float)
        h, w = depth.shape
        lo, hi = uv.min(0), uv.max(0)
        pad = cfg.margin_share * (hi - lo).max()
        u0, v0 = np.clip(np.floor(lo - pad).astype(int), 1, [w - 2, h - 2])
        u1, v1 = np.clip(np.ceil(hi + pad).astype(int), 1, [w - 2, h - 2])
        vv, uu = np.mgrid[v0:v1:cfg.stride_px, u0:u1:cfg.stride_px]
        z = depth[vv, uu]
        keep = z > 0
        for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            zn = depth[vv + dv, uu + du]
            keep &= (zn > 0) & (np.abs(zn - z) < cfg.max_jump_m)
        if not keep.any():
            continue
        z, u, v = z[keep], uu[keep], vv[keep]
        P = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        if T_color_turntable is not None:
            T_tt_c = inv_T(T_color_turntable)
            P = P[P @ T_tt_c[2, :3] + T_tt_c[2, 3] > cfg.min_height_m]
        out.append(transform_points(T_w_c[i], P))
    return np.concatenate(out) if out else np.zeros((0, 3))


def _even(n: int, k: int) -> np.ndarray:
    """At most ``k`` evenly spread indices of ``n``."""
    return np.arange(n) if n <= k else np.linspace(0, n - 1, k).round().astype(int)


def _pixels(K: np.ndarray, T_c_w: np.ndarray, J_w: np.ndarray) -> np.ndarray:
    """Pixels (f, 21, 2) of world keypoints ``J_w`` (21, 3) in cameras ``T_c_w`` (f, 4, 4)
    (``hand_graph.project_hand`` without its NaN for points behind a camera, which the least
    squares here must not see)."""
    Jc = np.einsum("fab,jb->fja", T_c_w[:, :3, :3], J_w) + T_c_w[:, None, :3, 3]
    return Jc[..., :2] / Jc[..., 2:] * np.diag(K)[:2] + K[:2, 2]


def _robust(r: np.ndarray, k: float) -> np.ndarray:
    """Residuals whose squares are the Cauchy loss: sign(r) sqrt(k^2 log(1 + (r/k)^2))."""
    return np.sign(r) * k * np.sqrt(np.log1p((r / k) ** 2))


def refine_with_depth(
    cloud_w: np.ndarray, uv: np.ndarray, ok: np.ndarray, sigma_px: np.ndarray, K: np.ndarray,
    T_w_c: np.ndarray, active: np.ndarray, side: HandSide, T_w_p: np.ndarray,
    angles: np.ndarray, bone_scale: np.ndarray, scale: float, cfg: HandDepthConfig,
) -> DepthRefinement | None:
    """The hand refined against the cloud ``cloud_w`` (n, 3) and the detections ``uv``
    (m, 21, 2) (``ok`` (m, 21), sigmas ``sigma_px`` (m, 21)) of the ``active`` (m,) frames,
    cameras ``T_w_c`` (m, 4, 4) held; bone factors ``bone_scale`` (20,) held. Two rounds: the
    points within ``gate_m`` of the start's surface, then within ``gate_sigmas`` robust
    sigmas of the first result's. None with fewer than ``min_points`` points."""
    from scipy.optimize import least_squares

    model = HandModel(side)
    lower, upper = model.lower_rad, model.upper_rad
    a0 = np.clip(np.asarray(angles, float), lower, upper)
    rows = np.flatnonzero(active)
    T_c_w = np.stack([inv_T(T_w_c[i]) for i in rows])
    sel = ok[rows]
    target = uv[rows][sel]
    inv_sigma = 1.0 / sigma_px[rows][sel]
    log_s0 = float(np.log(scale))

    def unpack(x):
        return T_w_p @ from_rotvec(x[:3], x[3:6]), x[6:26], log_s0 + x[26], x[27]

    def reproj(T, ang, s):
        p = _pixels(K, T_c_w, model.keypoints(ang, T, s, bone_scale))
        return ((p[sel] - target) * inv_sigma[:, None]).ravel()

    def distances(x, pts):
        T, ang, ls, off = unpack(x)
        return capsule_distance(pts, model.capsules(ang, T, np.exp(ls), bone_scale)) - off

    x = np.concatenate([np.zeros(6), a0, [0.0, 0.0]])
    start_d = distances(x, cloud_w)
    pts = cloud_w[np.abs(start_d) <= cfg.gate_m]
    before = after = float("nan")
    for rnd in range(2):
        if rnd == 1:
            d = distances(x, cloud_w)
            spread = 1.4826 * np.median(np.abs(d[np.abs(d) <= cfg.gate_m]))
            pts = cloud_w[np.abs(d) <= max(cfg.min_gate_m, cfg.gate_sigmas * spread)]
        if len(pts) < cfg.min_points:
            return None
        pts = pts[_even(len(pts), cfg.max_points)]
        w = np.sqrt(min(1.0, cfg.effective_points / len(pts)))

        def residuals(x, pts=pts, w=w):
            T, ang, ls, off = unpack(x)
            d = capsule_distance(pts, model.capsules(ang, T, np.exp(ls), bone_scale)) - off
            return np.concatenate([
                w * np.where(d > 0, _robust(d / cfg.sigma_m, cfg.outside_cauchy_k),
                             _robust(d / cfg.sigma_m, cfg.cauchy_k)),
                cfg.keypoint_weight * _robust(reproj(T, ang, np.exp(ls)), cfg.cauchy_k),
                (x[6:26] - a0) / cfg.angle_sigma_rad,
                [x[26] / cfg.scale_sigma, x[27] / cfg.offset_sigma_m],
            ])

        lo = np.concatenate([np.full(6, -np.inf), lower, [-np.inf, -np.inf]])
        hi = np.concatenate([np.full(6, np.inf), upper, [np.inf, np.inf]])
        if rnd == 1:
            before = 1.4826 * float(np.median(np.abs(
                distances(np.concatenate([np.zeros(6), a0, [0.0, x[27]]]), pts))))
        x = least_squares(residuals, np.clip(x, lo, hi), bounds=(lo, hi), x_scale="jac",
                          max_nfev=cfg.max_nfev, method="trf").x
        if rnd == 1:
            after = 1.4826 * float(np.median(np.abs(distances(x, pts))))
    T, ang, ls, off = unpack(x)
    return DepthRefinement(T, ang, float(np.exp(ls)), float(off), len(pts), before, after)


def _median_reproj_px(model, T_w_p, angles, scale, bone_scale, T_w_c, active, uv, ok, K):
    """Median pixel residual of the detections ``ok`` in the ``active`` frames."""
    rows = np.flatnonzero(active)
    T_c_w = np.stack([inv_T(T_w_c[i]) for i in rows])
    p = _pixels(K, T_c_w, model.keypoints(angles, T_w_p, scale, bone_scale))
    sel = ok[rows]
    return float(np.median(np.linalg.norm(p[sel] - uv[rows][sel], axis=1))) if sel.any() \
        else float("nan")


def refine_solved_hand(
    depth_frame: Callable[[int], np.ndarray], K: np.ndarray, steady_from: int,
    T_c_p: np.ndarray, active: np.ndarray, uv: np.ndarray, ok: np.ndarray,
    sigma_px: np.ndarray, side: HandSide, angles: np.ndarray, bone_scale: np.ndarray,
    scale: float, T_color_turntable: np.ndarray | None, cfg: HandDepthConfig,
) -> tuple[np.ndarray, np.ndarray, float, DepthRefineReport]:
    """The joint solve's final hand refined against its fused depth, cameras held.

    T_c_p : (m, 4, 4) the palm in every solve frame's camera (filled, ``fill_poses``; the
    world is camera 0's, as the result's); active : (m,) the kept frames; uv, ok, sigma_px :
    (m, 21, 2), (m, 21), (m, 21) detections; angles (20,), bone_scale (20,), scale : the hand.
    Returns ``T_c_p``, angles and scale, refined where kept (else the inputs), and the report.
    """
    model = HandModel(side)
    T_w_p = T_c_p[0].copy()
    T_w_c = np.stack([T_w_p @ inv_T(T) for T in T_c_p])
    T_w_c[0] = np.eye(4)
    J0 = model.keypoints(angles, T_w_p, scale, bone_scale)
    args = (T_w_c, active, uv, ok, K)
    before_px = _median_reproj_px(model, T_w_p, angles, scale, bone_scale, *args)

    def unrefined(note, cloud=0, ref=None, after_px=float("nan")):
        nan = float("nan")
        return T_c_p, angles, scale, DepthRefineReport(
            False, note, cloud, 0 if ref is None else ref.points,
            nan if ref is None else ref.offset_m, nan if ref is None else ref.rms_before_m,
            nan if ref is None else ref.rms_after_m, before_px, after_px, J0)

    rows = np.flatnonzero(active)
    rows = rows[_even(len(rows), cfg.frames)]
    try:
        cloud = hand_cloud(depth_frame, K, steady_from, rows, T_w_c, J0, T_color_turntable, cfg)
        ref = refine_with_depth(cloud, uv, ok, sigma_px, K, T_w_c, active, side, T_w_p, angles,
                                bone_scale, scale, cfg)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return unrefined(f"failed: {exc}"[:200])
    if ref is None:
        return unrefined(f"too few points near the hand (of {len(cloud)})", len(cloud))
    if not (np.all(np.isfinite(ref.T_w_p)) and np.all(np.isfinite(ref.angles_rad))
            and np.isfinite(ref.scale)):
        return unrefined("non-finite result", len(cloud))
    after_px = _median_reproj_px(model, ref.T_w_p, ref.angles_rad, ref.scale, bone_scale, *args)
    if not after_px <= cfg.max_reproj_growth * before_px:
        return unrefined(f"reprojection {before_px:.2f} -> {after_px:.2f} px", len(cloud), ref,
                         after_px)
    T_c_p_new = np.stack([inv_T(T) @ ref.T_w_p for T in T_w_c])
    report = DepthRefineReport(True, "", len(cloud), ref.points, ref.offset_m, ref.rms_before_m,
                               ref.rms_after_m, before_px, after_px, J0)
    return T_c_p_new, ref.angles_rad, ref.scale, report


__all__ = ["DepthRefineReport", "DepthRefinement", "HandDepthConfig", "capsule_distance",
           "hand_cloud", "refine_solved_hand", "refine_with_depth"]
