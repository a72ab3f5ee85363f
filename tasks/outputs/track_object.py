"""Per-frame object tracking in each steady frame's own depth (issue 19, ``propagate_poses``).

After the steady onset the hand and the object are one rigid body, and the paper carries the
object into every frame with stage 2's virtual cameras: ``T_c_o[i] = inv(T_w_c[i]) @ T_w_o``.
Those cameras come from 2D hand keypoints alone; at realistic detector noise they are degrees
off, and every frame's object pose with them. Each frame has its own aligned depth and the
object's mesh is known, so the object is registered into that depth, frame by frame:

- the frame's depth (valid, within range, flying pixels dropped as ``estimate_adjustment``
  does) without the hand's pixels (:func:`adjustment_region.hand_mask`: the final hand, rigid
  with the object, rendered at the start pose, plus the detected keypoints' bones, grown by
  ``mask_dilate_px``), and of the rest only the points within the object's radius plus
  ``reach_m`` of the start pose's centre;
- robust (Tukey) coarse-to-fine point-to-plane ICP of those points onto the mesh's surface
  samples (:func:`registration.engine.refine`), from two starts: the propagated pose and the
  previous frame's tracked pose (when one was tracked at most ``previous_within`` frames
  before: the camera moves little between frames, far less than stage 2's error);
- a start's result is a candidate only when its correction (rotation, and the object centre's
  displacement) is within ``max_rotation_deg`` / ``max_translation_m`` of where it started, and
  its fitness, RMSE and points pass the gates; among the candidates the one the depth agrees
  with most (rendered against measured, hand masked: :func:`depth_agreement`) is kept when it
  agrees on at least ``min_agreement`` and at least as well as the propagated pose does.
  Otherwise the frame keeps the propagated pose, and ``ObjectTracking.reason`` says why.

A near-symmetric object (a bottle, a can) cannot flip: every correction starts from the
propagated pose or the previous frame's tracked one and is bounded, far below a twin's
half turn; a turn about the symmetry axis the depth cannot see stays where the start put it.

Pure numpy and Open3D; no Prefect. The stage's glue (``tasks/pipeline.py``) reads the depth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import inv_T, rotation_error_deg
from graspcap.tasks.hand.image_masks import grow_mask, hand_mask_from_keypoints
from graspcap.tasks.object_pose.adjustment_region import hand_mask
from graspcap.tasks.object_pose.registration.depth_agreement import depth_agreement
from graspcap.tasks.object_pose.registration.engine import (
    Model,
    RegistrationConfig,
    prepare_model,
    refine,
)
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded
from graspcap.tasks.object_pose.registration.point_clouds import (
    cloud_from_depth,
    drop_flying_pixels,
    to_pcd,
    valid_depth,
)

PROPAGATED = "propagated"
PREVIOUS = "previous"


class TrackObjectConfig(StageConfig):
    """Per-frame tracking of the object in each steady frame's depth (``propagate_poses``)."""

    enabled: bool = True
    """Track the object in every steady frame's depth and carry the hand with the corrected
    cameras; False keeps stage 2's cameras, as ``propagate_poses/2`` did."""
    max_range_m: float = 3.0
    """Depth beyond this is treated as invalid."""
    drop_flying: bool = True
    """Drop the pixels on no surface (a time-of-flight camera's veil at depth edges), as
    ``estimate_adjustment`` does."""
    mask_dilate_px: int = 3
    """The hand's pixels are grown by this much before they are dropped."""
    bone_radius_px: float = 6.0
    """Half-thickness of the detected keypoints' bones added to the hand's pixels."""
    reach_m: float = 0.04
    """Depth points within the object's radius plus this of the start pose's centre take part
    (the start is the propagated pose, or the previous frame's tracked pose)."""
    min_points: int = 100
    """Fewer depth points than this near the start pose (the hand covers the object, holes):
    the frame is not tracked."""
    max_rotation_deg: float = 20.0
    """A correction that turns the object by more than this from its start is rejected: a few
    times stage 2's camera error at realistic detector noise (4-12 deg median), well under a
    near-symmetric object's twin (90-180 deg)."""
    max_translation_m: float = 0.08
    """A correction that moves the object's centre by more than this from its start is
    rejected."""
    min_fitness: float = 0.05
    """Fewest share of the depth points within reach (the object's radius plus ``reach_m``
    of its centre) within ``registration.eval_distance_m`` of the posed mesh's surface: a
    floor only (ICP found some of the object's surface). The table, the background and the
    hand's unmasked rim are within reach too: right poses score 0.15-0.4 (a realistic bottle
    at 0.16, a wild carton at 0.35); the depth agreement (``min_agreement``) is the gate."""
    max_rmse_m: float = 0.004
    """Largest RMS distance of those inliers to the surface."""
    agree_tol_m: float = 0.01
    """A pixel agrees with the posed object when its depth is within this of the rendered one
    (``frame_validity``'s ``depth_tol_m``)."""
    agree_stride_px: int = 2
    """The depth agreement judges every this-th pixel of every this-th row."""
    min_agreement: float = 0.5
    """The tracked pose is kept only where the depth agrees with it on this share of the
    visible object pixels (``frame_validity``'s ``min_agreement``), and at least as well as
    with the propagated pose."""
    previous_within: int = 3
    """The previous tracked pose is a start when it was tracked at most this many frames
    before (0: the propagated pose is the only start)."""
    registration: RegistrationConfig = RegistrationConfig(
        icp_voxels_m=(0.004, 0.0025, 0.0015), icp_max_distance_m=(0.03, 0.01, 0.004),
    )
    """ICP levels (the first reaches 3 cm: the propagated pose is degrees and centimetres
    off) and the surface samples; ``eval_distance_m`` scores the fitness."""


