"""Per-frame object tracking in each steady frame's own depth (issue 19; run by
``estimate_adjustment``'s glue, whose ``T_w_o`` becomes the mean over the registered frames
(:mod:`tracked_average`), and used by ``propagate_poses``).

After the steady onset the hand and the object are one rigid body, and the paper carries the
object into every frame with stage 2's virtual cameras: ``T_c_o[i] = inv(T_w_c[i]) @ T_w_o``.
Those cameras come from 2D hand keypoints alone; at realistic detector noise they are degrees
off, and every frame's object pose with them. Each frame has its own aligned depth and the
object's mesh is known, so the object is registered into that depth, frame by frame:

- the frame's depth in the object's pixel box at its start poses (valid, within range,
  flying pixels dropped as ``estimate_adjustment`` does) without the hand's pixels
  (:func:`adjustment_region.hand_mask`: the final hand, rigid with the object, rendered at
  the start pose, plus the detected keypoints' bones, grown by ``mask_dilate_px``), and of
  the rest only the points within ``band_m`` of the object's surface at the start pose (the
  table, the background and the hand's unmasked rim within the object's reach pulled a thin
  remote 50-180 deg away);
- robust (Tukey) coarse-to-fine point-to-plane ICP of those points onto the mesh's surface
  samples (:func:`registration.engine.refine`), from two starts: the propagated pose and the
  previous frame's tracked pose (when one was tracked at most ``previous_within`` frames
  before: the camera moves little between frames, far less than stage 2's error); the
  propagated start first, the previous one only when the first's result is not kept
  (``first_start_suffices``: half the ICP of most tracked frames);
- the ICP correction is kept only along the directions the points constrain
  (``min_constraint``: the eigen-directions of their point-to-plane information), so a flat
  face's slide and in-plane turn, or a can's turn about its axis, stay where the start put
  them;
- a start's result is a candidate only when its correction (rotation, and the object centre's
  displacement) is within ``max_rotation_deg`` / ``max_translation_m`` of where it started and of
  the propagated pose, its fitness, RMSE and points pass the gates, and (with ``joints_o``) the
  hand's joints carried with it land no further from the detected keypoints than
  ``max_reproj_increase`` beyond the propagated pose's. Each pose is scored by the depth rendered
  against the measured (hand masked, :func:`depth_agreement`): the truncated mean squared difference
  (a pixel off by more than ``agree_tol_m`` costs ``agree_tol_m``'s square). The best candidate is
  kept when the depth agrees with it on at least ``min_agreement`` and it costs at most ``1 -
  min_gain`` of the propagated pose's cost: where stage 2's camera is already right the depth cannot
  tell a better pose (it leaves a flat object's turn in its plane nearly free, ICP drifts along it
  with the sensor's noise), and the frame keeps it. Otherwise the frame keeps the propagated pose,
  and ``ObjectTracking.reason`` says why.

A near-symmetric object (a bottle, a can) cannot flip: every correction starts from the
propagated pose or the previous frame's tracked one and is bounded, far below a twin's
half turn. A body of revolution (:func:`symmetry.revolution_axis`: a can, a bulb) keeps the
propagated pose's spin about its axis whichever start the correction came from
(``revolution_tolerance_m``): ``min_constraint`` already drops the spin of a correction from
the propagated pose (at most 0.03 deg on wild [22921, 4], a can), but a start from the
previous frame's tracked pose carried that frame's spin, in its camera, into the next, turning
a right camera about the axis (+1.0-1.5 deg on the frames so tracked).

Pure numpy and Open3D; no Prefect. ``estimate_adjustment``'s glue (``tasks/pipeline.py``) reads
the depth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import inv_T, make_T, rotation_error_deg, transform_points
from graspcap.tasks.hand.image_masks import grow_mask, hand_mask_from_keypoints
from graspcap.tasks.object_pose.adjustment_region import hand_mask
from graspcap.tasks.object_pose.registration.depth_agreement import depth_agreement, image_box
from graspcap.tasks.object_pose.registration.engine import (
    Model,
    RegistrationConfig,
    evaluate,
    prepare_model,
    refine,
    surface_distance,
)
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded
from graspcap.tasks.object_pose.registration.point_clouds import (
    cloud_from_depth,
    drop_flying_pixels,
    to_pcd,
    valid_depth,
)
from graspcap.tasks.object_pose.registration.symmetry import revolution_axis

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

# scipy: imported where used, so that importing the stage table stays cheap

PROPAGATED = "propagated"
PREVIOUS = "previous"


class TrackObjectConfig(StageConfig):
    """Per-frame tracking of the object in each steady frame's depth
    (``estimate_adjustment.tracking``)."""

    enabled: bool = True
    """Track the object in every steady frame's depth (``propagate_poses`` carries the hand with
    the cameras it defines); False keeps stage 2's cameras, as ``propagate_poses/2`` did."""
    max_range_m: float = 3.0
    """Depth beyond this is treated as invalid."""
    drop_flying: bool = True
    """Drop the pixels on no surface (a time-of-flight camera's veil at depth edges), as
    ``estimate_adjustment`` does."""
    mask_dilate_px: int = 3
    """The hand's pixels are grown by this much before they are dropped."""
    bone_radius_px: float = 6.0
    """Half-thickness of the detected keypoints' bones added to the hand's pixels."""
    box_margin_m: float = 0.01
    """Only the object's pixel box at its start poses is read (the hand rendered, the depth's
    points taken), grown by what ``band_m`` plus this span at the object's nearest point."""
    reach_m: float = 0.04
    """Depth points within the object's radius plus this of the start pose's centre are
    looked at (the start is the propagated pose, or the previous frame's tracked pose)..."""
    band_m: float = 0.025
    """...and of them those within this of the object's surface at the start pose take part:
    the object's own points while the start is off by up to ~10 deg / 2 cm."""
    min_points: int = 100
    """Fewer depth points than this in the band (the hand covers the object, holes): the
    frame is not tracked."""
    min_constraint: float = 0.02
    """A correction moves the object only along the directions the depth points constrain:
    eigen-directions of their point-to-plane information (about the object's centre, turns in
    metres at its radius) whose eigenvalue is at least this share of the largest; the others
    stay where the start put them (0: the whole ICP correction). A flat face seen alone lets
    ICP slide and turn in its plane (a thin remote went 50-180 deg) and a can turn about its
    axis, on the sensor's noise."""
    revolution_tolerance_m: float = 0.005
    """An object whose surface turns of 30, 60, ... 330 deg about a principal axis move by at
    most this (:func:`symmetry.revolution_axis`: a can, a bulb; the evaluation's symmetry
    tolerance) is a body of revolution: a correction's turn about that axis (its spin, which
    the depth cannot see) is dropped, and the tracked pose keeps the propagated pose's spin,
    stage 2's camera's, taking from the depth only the axis's direction and the position
    (0: the whole correction). ``min_constraint`` alone let ICP's spin through where a
    partly seen can's facets, rim and tab weighed a little (wild [22921, 4], can: stage 2's
    cameras 0.70 deg, the delivered 1.62 deg), and a start from the previous frame carried
    its spin into the next frame."""
    constraint_distance_m: float = 0.004
    """Depth points within this of the mesh's samples (after ICP) count in that information."""
    max_rotation_deg: float = 20.0
    """A correction that turns the object by more than this from its start, or from the
    propagated pose, is rejected: a few times stage 2's camera error at realistic detector
    noise (4-12 deg median), well under a near-symmetric object's twin (90-180 deg)."""
    max_translation_m: float = 0.08
    """A correction that moves the object's centre by more than this from its start, or from
    the propagated pose, is rejected."""
    min_fitness: float = 0.3
    """Fewest share of the depth points in the band within ``registration.eval_distance_m``
    of the posed mesh's surface."""
    max_rmse_m: float = 0.004
    """Largest RMS distance of those inliers to the surface."""
    agree_tol_m: float = 0.01
    """A pixel agrees with the posed object when its depth is within this of the rendered one
    (``frame_validity``'s ``depth_tol_m``)."""
    agree_stride_px: int = 2
    """The depth agreement judges every this-th pixel of every this-th row."""
    min_agreement: float = 0.5
    """The tracked pose is kept only where the depth agrees with it on this share of the
    visible object pixels (``frame_validity``'s ``min_agreement``)..."""
    min_gain: float = 0.2
    """...and its depth cost (truncated mean squared difference) is at most ``1 - min_gain``
    of the propagated pose's: a clear improvement, not the sensor's noise..."""
    max_reproj_increase: float = 0.03
    """...and the hand's joints, carried with it (one rigid body), project at most this share
    of the hand's image size (its detected keypoints' box diagonal) further from the detected
    keypoints (median) than at the propagated pose: a correction the hand's own detections
    contradict found a surface other than the object (a wrong ``T_adj`` 0.3 m off, the depth
    beside it; wild real-detector [9700, 2]). Needs ``joints_o``; at least 6 keypoints at
    ``detect_confidence``."""
    detect_confidence: float = 0.2
    """A keypoint counts as detected at or above this confidence."""
    previous_within: int = 3
    """The previous tracked pose is a start when it was tracked at most this many frames
    before (0: the propagated pose is the only start)."""
    first_start: Literal["propagated", "previous"] = "propagated"
    """The start tried first..."""
    first_start_suffices: bool = True
    """...and when its result passes every gate and would be kept (agreement, gain), the
    other start is not tried (half the ICP of such a frame). False: both starts always run
    and the lower depth cost wins."""
    same_start_deg: float = 1.0
    """The second start is not tried when it lies within this rotation...
    """
    same_start_m: float = 0.002
    """...and this displacement of the object's centre from the first (ICP from either ends in
    the same place)."""
    registration: RegistrationConfig = RegistrationConfig(
        icp_voxels_m=(0.004, 0.0025, 0.0015), icp_max_distance_m=(0.02, 0.008, 0.004),
        icp_max_points=2000, eval_max_points=3000,
    )
    """ICP levels (the first reaches 2 cm: the propagated pose is degrees and centimetres
    off; the depth is voxelised at the finest level first) and the surface samples;
    ``eval_distance_m`` scores the fitness (on at most ``eval_max_points`` points)."""


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
    gain : (m,) float
        1 - the tracked pose's depth cost over the propagated pose's (NaN where no candidate
        was scored).
    T_c_o_registered : (m, 4, 4) float
        The best candidate where ``registered`` (the frame's depth registered, whether or not
        the gain test kept it), else the propagated pose.
    registered : (m,) bool
        A candidate passed every gate but the gain (the depth agrees with it on at least
        ``min_agreement``); True wherever ``tracked``.
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
    gain: np.ndarray
    T_c_o_registered: np.ndarray | None = None
    registered: np.ndarray | None = None


