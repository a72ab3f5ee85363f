"""The joint solve's whole-frame tests (``hand_sfm.joint_solve``; ``docs/hand_solver.md``,
"Whole frames"): per-frame residuals, the depth's disagreement with a frame's solved camera,
and the frames off the longest smoothly turning chain of cameras."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.hand_sfm.hand_graph import project_hand

if TYPE_CHECKING:
    from graspcap.tasks.hand_sfm.joint_config import JointSolveConfig


def residuals_px(K, T_c_p, J, uv, ok) -> np.ndarray:
    """Pixel residuals (m, 21); NaN for missing detections or cameras."""
    proj = project_hand(K, T_c_p, J)
    res = np.linalg.norm(proj - uv, axis=2)
    return np.where(ok & np.isfinite(res), res, np.nan)


def frame_medians(res: np.ndarray) -> np.ndarray:
    out = np.full(len(res), np.nan)
    has = np.isfinite(res).any(1)
    out[has] = np.nanmedian(res[has], axis=1)
    return out


def depth_disagrees(T_c_p, J, offset_m, readings, cfg: JointSolveConfig) -> np.ndarray:
    """(m,) frames with enough depth readings of which too few agree with the solved camera
    (``frame_min_depth_share``)."""
    z = (np.einsum("mab,jb->mja", T_c_p[:, :3, :3], J) + T_c_p[:, None, :3, 3])[..., 2]
    has = np.isfinite(readings) & np.isfinite(z)
    with np.errstate(invalid="ignore"):
        agree = has & (np.abs(z - readings - offset_m) <= cfg.frame_depth_gate_m)
    n = has.sum(1)
    return (n >= cfg.frame_min_readings) & (agree.sum(1) < cfg.frame_min_depth_share * n)


def off_smooth_path(T_c_p, active, cfg: JointSolveConfig) -> np.ndarray:
    """(m,) active frames off the longest chain of frames whose consecutive cameras turn
    like a hand turning smoothly (at most ``frame_turn_deg_per_frame`` per frame, or
    ``frame_turn_min_deg``): a mirrored detection is explained by a camera on the other side
    of the hand, another hand's by a camera somewhere else; either breaks the chain."""
    idx = np.flatnonzero(active)
    out = np.zeros(len(T_c_p), bool)
    if len(idx) < 2:
        return out
    R = T_c_p[idx, :3, :3]
    cos = (np.einsum("kab,nab->kn", R, R) - 1.0) / 2.0
    turn = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    allowed = np.maximum(cfg.frame_turn_min_deg,
                         cfg.frame_turn_deg_per_frame * np.abs(idx[:, None] - idx[None, :]))
    fits = turn <= allowed
    length, back = np.ones(len(idx), int), np.full(len(idx), -1)
    for n in range(1, len(idx)):  # longest chain ending at n (a path in a DAG)
        prev = np.flatnonzero(fits[n, :n])
        if len(prev):
            k = prev[np.argmax(length[prev])]
            length[n], back[n] = length[k] + 1, k
    n = int(np.argmax(length))
    on = np.zeros(len(idx), bool)
    while n >= 0:
        on[n], n = True, back[n]
    out[idx[~on]] = True
    return out


def frames_to_drop(judged, depth_bad, other_bad, least: int) -> np.ndarray | None:
    """(m,) judged frames to drop: those failing the depth test or the other tests, or where
    that keeps fewer than ``least`` frames, those failing the other tests alone (the depth test
    condemns nearly every frame where most readings land on the object in front of the hand or
    the start's scale is off: real-detector [90137, 1], 0.00-0.33 of the readings agree on right
    frames, and dropping no frame at all let one mirrored detection turn the cameras 177 deg);
    None when that too keeps fewer.

    judged, depth_bad, other_bad : (m,) bool
    """
    for bad in (depth_bad | other_bad, other_bad):
        if (judged & ~bad).sum() >= least:
            return judged & bad
    return None
