"""Propagate the object and palm poses, and the hand joints, to every steady video frame.

Paper, end of Section 3: with the virtual cameras ``T_w_c[i]`` of stage 2,
``T_c_o[i] = inv(T_w_c[i]) @ T_adj @ T_w_o_stage1`` and ``T_c_p[i] = inv(T_w_c[i]) @ T_w_p``.
The static hand's joints are carried into each camera and projected, and compared with the
frame's detected 2D keypoints. Pure numpy, vectorised over frames.

Stage 2's cameras come from 2D hand keypoints alone and are degrees off at realistic detector
noise; every frame's object pose inherits it. ``estimate_adjustment``'s glue
(``tasks/pipeline.py``, ``estimate_adjustment.tracking``) tracks the object in each steady
frame's own depth (:mod:`track_object`, from the registered pose, bounded corrections) and takes
``T_w_o`` as the mean over the registered frames (:mod:`tracked_average`); here, hand and object
being one rigid body after the onset, a tracked pose defines that frame's camera:
``T_w_c[i]' = T_w_o @ inv(T_c_o_tracked[i])`` (:func:`tracked_cameras`); the palm and the
joints are carried by the same corrected cameras (``PosePropagation.T_w_c``, the cameras
used; ``reconstruct_hand``'s own ``T_w_c`` is not changed). A frame the depth does not
support keeps stage 2's camera, with the reason in ``PosePropagation.tracking``.

The glue then adds each frame's validity (``frame_validity``: the hand detection used, the
camera solved, the object pose supported by the frame's depth), which needs the frame's
depth: the stage reads the grasp depth and the object mesh.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from graspcap.schemas.transforms import rigidity_problems
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.object_pose.track_object import ObjectTracking
from graspcap.tasks.outputs.frame_validity import FrameValidity, FrameValidityConfig

STAGE_VERSION = "propagate_poses/5"
STAGE = "propagate_poses"


class JointSource(StrEnum):
    """Which static 3D joints are carried into the frames."""

    SFM = "sfm"
    """``reconstruct_hand``'s joints (``joints_w``): what best explains the 2D detections."""
    FIT = "fit"
    """The fitted (and refined) hand model's joints (``joints_fit_w``): consistent with the
    hand mesh and ``T_c_p``."""


class PropagatePosesConfig(StageConfig):
    """Which joints to propagate and when a 2D detection counts as observed."""

    joints: JointSource = JointSource.SFM
    """Source of the 3D joints carried into each frame."""
    min_confidence: float = 0.0
    """Detections with confidence at or below this are not observed (NaN error)."""
    rigid_tol: float = 1e-4
    """Tolerance of the rigidity check on the input poses (max |R^T R - I|)."""
    validity: FrameValidityConfig = FrameValidityConfig()
    """Tolerances of the per-frame validity (``frame_validity``)."""


PRESETS: dict[str, PropagatePosesConfig] = {
    "default": PropagatePosesConfig(),
    "fitted": PropagatePosesConfig(joints=JointSource.FIT),
}


@dataclass(frozen=True)
class PosePropagation:
    """Per-frame poses and joints; m frames in the order given.

    Attributes
    ----------
    frame_indices : (m,) int
        Video frame index of each row.
    T_c_o : (m, 4, 4) float
        Object in each frame's camera.
    T_c_p : (m, 4, 4) float
        Palm frame in each frame's camera.
    joints_c : (m, 21, 3) float
        Propagated 3D joints in each camera, metres.
    joints_2d_px : (m, 21, 2) float
        Their projections (NaN for joints at or behind the camera plane).
    reproj_err_px : (m, 21) float
        Distance to the observed 2D keypoint (NaN where not observed or not projected).
    reproj_rmse_px : float
        RMS of the finite ``reproj_err_px`` (NaN when there is none).
    n_behind : int
        Joints (over all frames) at or behind the camera plane.
    validity : FrameValidity or None
        Per frame: hand detection used, camera solved, object pose supported by the depth,
        with reasons (the stage's glue adds it; None from :func:`propagate_poses` alone).
    T_w_c : (m, 4, 4) float or None
        The cameras the poses and joints were carried by: ``reconstruct_hand``'s, or where the
        object was tracked in the frame's depth, ``T_w_o @ inv(T_c_o_tracked)``
        (:func:`tracked_cameras`); the catalog's ``frames.T_w_c``.
    tracking : ObjectTracking or None
        Per frame: whether the object was tracked in its depth, and why not (the stage's glue
        adds ``estimate_adjustment``'s tracking; None when it did not track).
    """

    frame_indices: np.ndarray
    T_c_o: np.ndarray
    T_c_p: np.ndarray
    joints_c: np.ndarray
    joints_2d_px: np.ndarray
    reproj_err_px: np.ndarray
    reproj_rmse_px: float
    n_behind: int
    validity: FrameValidity | None = None
    T_w_c: np.ndarray | None = None
    tracking: ObjectTracking | None = None