DEFAULT = TrackObjectConfig()


@dataclass(frozen=True)
class ObjectTracking:
    """Per frame (the rows of ``PosePropagation``): the object pose tracked in its depth.

    Attributes
    ----------
    T_c_o : (m, 4, 4) float
        The tracked pose where ``tracked``, else the propagated one.
    tracked : (m,) bool
        The frame's depth gave the pose.
    reason : tuple of str or None
        Why a frame kept the propagated pose (None where tracked).
    start : tuple of str or None
        Where the kept correction started: ``"propagated"`` or ``"previous"`` (None where
        not tracked).
    correction_deg, correction_m : (m,) float
        The tracked pose against the propagated one: rotation (deg) and displacement of the
        object's centre (m); NaN where not tracked.
    fitness, rmse_m, agreement : (m,) float
        The kept candidate's ICP fitness and RMSE, and the depth's agreement with it; NaN
        where not tracked.
    """

    T_c_o: np.ndarray
    tracked: np.ndarray
    reason: tuple[str | None, ...]
    start: tuple[str | None, ...]
    correction_deg: np.ndarray
    correction_m: np.ndarray
    fitness: np.ndarray
    rmse_m: np.ndarray
    agreement: np.ndarray


@dataclass(frozen=True)
class _Tried:
    T_c_o: np.ndarray
    start: str
    fitness: float
    rmse_m: float
    agreement: float


def _depth(depth_m: np.ndarray, K: np.ndarray, config: TrackObjectConfig) -> np.ndarray:
    depth = valid_depth(depth_m, config.max_range_m)
    return drop_flying_pixels(depth, K) if config.drop_flying else depth