@dataclass(frozen=True)
class _Tried:
    T_c_o: np.ndarray
    start: str
    fitness: float
    rmse_m: float
    agreement: float
    cost: float


def _depth(depth_m: np.ndarray, K: np.ndarray, config: TrackObjectConfig) -> np.ndarray:
    depth = valid_depth(depth_m, config.max_range_m)
    return drop_flying_pixels(depth, K) if config.drop_flying else depth


def _correction(model: Model, T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation deg, displacement of the object's centre m) from pose ``T_a`` to ``T_b``."""
    c_a = T_a[:3, :3] @ model.centroid + T_a[:3, 3]
    c_b = T_b[:3, :3] @ model.centroid + T_b[:3, 3]
    return rotation_error_deg(T_a[:3, :3], T_b[:3, :3]), float(np.linalg.norm(c_b - c_a))


def _from_start(points: np.ndarray, model: Model, T_start: np.ndarray, start: str,
                T_prop: np.ndarray, config: TrackObjectConfig,
                axis: np.ndarray | None = None) -> _Tried | str:
    """ICP from ``T_start`` on the ``points`` (n, 3) near its surface: the result, or why not
    (its depth scores are filled in by the caller). The correction is bounded from the start
    and from the propagated pose ``T_prop`` alike: a chain of tracked frames never strays
    further from stage 2's cameras than one correction may. ``axis`` (3,), object frame: the
    model's axis of revolution, about which the result keeps ``T_prop``'s spin."""
    centre = T_start[:3, :3] @ model.centroid + T_start[:3, 3]
    near = points[np.linalg.norm(points - centre, axis=1) <= model.radius_m + config.reach_m]
    near = near[surface_distance(model, transform_points(inv_T(T_start), near)) <= config.band_m]
    if len(near) < config.min_points:
        return f"{len(near)} depth points near the object outside the hand " \
               f"(need {config.min_points})"
    scene = to_pcd(near)
    # its own score is not used (the pose is scored below, after the constrained projection)
    c = refine(scene, model, inv_T(T_start), config.registration, start, eval_points=1)
    T = _constrained(model, T_start, inv_T(c.T_o_s), transform_points(c.T_o_s, near), config)
    if axis is not None:
        T = _spin_kept(model, axis, T_prop, T)
    fitness, rmse = evaluate(scene, model, inv_T(T), config.registration.eval_distance_m,
                             config.registration.eval_max_points)
    for name, T0 in ((start, T_start), (PROPAGATED, T_prop)):
        rot, move = _correction(model, T0, T)
        if rot > config.max_rotation_deg or move > config.max_translation_m:
            return f"correction {rot:.1f} deg / {move * 1e3:.0f} mm from the {name} pose " \
                   f"(bound {config.max_rotation_deg:g} deg / " \
                   f"{config.max_translation_m * 1e3:g} mm)"
    if fitness < config.min_fitness or rmse > config.max_rmse_m:
        return f"fitness {fitness:.2f} (need {config.min_fitness:g}), RMSE " \
               f"{rmse * 1e3:.1f} mm (at most {config.max_rmse_m * 1e3:g})"
    return _Tried(T, start, fitness, rmse, float("nan"), float("nan"))


def _constrained(model: Model, T_start: np.ndarray, T_icp: np.ndarray, points_o: np.ndarray,
                 config: TrackObjectConfig) -> np.ndarray:
    """``T_icp`` with only the part of its correction from ``T_start`` that the depth
    constrains: the point-to-plane information of the ``points_o`` (n, 3, object frame) on the
    mesh (the rows ``[p x n, n]`` about the object's centre, rotations in metres at its
    radius); directions whose eigenvalue is below ``min_constraint`` of the largest are left
    where the start put them (a flat face's turn in its plane and slide along it, a can's
    turn about its axis)."""
    from scipy.spatial.transform import Rotation
    if config.min_constraint <= 0:
        return T_icp
    tree, normals = _surface_tree(model)
    d, idx = tree.query(points_o, distance_upper_bound=config.constraint_distance_m)
    ok = np.isfinite(d)
    if ok.sum() < 6:
        return T_start
    r = model.radius_m
    p = (points_o[ok] - model.centroid) / r
    n = normals[idx[ok]]
    J = np.hstack([np.cross(p, n), n])
    lam, U = np.linalg.eigh(J.T @ J)
    keep = lam >= config.min_constraint * lam[-1]
    delta = inv_T(T_start) @ T_icp  # the correction, object frame
    c = model.centroid
    twist = np.concatenate([Rotation.from_matrix(delta[:3, :3]).as_rotvec() * r,
                            delta[:3, :3] @ c + delta[:3, 3] - c])
    twist = U @ np.where(keep, U.T @ twist, 0.0)
    R = Rotation.from_rotvec(twist[:3] / r).as_matrix()
    return T_start @ make_T(R, c + twist[3:] - R @ c)


def _spin_kept(model: Model, axis: np.ndarray, T_prop: np.ndarray, T: np.ndarray
               ) -> np.ndarray:
    """``T`` (4, 4) with the spin of ``T_prop`` about the model's axis of revolution ``axis``
    (3, object frame, through its centroid): the correction ``T_prop -> T`` without its turn
    about the axis (its swing alone: the least rotation that takes the axis where ``T`` has
    it), the object's centre where ``T`` puts it."""
    a = axis / np.linalg.norm(axis)
    b = T_prop[:3, :3].T @ T[:3, :3] @ a  # the corrected axis, in the propagated object frame
    v, cos = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    V = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    swing = np.eye(3) + V + V @ V / (1.0 + cos)  # a -> b (|a - b| stays small: bounded turns)
    R = T_prop[:3, :3] @ swing
    c = model.centroid
    return make_T(R, T[:3, :3] @ c + T[:3, 3] - R @ c)


def _hand_agrees(tried: list[_Tried], T_prop: np.ndarray, joints_o: np.ndarray,
                 K: np.ndarray, kp: np.ndarray, config: TrackObjectConfig
                 ) -> tuple[list[_Tried], list[str]]:
    """The candidates whose hand joints (``joints_o`` carried by the pose) project at most
    ``max_reproj_increase`` of the hand's image size further (median) from the detected
    keypoints ``kp`` (21, 3) than at the propagated pose, and why the others are not."""
    seen = (kp[:, 2] >= config.detect_confidence) & np.all(np.isfinite(kp[:, :2]), axis=1)
    if seen.sum() < 6:
        return tried, []
    size = float(np.linalg.norm(np.ptp(kp[seen, :2], axis=0)))

    def err(T: np.ndarray) -> float:
        p = transform_points(T, joints_o[seen])
        if not np.all(p[:, 2] > 1e-6):
            return float("inf")
        uv = p[:, :2] / p[:, 2:] * np.diag(K)[:2] + K[:2, 2]
        return float(np.median(np.linalg.norm(uv - kp[seen, :2], axis=1)))

    base = err(T_prop)
    ok, why = [], []
    for t in tried:
        e = err(t.T_c_o)
        if e <= base + config.max_reproj_increase * size:
            ok.append(t)
        else:
            why.append(f"from the {t.start} pose: the hand's detections contradict it (its "
                       f"joints {e:.0f} px from them, {base:.0f} px at the propagated pose)")
    return ok, why


def _box(K: np.ndarray, vertices_o: np.ndarray, poses: list[np.ndarray],
         shape: tuple[int, ...], margin_m: float) -> tuple[int, int, int, int]:
    """Pixel box (u0, v0, u1, v1), end exclusive, within the image, of the object at every
    pose in ``poses`` (:func:`image_box`), grown by what ``margin_m`` spans at its nearest."""
    h, w = shape[:2]
    pts = [transform_points(T, vertices_o) for T in poses]
    boxes = np.array([image_box(K, p, w, h) for p in pts])
    z = max(min(float(p[:, 2].min()) for p in pts), 0.1)
    margin = int(np.ceil(max(K[0, 0], K[1, 1]) * margin_m / z))
    lo = np.maximum(boxes[:, :2].min(axis=0) - margin, 0)
    hi = np.minimum(boxes[:, 2:].max(axis=0) + margin, (w, h))
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _surface_tree(model: Model) -> tuple[cKDTree, np.ndarray]:
    from scipy.spatial import cKDTree

    """A KD-tree of the model's surface samples and their normals (kept per model)."""
    key = id(model.dense)
    if _TREES.get("key") != key:
        _TREES.update(key=key, tree=cKDTree(np.asarray(model.dense.points)),
                      normals=np.asarray(model.dense.normals).copy())
    return _TREES["tree"], _TREES["normals"]


_TREES: dict = {}


def _scored(depth: np.ndarray, K: np.ndarray, mesh: tuple, T_c_o: np.ndarray,
            keep: np.ndarray, config: TrackObjectConfig) -> tuple[float, float]:
    """(agreeing share, truncated mean squared depth difference) of the pose's visible
    pixels outside the hand; (0, inf) when none is seen."""
    share, rms, n = depth_agreement(depth, K, mesh, T_c_o, config.agree_tol_m, keep,
                                    config.agree_stride_px)
    if n == 0:
        return 0.0, float("inf")
    return share, share * rms**2 + (1.0 - share) * config.agree_tol_m**2


def _verdict(best: _Tried, cost_prop: float, config: TrackObjectConfig
             ) -> tuple[str | None, float]:
    """(why the candidate is not kept or None, its gain over the propagated pose's depth
    cost ``cost_prop``)."""
    gain = 1.0 - best.cost / cost_prop if cost_prop > 0 else 0.0
    if best.agreement < config.min_agreement:
        return (f"not tracked: the depth agrees with the tracked pose on "
                f"{best.agreement:.0%} (need {config.min_agreement:.0%})"), gain
    if gain < config.min_gain:
        return (f"not tracked: the depth explains the tracked pose {gain:.0%} better than "
                f"the propagated one (need {config.min_gain:.0%})"), gain
    return None, gain


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
    joints_o: np.ndarray | None = None,
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
    joints_o : (21, 3) float, the propagated hand joints in the object frame (rigid with it),
        optional: a tracked pose that carries them away from the detections is rejected
        (``max_reproj_increase``).
    """
    T_c_o = np.asarray(T_c_o, dtype=float)
    K = np.asarray(K, dtype=float)
    m = len(T_c_o)
    mesh = (np.asarray(object_mesh[0], float), np.asarray(object_mesh[1], np.int64))
    model = prepare_model(*mesh, config.registration)
    finest = min(config.registration.icp_voxels_m)
    axis = (revolution_axis(model, config.revolution_tolerance_m)
            if config.revolution_tolerance_m > 0 else None)
    out_T = T_c_o.copy()
    tracked = np.zeros(m, bool)
    reg_T, registered = T_c_o.copy(), np.zeros(m, bool)
    reasons: list[str | None] = []
    starts: list[str | None] = []
    nums = np.full((6, m), np.nan)  # correction deg, m, fitness, rmse, agreement, gain
    last: tuple[int, np.ndarray] | None = None  # (frame, tracked pose)
    for j, f in enumerate(np.asarray(frame_indices, dtype=int)):
        T_prop = T_c_o[j]
        pose_starts = [(PROPAGATED, T_prop)]
        if last is not None and 0 < f - last[0] <= config.previous_within:
            pose_starts.append((PREVIOUS, last[1]))
        T_mask = pose_starts[-1][1]  # the hand where the best-known pose puts it
        if config.first_start == PREVIOUS:
            pose_starts.reverse()
        raw = np.asarray(read_depth(int(f)))
        u0, v0, u1, v1 = _box(K, mesh[0], [T for _, T in pose_starts], raw.shape,
                              config.band_m + config.box_margin_m)
        if u1 - u0 < 2 or v1 - v0 < 2:
            reasons.append("not tracked: the object is out of view")
            starts.append(None)
            continue
        # the object's pixel box: the same rays with the principal point moved (every point,
        # render and projection below is that of the whole image)
        K_box = K.copy()
        K_box[:2, 2] -= (u0, v0)
        depth = _depth(raw[v0:v1, u0:u1], K_box, config)
        kp = np.asarray(keypoints[j], dtype=float) - (u0, v0, 0.0)
        if hand_mesh_o is None:
            hand = hand_mask_from_keypoints(kp[:, :2], kp[:, 2], depth.shape,
                                            config.bone_radius_px)
        else:
            hand = hand_mask(depth.shape, K_box, T_mask, hand_mesh_o, kp, config.bone_radius_px)
        keep = ~grow_mask(hand, config.mask_dilate_px)
        points = cloud_from_depth(depth, K_box, keep)
        if finest > 0:  # every ICP level and score works at or above this resolution
            points = np.asarray(to_pcd(points).voxel_down_sample(finest).points)
        tried, why = [], []
        cost_prop: float | None = None
        for k, (start, T0) in enumerate(pose_starts):
            if k > 0 and config.first_start_suffices:
                rot, move = _correction(model, pose_starts[0][1], T0)
                if rot <= config.same_start_deg and move <= config.same_start_m:
                    break
            r = _from_start(points, model, T0, start, T_prop, config, axis)
            if isinstance(r, str):
                why.append(f"from the {start} pose: {r}" if len(pose_starts) > 1 else r)
                continue
            agree, cost = _scored(depth, K_box, mesh, r.T_c_o, keep, config)
            t = _Tried(r.T_c_o, r.start, r.fitness, r.rmse_m, agree, cost)
            if joints_o is not None:
                ok, far = _hand_agrees([t], T_prop, joints_o, K_box, kp, config)
                why += far
                if not ok:
                    continue
            tried.append(t)
            if config.first_start_suffices and len(pose_starts) > 1 and len(tried) == 1:
                if cost_prop is None:
                    cost_prop = _scored(depth, K_box, mesh, T_prop, keep, config)[1]
                if _verdict(t, cost_prop, config)[0] is None:
                    break  # kept: the other start need not run
        best = min(tried, key=lambda t: (t.cost, -t.agreement), default=None)
        reason = None
        if best is None:
            reason = "not tracked: " + "; ".join(why)
        else:
            if cost_prop is None:
                cost_prop = _scored(depth, K_box, mesh, T_prop, keep, config)[1]
            reason, nums[5, j] = _verdict(best, cost_prop, config)
            if best.agreement >= config.min_agreement:
                reg_T[j], registered[j] = best.T_c_o, True
        reasons.append(reason)
        starts.append(None if reason else best.start)
        if reason is None:
            out_T[j], tracked[j] = best.T_c_o, True
            nums[:5, j] = (*_correction(model, T_prop, best.T_c_o), best.fitness, best.rmse_m,
                           best.agreement)
            last = (int(f), best.T_c_o)
    return ObjectTracking(out_T, tracked, tuple(reasons), tuple(starts), *nums,
                          T_c_o_registered=reg_T, registered=registered)


__all__ = ["ObjectTracking", "TrackObjectConfig", "track_object"]
