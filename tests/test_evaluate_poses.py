"""Scoring of the pose stages against synthetic truth (``graspcap.synth.evaluate``)."""

from __future__ import annotations

import numpy as np

from graspcap.synth.evaluate import _T_adj_at
from graspcap.tasks.geometry import from_rotvec, inv_T, pose_error


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
