"""propagate_poses: the paper's formulas, consistency of the 3D and 2D joints, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import from_rotvec, inv_T, make_T, project, transform_points
from graspcap.tasks.hand.model import HandModel
from graspcap.tasks.outputs.propagate_poses import (
    PRESETS,
    JointSource,
    PropagatePosesConfig,
    propagate_poses,
)

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])


def scene(rng: np.random.Generator, m: int = 12):
    """Static hand about 0.5 m in front of the first camera; cameras orbiting it a little."""
    T_w_p = from_rotvec(rng.normal(scale=0.5, size=3), [0.02, -0.01, 0.5])
    model = HandModel()
    angles = rng.uniform(model.lower_rad, model.upper_rad) * 0.5
    joints_w = model.keypoints(angles, T_w_p, 1.05)
    centre = joints_w.mean(axis=0)
    T_w_c = [np.eye(4)]
    for _ in range(m - 1):
        # turn the camera about the hand's centre by up to ~25 degrees
        R = from_rotvec(rng.normal(scale=0.25, size=3), np.zeros(3))
        T_w_c.append(make_T(np.eye(3), centre) @ R @ make_T(np.eye(3), -centre))
    T_w_c = np.stack(T_w_c)
    T_adj = from_rotvec(rng.normal(scale=0.05, size=3), rng.normal(scale=0.01, size=3))
    T_w_o = from_rotvec(rng.normal(size=3), [0.0, 0.05, 0.55])
    return dict(
        T_w_c=T_w_c, T_adj=T_adj, T_w_o_stage1=T_w_o, T_w_p=T_w_p, joints_w=joints_w, K=K,
        frame_indices=np.arange(40, 40 + m),
    )  # fmt: skip


def test_identity_cameras_give_the_world_poses():
    rng = np.random.default_rng(20)
    s = scene(rng, m=3)
    s["T_w_c"] = np.repeat(np.eye(4)[None], 3, axis=0)
    out = propagate_poses(**s)
    for i in range(3):
        np.testing.assert_allclose(out.T_c_o[i], s["T_adj"] @ s["T_w_o_stage1"], atol=1e-12)
        np.testing.assert_allclose(out.T_c_p[i], s["T_w_p"], atol=1e-12)
        np.testing.assert_allclose(out.joints_c[i], s["joints_w"], atol=1e-12)
    np.testing.assert_array_equal(out.frame_indices, s["frame_indices"])
    assert np.all(np.isnan(out.reproj_err_px)) and np.isnan(out.reproj_rmse_px)


def test_consistency_of_poses_joints_and_pixels():
    rng = np.random.default_rng(21)
    s = scene(rng)
    out = propagate_poses(**s)
    m = len(s["T_w_c"])
    assert out.T_c_o.shape == out.T_c_p.shape == (m, 4, 4)
    assert out.joints_c.shape == (m, 21, 3) and out.joints_2d_px.shape == (m, 21, 2)
    assert out.n_behind == 0
    joints_p = transform_points(inv_T(s["T_w_p"]), s["joints_w"])
    for i in range(m):
        np.testing.assert_allclose(
            project(K, out.joints_c[i]), out.joints_2d_px[i], rtol=0, atol=1e-9
        )
        # palm-frame joints are the same in every frame
        np.testing.assert_allclose(
            transform_points(inv_T(out.T_c_p[i]), out.joints_c[i]), joints_p, atol=1e-12
        )
        # the object's pose relative to the palm does not depend on the frame
        np.testing.assert_allclose(
            inv_T(out.T_c_p[i]) @ out.T_c_o[i],
            inv_T(s["T_w_p"]) @ s["T_adj"] @ s["T_w_o_stage1"],
            atol=1e-12,
        )
    # the cameras do move: the pixels differ between frames by more than 10 px somewhere
    assert np.abs(out.joints_2d_px[1:] - out.joints_2d_px[0]).max() > 10.0


def test_vectorised_equals_per_frame_loop():
    rng = np.random.default_rng(22)
    s = scene(rng, m=9)
    obs = np.concatenate([rng.uniform(0, 640, (9, 21, 2)), rng.uniform(0, 1, (9, 21, 1))], 2)
    out = propagate_poses(**s, keypoints_2d=obs)
    for i, T_w_c in enumerate(s["T_w_c"]):
        T_c_w = inv_T(T_w_c)
        np.testing.assert_allclose(out.T_c_o[i], T_c_w @ s["T_adj"] @ s["T_w_o_stage1"], atol=1e-12)
        np.testing.assert_allclose(out.T_c_p[i], T_c_w @ s["T_w_p"], atol=1e-12)
        joints_c = transform_points(T_c_w, s["joints_w"])
        np.testing.assert_allclose(out.joints_c[i], joints_c, atol=1e-12)
        err = np.linalg.norm(project(K, joints_c) - obs[i, :, :2], axis=1)
        np.testing.assert_allclose(out.reproj_err_px[i], err, atol=1e-9)


def test_reprojection_error_against_observations():
    rng = np.random.default_rng(23)
    s = scene(rng, m=6)
    clean = propagate_poses(**s).joints_2d_px
    offset = rng.normal(scale=2.0, size=clean.shape)
    obs = np.concatenate([clean + offset, np.ones((6, 21, 1))], axis=2)
    obs[0, 3, 2] = 0.0  # not detected
    obs[1, 4, :2] = np.nan  # not detected, NaN pixels
    obs[2, 5, 2] = 0.2  # detected with low confidence
    out = propagate_poses(**s, keypoints_2d=obs)
    expected = np.linalg.norm(offset, axis=2)
    expected[0, 3] = expected[1, 4] = np.nan
    np.testing.assert_allclose(out.reproj_err_px, expected, atol=1e-9)
    finite = expected[np.isfinite(expected)]
    assert out.reproj_rmse_px == pytest.approx(np.sqrt(np.mean(finite**2)), rel=1e-12)
    strict = propagate_poses(**s, keypoints_2d=obs, config=PropagatePosesConfig(min_confidence=0.3))
    assert np.isnan(strict.reproj_err_px[2, 5])
    assert np.isfinite(strict.reproj_err_px).sum() == 6 * 21 - 3


def test_fitted_joints_source_and_points_behind():
    rng = np.random.default_rng(24)
    s = scene(rng, m=4)
    fitted = s["joints_w"] + 0.003
    out = propagate_poses(**s, joints_fit_w=fitted, config=PRESETS["fitted"])
    assert PRESETS["fitted"].joints is JointSource.FIT
    np.testing.assert_allclose(out.joints_c[0], fitted, atol=1e-12)  # T_w_c[0] = I
    with pytest.raises(StageError, match="joints_fit_w"):
        propagate_poses(**s, config=PRESETS["fitted"])
    s["T_w_c"][2] = make_T(np.eye(3), [0.0, 0.0, 1.0])  # camera beyond the hand
    out = propagate_poses(**s)
    assert out.n_behind == 21 and np.all(np.isnan(out.joints_2d_px[2]))
    assert np.all(np.isfinite(out.joints_2d_px[[0, 1, 3]]))


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("T_adj", np.diag([1.0, 1.0, -1.0, 1.0]), "T_adj .*reflection"),
        ("T_w_p", np.full((4, 4), np.nan), "T_w_p .*NaN"),
        ("T_w_c", np.eye(4), r"\(m, 4, 4\)"),
        ("joints_w", np.zeros((20, 3)), "joints_w"),
        ("frame_indices", np.arange(3.0), "frame_indices"),
        ("K", np.eye(2), "K must"),
    ],
)
def test_bad_inputs_raise_stage_error(field, value, match):
    s = scene(np.random.default_rng(25), m=3)
    s[field] = value
    with pytest.raises(StageError, match=match):
        propagate_poses(**s)


def test_a_bad_camera_is_named():
    s = scene(np.random.default_rng(26), m=5)
    s["T_w_c"][3, :3, :3] *= 1.1
    with pytest.raises(StageError, match=r"T_w_c\[3\].*orthonormal.*1 of 5"):
        propagate_poses(**s)
    s = scene(np.random.default_rng(26), m=5)
    with pytest.raises(StageError, match="keypoints_2d"):
        propagate_poses(**s, keypoints_2d=np.zeros((4, 21, 3)))
