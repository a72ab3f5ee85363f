"""estimate_adjustment over the steady frames: which frame is registered (the first, else
the one ``frames_after_onset`` later when the first fails or fits poorly), and which other
steady frames it is offered (:class:`.SteadyView`, evenly spread over the posed ones), each
carried into the registered frame by ``reconstruct_hand``'s virtual cameras. The registration
itself is :func:`.estimate_adjustment.estimate_adjustment`. Where every one of those refuses,
the last resort is :func:`frame_consensus`: the object registered in several steady frames
alone, and a pose that three of them find independently kept.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.object_pose import estimate_adjustment as ea
from graspcap.tasks.object_pose.adjustment_region import hand_mask
from graspcap.tasks.object_pose.estimate_adjustment import (
    PRESETS,
    Adjustment,
    EstimateAdjustmentConfig,
    SteadyView,
)
from graspcap.tasks.object_pose.registration.engine import (
    Model,
    prepare_model,
    strided,
    surface_distance,
)


def spread_frames(pose_valid: np.ndarray, ref: int, count: int) -> list[int]:
    """Up to ``count`` frames other than ``ref``, evenly spread over the posed ones (``pose_valid``
    (m,) bool), the last posed frame included: the views of :class:`SteadyView`."""
    posed = np.flatnonzero(np.asarray(pose_valid, bool))
    posed = posed[posed != ref]
    if count <= 0 or len(posed) == 0:
        return []
    pick = np.unique(np.round(np.linspace(0, len(posed) - 1, count + 1)[1:]).astype(int))
    return [int(posed[i]) for i in pick]


def estimate_adjustment_steady(
    read_depth: Callable[[int], np.ndarray],
    K: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    hand_mesh_w: tuple[np.ndarray, np.ndarray],
    keypoints: np.ndarray,
    T_w_c: np.ndarray,
    pose_valid: np.ndarray,
    T_w_o_stage1: np.ndarray,
    config: EstimateAdjustmentConfig = PRESETS["default"],
    T_w_o_stage1_alt: np.ndarray | None = None,
) -> Adjustment:
    """The stage on the steady frames: :func:`.estimate_adjustment` on the first steady frame's
    depth with the hand masked out (:func:`adjustment_region.hand_mask`). When that fails or
    fits below ``config.accept_fitness`` (the onset is often detected a few frames early, while
    the object still settles), also on the frame ``config.frames_after_onset`` later, its pose
    carried back by that frame's virtual camera; the better fit is kept. When both fail, the
    pose several steady frames find alone (:func:`frame_consensus`: a small object inside the
    fist shows too few pixels in any one frame).

    Parameters
    ----------
    read_depth : steady frame k -> its depth (h, w) float, metres.
    hand_mesh_w : the fitted hand (vertices (n, 3) in the world, faces (f, 3)).
    keypoints : (m, 21, 3) float, the steady frames' keypoints (pixels, confidence).
    T_w_c : (m, 4, 4) the steady frames' cameras; the world is steady frame 0's camera.
    pose_valid : (m,) bool, frames whose camera was solved.
    T_w_o_stage1, T_w_o_stage1_alt : ``register_object``'s pose and, when it is ambiguous, its
        runner-up.
    """

    def view(k: int) -> tuple[np.ndarray, np.ndarray]:
        depth = read_depth(k)
        return depth, hand_mask(depth.shape, K, inv_T(T_w_c[k]), hand_mesh_w, keypoints[k])

    def attempt(k: int, cfg: EstimateAdjustmentConfig = config, fused: bool = True
                ) -> Adjustment:
        depth, mask = view(k)

        def others(count: int) -> list[SteadyView]:
            return [SteadyView(*view(j), inv_T(T_w_c[k]) @ T_w_c[j])
                    for j in spread_frames(pose_valid, k, count)]

        adj = ea.estimate_adjustment(
            depth, K, mesh_vertices, mesh_faces, T_w_o_stage1, mask, cfg,
            T_w_o_stage1_alt=T_w_o_stage1_alt, other_views=others if fused else None,
        )
        return replace(adj, T_adj=T_w_c[k] @ adj.T_adj, T_w_o=T_w_c[k] @ adj.T_w_o)

    alone = config.model_copy(update={"min_points": config.min_points_floor})  # a few pixels
    try:
        return _registered(attempt, pose_valid, config)
    except StageError as failed:
        if config.consensus_views <= 0:
            raise
        frames = [0, *spread_frames(pose_valid, 0, config.consensus_views)]
        model = prepare_model(mesh_vertices, mesh_faces, config.registration)
        try:
            return frame_consensus(lambda k: attempt(k, alone, fused=False), frames, model,
                                   config)
        except StageError as e:
            raise StageError(ea.STAGE, f"{failed.reason}; {e.reason}") from None


def _registered(attempt: Callable[[int], Adjustment], pose_valid: np.ndarray,
                config: EstimateAdjustmentConfig) -> Adjustment:
    """The first steady frame's registration, or the one ``frames_after_onset`` later where the
    first fails or fits below ``accept_fitness`` (the better fit)."""
    k = min(config.frames_after_onset, len(pose_valid) - 1)
    try:
        first = attempt(0)
    except StageError:
        if k == 0 or not pose_valid[k]:
            raise
        return attempt(k)
    if first.fitness >= config.accept_fitness or k == 0 or not pose_valid[k]:
        return first
    try:
        later = attempt(k)
    except StageError:
        return first
    return later if later.fitness > first.fitness else first


def pose_gap_m(model: Model, T_a: np.ndarray, T_b: np.ndarray, points: int = 400) -> float:
    """How far apart two poses (4, 4) put the object: the mean distance from its surface at
    ``T_a`` to its surface at ``T_b`` (``points`` samples), the larger of the two directions.
    Poses the shape is symmetric under are 0 apart."""
    pts = np.asarray(strided(model.coarse, points).points)
    there = [surface_distance(model, transform_points(inv_T(U) @ T, pts)).mean()
             for T, U in ((T_a, T_b), (T_b, T_a))]
    return float(max(there))


def frame_consensus(
    register: Callable[[int], Adjustment], frames: list[int], model: Model,
    config: EstimateAdjustmentConfig,
) -> Adjustment:
    """The pose that ``config.consensus_min_frames`` steady frames find independently:
    ``register(k)`` registers the object in frame ``k`` alone (its pose carried into the first
    steady frame), for each of ``frames``; those fitting at least ``consensus_min_fitness``
    vote, two agreeing within ``consensus_m`` (:func:`pose_gap_m`). The pose with the most
    frames agreeing with it (ties: more judged pixels, then the earlier frame) is kept, its
    ``n_points`` the agreeing frames' pixels, ``views`` their number. Raises ``StageError``
    when no pose gathers enough frames."""
    found: list[tuple[int, Adjustment]] = []
    for k in frames:
        try:
            adj = register(k)
        except StageError:
            continue
        if adj.fitness >= config.consensus_min_fitness:
            found.append((k, adj))
    near = np.eye(len(found), dtype=bool)  # each pair's gap measured once
    for i, j in zip(*np.triu_indices(len(found), 1), strict=True):
        near[i, j] = near[j, i] = (
            pose_gap_m(model, found[i][1].T_w_o, found[j][1].T_w_o) <= config.consensus_m)
    best: tuple[tuple[int, int, int], Adjustment] | None = None
    for (k, adj), row in zip(found, near, strict=True):
        agree = [a for (_, a), close in zip(found, row, strict=True) if close]
        rank = (len(agree), sum(a.n_points for a in agree), -k)
        if best is None or rank > best[0]:
            best = (rank, replace(adj, path=ea.AdjustmentPath.FRAME_CONSENSUS, views=len(agree),
                                  n_points=rank[1]))
    if best is None or best[0][0] < config.consensus_min_frames:
        most = 0 if best is None else best[0][0]
        raise StageError(ea.STAGE, f"registered alone in {len(frames)} steady frames, {len(found)} "
                                   f"fit; at most {most} agree on a pose (need "
                                   f"{config.consensus_min_frames})")
    return best[1]
