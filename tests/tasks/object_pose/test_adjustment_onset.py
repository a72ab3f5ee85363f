"""estimate_adjustment_steady on plain inputs: which steady frame it registers, the later-frame
retry and its pose carried back, the hand mask it passes, without the upstream DAG."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, make_T, rot_z
from graspcap.tasks.object_pose import estimate_adjustment as ea
from graspcap.tasks.object_pose.adjustment_region import hand_mask
from graspcap.tasks.object_pose.adjustment_steady import (
    estimate_adjustment_steady,
    spread_frames,
)

K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
M = 8  # steady frames
T_W_C = np.stack([make_T(rot_z(0.01 * k)[:3, :3], [0.01 * k, 0, 0]) for k in range(M)])
T_W_O1 = make_T(np.eye(3), [0, 0, 0.5])
TRI = (np.array([[0.0, 0, 5], [0.1, 0, 5], [0, 0.1, 5]]), np.array([[0, 1, 2]]))


def _run(monkeypatch, fitness: dict[int, float | None], **config):
    """The stage with the single-frame registration replaced: frame k (its depth is filled
    with k) fits with ``fitness[k]`` (None: raises), T_adj = identity in that frame's camera."""
    calls = []

    def fake(depth, K_, V, F, T_w_o, mask, config, T_w_o_stage1_alt=None, other_views=None):
        k = int(depth[0, 0])
        calls.append((k, mask.shape, T_w_o_stage1_alt))
        if fitness.get(k) is None:
            raise StageError("estimate_adjustment", f"frame {k} fails")
        return ea.Adjustment(np.eye(4), T_w_o, fitness[k], 0.001, 100,
                             ea.AdjustmentPath.STAGE1_ICP, False)

    monkeypatch.setattr(ea, "estimate_adjustment", fake)
    keypoints = np.zeros((M, 21, 3))
    result = estimate_adjustment_steady(
        lambda k: np.full((48, 64), float(k)), K, *TRI, TRI, keypoints, T_W_C,
        np.ones(M, bool), T_W_O1, ea.EstimateAdjustmentConfig(**config),
    )
    return result, [c[0] for c in calls]


def test_a_good_first_frame_is_kept(monkeypatch):
    result, frames = _run(monkeypatch, {0: 0.9, 5: 0.99})
    assert frames == [0] and result.fitness == 0.9
    np.testing.assert_array_equal(result.T_w_o, T_W_O1)


def test_a_weak_first_frame_tries_the_later_one_and_keeps_the_better(monkeypatch):
    result, frames = _run(monkeypatch, {0: 0.6, 5: 0.8})
    assert frames == [0, 5] and result.fitness == 0.8
    np.testing.assert_allclose(result.T_w_o, T_W_C[5] @ T_W_O1)  # carried by frame 5's camera
    np.testing.assert_allclose(result.T_adj, T_W_C[5])
    result, frames = _run(monkeypatch, {0: 0.6, 5: 0.5})
    assert frames == [0, 5] and result.fitness == 0.6


def test_a_failing_first_frame_falls_back_to_the_later_one(monkeypatch):
    result, frames = _run(monkeypatch, {0: None, 3: 0.7}, frames_after_onset=3)
    assert frames == [0, 3] and result.fitness == 0.7
    with pytest.raises(StageError, match="frame 0 fails; registered alone in 7 steady frames"):
        _run(monkeypatch, {0: None}, frames_after_onset=0)


def test_when_every_registration_fails_the_frames_that_agree_alone_decide(monkeypatch):
    """The last resort (``frame_consensus``): each steady frame registered alone, without other
    views and with ``min_points_floor`` pixels enough; three frames whose poses, carried by
    their cameras, agree make the result."""
    calls = []

    def fake(depth, K_, V, F, T_w_o, mask, config, T_w_o_stage1_alt=None, other_views=None):
        k = int(depth[0, 0])
        alone = other_views is None and config.min_points == config.min_points_floor
        calls.append((k, alone))
        if not alone or k not in (2, 4, 6):
            raise StageError("estimate_adjustment", f"frame {k} fails")
        T_c_o = inv_T(T_W_C[k]) @ T_W_O1  # the object where it is, seen from frame k
        return ea.Adjustment(T_c_o @ inv_T(T_w_o), T_c_o, 0.95, 0.001, 50,
                             ea.AdjustmentPath.NEAR_HAND_GLOBAL, False)

    monkeypatch.setattr(ea, "estimate_adjustment", fake)
    result = estimate_adjustment_steady(
        lambda k: np.full((48, 64), float(k)), K, *TRI, TRI, np.zeros((M, 21, 3)), T_W_C,
        np.ones(M, bool), T_W_O1, ea.EstimateAdjustmentConfig(frames_after_onset=3),
    )
    assert calls[:2] == [(0, False), (3, False)]  # the first frame, then the later one
    assert calls[2:] == [(k, True) for k in [0, *spread_frames(np.ones(M, bool), 0, 11)]]
    assert result.path == ea.AdjustmentPath.FRAME_CONSENSUS
    assert result.views == 3 and result.n_points == 150
    np.testing.assert_allclose(result.T_w_o, T_W_O1, atol=1e-12)
    np.testing.assert_allclose(result.T_adj, np.eye(4), atol=1e-12)


def test_the_hand_mask_is_the_rendered_hand_plus_the_keypoint_bones():
    hand_w = (np.array([[-0.05, -0.05, 1], [0.05, -0.05, 1], [0, 0.05, 1]]),
              np.array([[0, 1, 2]]))  # about pixels 27-37 x 19-29
    keypoints = np.zeros((21, 3))
    keypoints[:, :2] = [60, 5]
    keypoints[0] = [60, 5, 1.0]  # one confident keypoint, far from the rendered triangle
    mask = hand_mask((48, 64), K, inv_T(np.eye(4)), hand_w, keypoints, bone_radius_px=2)
    assert mask[24, 32] and mask[5, 60]  # the triangle's centre, the keypoint's disc
    assert not mask[5, 5] and not mask[45, 60] and not mask[24, 45]
    assert mask.sum() < 0.1 * mask.size