def _correction(model: Model, T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, displacement of the object's centre m) from pose ``T_a`` to ``T_b``."""
    c_a = T_a[:3, :3] @ model.centroid + T_a[:3, 3]
    c_b = T_b[:3, :3] @ model.centroid + T_b[:3, 3]
    return rotation_error_deg(T_a[:3, :3], T_b[:3, :3]), float(np.linalg.norm(c_b - c_a))


def _from_start(points: np.ndarray, model: Model, T_start: np.ndarray, start: str,
                config: TrackObjectConfig) -> _Tried | str:
    """ICP from ``T_start`` on the ``points`` (n, 3) within reach: the result, or why not."""
    centre = T_start[:3, :3] @ model.centroid + T_start[:3, 3]
    near = points[np.linalg.norm(points - centre, axis=1) <= model.radius_m + config.reach_m]
    if len(near) < config.min_points:
        return f"{len(near)} depth points near the object outside the hand " \
               f"(need {config.min_points})"
    c = refine(to_pcd(near), model, inv_T(T_start), config.registration, start)
    T = inv_T(c.T_o_s)
    rot, move = _correction(model, T_start, T)
    if rot > config.max_rotation_deg or move > config.max_translation_m:
        return f"correction {rot:.1f} deg / {move * 1e3:.0f} mm from the {start} pose " \
               f"(bound {config.max_rotation_deg:g} deg / {config.max_translation_m * 1e3:g} mm)"
    if c.fitness < config.min_fitness or c.inlier_rmse_m > config.max_rmse_m:
        return f"fitness {c.fitness:.2f} (need {config.min_fitness:g}), RMSE " \
               f"{c.inlier_rmse_m * 1e3:.1f} mm (at most {config.max_rmse_m * 1e3:g})"
    return _Tried(T, start, c.fitness, c.inlier_rmse_m, float("nan"))


@single_threaded()
def track_object(
    T_c_o: np.ndarray,
    frame_indices: np.ndarray,
    read_depth: Callable[[int], np.ndarray],
    K: np.ndarray,
    object_mesh: tuple[np.ndarray, np.ndarray],
    hand_mesh_o: tuple[np.ndarray, np.ndarray] | None,
    keypoints: np.ndarray,
    config: TrackObjectConfig = DEFAULT,
) -> ObjectTracking:
    """Track the object in every frame's depth, from its propagated pose.

    Parameters
    ----------
    T_c_o : (m, 4, 4) float, the propagated object poses (``PosePropagation.T_c_o``).
    frame_indices : (m,) int, their video frames (increasing).
    read_depth : video frame index -> its depth (h, w) metres, aligned to colour, 0 = none.
    K : (3, 3) colour intrinsics (ideal pixels).
    object_mesh, hand_mesh_o : (vertices, faces), both in the object frame (the final hand,
        rigid with the object; None: only the keypoints' bones mask the hand).
    keypoints : (m, 21, 3) float, the frames' detections (ideal pixels, confidence).
    """
    T_c_o = np.asarray(T_c_o, dtype=float)
    K = np.asarray(K, dtype=float)
    m = len(T_c_o)
    mesh = (np.asarray(object_mesh[0], float), np.asarray(object_mesh[1], np.int64))
    model = prepare_model(*mesh, config.registration)
    out_T = T_c_o.copy()
    tracked = np.zeros(m, bool)
    reasons: list[str | None] = []
    starts: list[str | None] = []
    nums = np.full((5, m), np.nan)  # correction deg, m, fitness, rmse, agreement
    last: tuple[int, np.ndarray] | None = None  # (frame, tracked pose)
    for j, f in enumerate(np.asarray(frame_indices, dtype=int)):
        T_prop = T_c_o[j]
        pose_starts = [(PROPAGATED, T_prop)]
        if last is not None and 0 < f - last[0] <= config.previous_within:
            pose_starts.append((PREVIOUS, last[1]))
        depth = _depth(read_depth(int(f)), K, config)
        T_mask = pose_starts[-1][1]  # the hand where the best-known pose puts it
        kp = np.asarray(keypoints[j], dtype=float)
        if hand_mesh_o is None:
            hand = hand_mask_from_keypoints(kp[:, :2], kp[:, 2], depth.shape,
                                            config.bone_radius_px)
        else:
            hand = hand_mask(depth.shape, K, T_mask, hand_mesh_o, kp, config.bone_radius_px)
        keep = ~grow_mask(hand, config.mask_dilate_px)
        points = cloud_from_depth(depth, K, keep)
        tried, why = [], []
        for start, T0 in pose_starts:
            r = _from_start(points, model, T0, start, config)
            if isinstance(r, str):
                why.append(f"from the {start} pose: {r}" if len(pose_starts) > 1 else r)
                continue
            agree = depth_agreement(depth, K, mesh, r.T_c_o, config.agree_tol_m, keep,
                                    config.agree_stride_px)[0]
            tried.append(_Tried(r.T_c_o, r.start, r.fitness, r.rmse_m, agree))
        best = max(tried, key=lambda t: (t.agreement, t.fitness), default=None)
        reason = None
        if best is None:
            reason = "not tracked: " + "; ".join(why)
        elif best.agreement < config.min_agreement:
            reason = (f"not tracked: the depth agrees with the tracked pose on "
                      f"{best.agreement:.0%} (need {config.min_agreement:.0%})")
        else:
            prop_agree = depth_agreement(depth, K, mesh, T_prop, config.agree_tol_m, keep,
                                         config.agree_stride_px)[0]
            if best.agreement < prop_agree:
                reason = (f"not tracked: the depth agrees with the propagated pose more "
                          f"({prop_agree:.0%} against {best.agreement:.0%})")
        reasons.append(reason)
        starts.append(None if reason else best.start)
        if reason is None:
            out_T[j], tracked[j] = best.T_c_o, True
            nums[:, j] = (*_correction(model, T_prop, best.T_c_o), best.fitness, best.rmse_m,
                          best.agreement)
            last = (int(f), best.T_c_o)
    return ObjectTracking(out_T, tracked, tuple(reasons), tuple(starts), *nums)


__all__ = ["ObjectTracking", "TrackObjectConfig", "track_object"]