def _pose(name: str, T: np.ndarray, tol: float) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    problems = rigidity_problems(T, tol)
    if problems:
        raise StageError(STAGE, f"{name} is not a rigid transform: {'; '.join(problems)}")
    return T


def _inv_batch(T: np.ndarray) -> np.ndarray:
    """Inverses (m, 4, 4) of rigid transforms (m, 4, 4)."""
    Rt = np.swapaxes(T[:, :3, :3], 1, 2)
    out = np.zeros_like(T)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("mij,mj->mi", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _check_cameras(T_w_c: np.ndarray, tol: float) -> np.ndarray:
    T = np.asarray(T_w_c, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise StageError(STAGE, f"T_w_c must be (m, 4, 4), got {T.shape}")
    R = T[:, :3, :3]
    with np.errstate(invalid="ignore"):
        orth = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
        bad = ~np.isfinite(T).all(axis=(1, 2)) | ~(orth <= tol) | (np.linalg.det(R) < 0)
        bad |= ~np.all(np.abs(T[:, 3] - [0, 0, 0, 1]) <= tol, axis=1)
    for i in np.nonzero(bad)[0][:1]:  # name the first bad camera with the shared checker
        problems = "; ".join(rigidity_problems(T[i], tol))
        raise StageError(STAGE, f"T_w_c[{i}] is not a rigid transform: {problems} "
                         f"({int(bad.sum())} of {len(T)} cameras are not)")  # fmt: skip
    return T


def _pick_joints(joints_w, joints_fit_w, config: PropagatePosesConfig) -> np.ndarray:
    if config.joints == JointSource.FIT:
        if joints_fit_w is None:
            raise StageError(STAGE, "config asks for the fitted joints but joints_fit_w is None")
        joints, name = joints_fit_w, "joints_fit_w"
    else:
        joints, name = joints_w, "joints_w"
    joints = np.asarray(joints, dtype=float)
    if joints.shape != (21, 3) or not np.all(np.isfinite(joints)):
        raise StageError(STAGE, f"{name} must be (21, 3) and finite, got shape {joints.shape}")
    return joints


def propagate_poses(
    T_w_c: np.ndarray,
    T_adj: np.ndarray,
    T_w_o_stage1: np.ndarray,
    T_w_p: np.ndarray,
    joints_w: np.ndarray,
    K: np.ndarray,
    frame_indices: np.ndarray,
    keypoints_2d: np.ndarray | None = None,
    *,
    joints_fit_w: np.ndarray | None = None,
    config: PropagatePosesConfig = PRESETS["default"],
) -> PosePropagation:
    """Carry the static object, palm and joints into every frame's camera.

    Parameters
    ----------
    T_w_c : (m, 4, 4) float
        Virtual cameras of ``reconstruct_hand`` (world = colour camera at the first steady frame).
    T_adj : (4, 4) float
        Object motion during grasp adjustment, world frame.
    T_w_o_stage1 : (4, 4) float
        Object pose of ``register_object``.
    T_w_p : (4, 4) float
        Palm pose (``fit_hand``'s, or ``refine_grasp``'s).
    joints_w : (21, 3) float
        ``reconstruct_hand``'s joints, world, metres.
    K : (3, 3) float
        Colour intrinsics.
    frame_indices : (m,) int
        Video frame index of each camera.
    keypoints_2d : (m, 21, 3) float, optional
        Observed (u, v, confidence) per frame; confidence <= ``min_confidence`` or NaN
        coordinates mean not observed.
    joints_fit_w : (21, 3) float, optional
        The fitted model's joints; required when ``config.joints`` is ``fit``.
    """
    T_w_c = _check_cameras(T_w_c, config.rigid_tol)
    m = len(T_w_c)
    T_w_o = _pose("T_adj", T_adj, config.rigid_tol) @ _pose(
        "T_w_o_stage1", T_w_o_stage1, config.rigid_tol
    )
    T_w_p = _pose("T_w_p", T_w_p, config.rigid_tol)
    joints = _pick_joints(joints_w, joints_fit_w, config)
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise StageError(STAGE, f"K must be a finite (3, 3) matrix, got shape {K.shape}")
    frames = np.asarray(frame_indices)
    if frames.shape != (m,) or not np.issubdtype(frames.dtype, np.integer):
        raise StageError(STAGE, f"frame_indices must be (m,) = ({m},) integers, got "
                         f"{frames.shape} {frames.dtype}")  # fmt: skip

    T_c_w = _inv_batch(T_w_c)
    T_c_o = T_c_w @ T_w_o
    T_c_p = T_c_w @ T_w_p
    joints_c = np.einsum("mij,kj->mki", T_c_w[:, :3, :3], joints) + T_c_w[:, None, :3, 3]
    in_front = joints_c[..., 2] > 1e-9
    uvw = joints_c @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[..., :2] / uvw[..., 2:3]
    uv[~in_front] = np.nan

    err = np.full((m, 21), np.nan)
    if keypoints_2d is not None:
        obs = np.asarray(keypoints_2d, dtype=float)
        if obs.shape != (m, 21, 3):
            raise StageError(STAGE, f"keypoints_2d must be ({m}, 21, 3), got {obs.shape}")
        seen = (obs[..., 2] > config.min_confidence) & np.all(np.isfinite(obs[..., :2]), axis=-1)
        dist = np.linalg.norm(uv - obs[..., :2], axis=-1)
        err = np.where(seen, dist, np.nan)
    finite = err[np.isfinite(err)]
    rmse = float(np.sqrt(np.mean(finite**2))) if finite.size else float("nan")
    return PosePropagation(
        frame_indices=frames.astype(np.int64),
        T_c_o=T_c_o,
        T_c_p=T_c_p,
        joints_c=joints_c,
        joints_2d_px=uv,
        reproj_err_px=err,
        reproj_rmse_px=rmse,
        n_behind=int(np.sum(~in_front)),
        T_w_c=T_w_c,
    )


def tracked_cameras(T_w_c: np.ndarray, T_w_o: np.ndarray, tracking: ObjectTracking
                    ) -> np.ndarray:
    """The cameras (m, 4, 4) a tracking defines: where a frame's object was tracked,
    ``T_w_o @ inv(T_c_o_tracked)`` (hand and object are one rigid body after the onset, so
    the object's pose in the frame is the frame's camera); elsewhere ``T_w_c`` as given.
    ``T_w_o`` (4, 4) is ``T_adj @ T_w_o_stage1``."""
    out = np.array(T_w_c, dtype=float)
    rows = np.flatnonzero(np.asarray(tracking.tracked, bool))
    if len(rows):
        out[rows] = np.asarray(T_w_o, float) @ _inv_batch(np.asarray(tracking.T_c_o)[rows])
    return out


__all__ = [
    "PRESETS", "STAGE_VERSION", "JointSource", "PosePropagation", "PropagatePosesConfig",
    "propagate_poses", "tracked_cameras",
]  # fmt: skip
