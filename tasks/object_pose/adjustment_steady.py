"""estimate_adjustment over the steady frames: which frame is registered (the first, else
the one ``frames_after_onset`` later when the first fails or fits poorly), and which other
steady frames it is offered (:class:`.SteadyView`, evenly spread over the posed ones), each
carried into the registered frame by ``reconstruct_hand``'s virtual cameras. The registration
itself is :func:`.estimate_adjustment.estimate_adjustment`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.object_pose import estimate_adjustment as ea
from graspcap.tasks.object_pose.adjustment_region import hand_mask
from graspcap.tasks.object_pose.estimate_adjustment import (
    PRESETS,
    Adjustment,
    EstimateAdjustmentConfig,
    SteadyView,
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
    carried back by that frame's virtual camera; the better fit is kept.

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

    def attempt(k: int) -> Adjustment:
        depth, mask = view(k)

        def others(count: int) -> list[SteadyView]:
            return [SteadyView(*view(j), inv_T(T_w_c[k]) @ T_w_c[j])
                    for j in spread_frames(pose_valid, k, count)]

        adj = ea.estimate_adjustment(
            depth, K, mesh_vertices, mesh_faces, T_w_o_stage1, mask, config,
            T_w_o_stage1_alt=T_w_o_stage1_alt, other_views=others,
        )
        return replace(adj, T_adj=T_w_c[k] @ adj.T_adj, T_w_o=T_w_c[k] @ adj.T_w_o)

    k = min(config.frames_after_onset, len(T_w_c) - 1)
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
