"""Scoring of the pose stages against synthetic truth (``graspcap.synth.evaluate``)."""

from __future__ import annotations

import numpy as np

from graspcap.synth.evaluate import _anchor, _camera_errors, _mpjpe_mm, _T_adj_at
from graspcap.tasks.core.geometry import from_rotvec, inv_T, pose_error


def test_T_adj_truth_follows_the_detected_steady_frame():
    """The pipeline registers the object in the frame it was given as the first steady one;
    after the true onset the object moves with the hand, so the truth it is scored against
    must be the object's pose in that frame (not the onset's), before the onset the onset's."""
    rng = np.random.default_rng(0)
    T_w_c = np.stack([np.eye(4)] + [from_rotvec(rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3))
                                    for _ in range(5)])  # fmt: skip
    truth = {"steady_from": 10, "T_w_c": T_w_c,
             "T_adj": from_rotvec(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.1, -0.2])),
             "T_w_o_stage1": from_rotvec(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 0.7]))}
    for s in (8, 10):
        np.testing.assert_allclose(_T_adj_at(truth, s), truth["T_adj"])
    T_obj_12 = inv_T(T_w_c[2]) @ truth["T_adj"] @ truth["T_w_o_stage1"]  # object in camera 12
    np.testing.assert_allclose(_T_adj_at(truth, 12) @ truth["T_w_o_stage1"], T_obj_12,
                               atol=1e-12)  # fmt: skip
    assert pose_error(_T_adj_at(truth, 12), truth["T_adj"])[0] > 1.0


def test_cameras_are_compared_from_a_camera_the_estimate_solved():
    """A first steady frame without detections gets an interpolated camera (a fill, several
    degrees off when the camera moves between frames); scored against it every camera would
    carry its error. The comparison starts at the next camera the estimate solved."""
    rng = np.random.default_rng(1)
    T_w_c = np.stack([np.eye(4)] + [from_rotvec(rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3))
                                    for _ in range(7)])  # fmt: skip
    truth = {"steady_from": 20, "T_w_c": T_w_c, "joints_w": rng.normal(0, 0.05, (21, 3))
             + [0.0, 0.0, 0.5]}  # fmt: skip
    # the estimate found the onset one frame early (19, its own world); frame 20 has no pose
    T_19 = from_rotvec(np.array([0.0, 0.05, 0.0]), np.array([0.01, 0.0, 0.0]))  # truth's cam 19
    est = np.concatenate([[np.eye(4)], np.einsum("ij,njk->nik", inv_T(T_19), T_w_c)])
    est[1] = est[1] @ from_rotvec(np.array([0.07, 0.0, 0.0]), np.zeros(3))  # 4 deg fill
    joints = (inv_T(T_19) @ np.c_[truth["joints_w"], np.ones(21)].T).T[:, :3]
    solved = np.ones(len(est), dtype=bool)
    solved[1] = False
    at = _anchor(19, 20, len(est), solved)
    assert at == 21
    cams = _camera_errors(est, 19, truth, at)
    assert len(cams) == 7 and cams.max() < 1e-9
    assert _mpjpe_mm(joints, est, 19, truth, at) < 1e-9
    at_fill = _anchor(19, 20, len(est), None)  # without the flags: frame 20, the fill
    assert at_fill == 20
    assert np.median(_camera_errors(est, 19, truth, at_fill)[:, 0]) > 3.5
