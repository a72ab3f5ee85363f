"""The object stages on wild sessions (issue 19, item 4): a can mostly hidden by the hand at
0.8 m from a Kinect v2-like camera, a symmetric object reported ambiguous.

The sessions are the wild profile with the real-detector keypoint model off (``bench/
object_stages.py``'s ``wild-nodet``), and estimate_adjustment is handed the written truth
upstream (onset, virtual cameras, the hand fitted to the true joints): the test is about the
object stages, not stage 2. Poses of a near-symmetric object are compared by ADD-S (the mean
distance of the posed model's points to the nearest of the true pose's), and its axis.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from graspcap.synth import PRESETS, SynthConfig, generate_session
from graspcap.synth.evaluate import load_truth
from graspcap.tasks.hand import fit_hand
from graspcap.tasks.hand.model import HandSide
from graspcap.tasks.object_pose.adjustment_steady import estimate_adjustment_steady
from graspcap.tasks.pipeline import STAGES, _ideal_keypoints, configs_for, run_stage

pytestmark = pytest.mark.slow


def _wild_session(out, seed, frames=40):
    config = SynthConfig.model_validate(
        {**PRESETS["wild"].model_dump(), "detector": None, "frames": frames}
    )
    d = generate_session(out, seed, config)
    return d, run_stage(STAGES["load_session"], d, configs_for()["load_session"], {})


def _adds_mm(V, T_est, T_true):
    pts = V[:: max(1, len(V) // 2000)]
    a = pts @ T_est[:3, :3].T + T_est[:3, 3]
    b = pts @ T_true[:3, :3].T + T_true[:3, 3]
    return 1e3 * float(cKDTree(b).query(a)[0].mean())


def _axis_deg(T_est, T_true):
    """Angle between the object's z axes (a can's or bulb's axis), either way up."""
    return float(np.degrees(np.arccos(min(1.0, abs(T_est[:3, 2] @ T_true[:3, 2])))))


@pytest.fixture(scope="module")
def occluded_can(tmp_path_factory):
    """Wild [9700, 1]: a 135 mm can at 0.81 m (960x540 Kinect colour), 60 % of its pixels
    behind the hand in the first steady frame. Before this change estimate_adjustment
    stopped on it ("object not found near the hand": the flying pixels joined the can to
    the scene behind it, 15 points kept of the 4100 on the can)."""
    return _wild_session(tmp_path_factory.mktemp("wild_can"), [9700, 1])


def test_a_can_mostly_inside_the_hand_at_0_8_m_is_registered(occluded_can):
    d, session = occluded_can
    truth = load_truth(d)
    V, F = session.read_mesh()
    stage1 = run_stage(STAGES["register_object"], d, configs_for()["register_object"],
                       {"load_session": session})
    s, T_w_c = int(truth["steady_from"]), truth["T_w_c"]
    hand = fit_hand.fit_hand(truth["joints_w"], HandSide(session.manifest.hand),
                             configs_for()["fit_hand"]).mesh()
    kp = np.load(d / "ground_truth" / "keypoints_clean.npy")[s : s + len(T_w_c)]
    kp = _ideal_keypoints(session, np.concatenate([kp, np.ones((*kp.shape[:-1], 1))], -1))
    adj = estimate_adjustment_steady(
        lambda k: session.read_depth_m(session.grasp_path("depth", s + k)), session.color_K,
        V, F, (hand.vertices, hand.faces), kp, T_w_c, np.ones(len(T_w_c), bool),
        stage1.T_w_o, configs_for()["estimate_adjustment"],
        T_w_o_stage1_alt=stage1.second_hypothesis,
    )
    T_true = truth["T_adj"] @ truth["T_w_o_stage1"]
    assert _adds_mm(V, adj.T_w_o, T_true) <= 4.0
    assert _axis_deg(adj.T_w_o, T_true) <= 3.0
    # a can's turn about its axis shows only in a 1.2 mm pull tab: never silently chosen
    assert adj.ambiguous


def test_a_can_on_the_turntable_is_reported_ambiguous(occluded_can):
    d, session = occluded_can
    truth = load_truth(d)
    V, _ = session.read_mesh()
    r = run_stage(STAGES["register_object"], d, configs_for()["register_object"],
                  {"load_session": session})
    assert r.ambiguous
    assert _adds_mm(V, r.T_w_o, truth["T_w_o_stage1"]) <= 4.0
    assert _axis_deg(r.T_w_o, truth["T_w_o_stage1"]) <= 3.0
    scan = run_stage(STAGES["register_scan"], d, configs_for()["register_scan"],
                     {"load_session": session})
    assert scan.ambiguous
    assert _adds_mm(V, scan.T_turntable_o_scan, truth["T_turntable_o_scan"]) <= 4.0
    assert _axis_deg(scan.T_turntable_o_scan, truth["T_turntable_o_scan"]) <= 3.0
