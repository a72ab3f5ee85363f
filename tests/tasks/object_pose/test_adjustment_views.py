"""estimate_adjustment with other steady frames (``other_views``): one frame's visible half
of a mug fits a flipped mug as well as the truth; the frames the participant turned it in
tell them apart."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.tasks.core.geometry import inv_T, pose_error
from graspcap.tasks.object_pose.adjustment_steady import spread_frames
from graspcap.tasks.object_pose.estimate_adjustment import PRESETS
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

UPSTREAM = ("load_session", "register_object", "detect_keypoints", "select_steady",
            "reconstruct_hand", "fit_hand")  # fmt: skip


def test_spread_frames_skip_the_reference_and_unposed_frames():
    valid = np.ones(20, bool)
    valid[[7, 19]] = False
    assert spread_frames(valid, 0, 3) == [6, 13, 18]  # evenly over the 17 posed others
    assert spread_frames(valid, 5, 2) == [10, 18]
    assert spread_frames(valid, 0, 0) == []
    assert spread_frames(np.array([True, False]), 0, 3) == []


@pytest.mark.slow
def test_a_mug_half_hidden_by_the_hand_is_registered_with_the_other_views(tmp_path):
    """Rig seed 11 #0 (easy, 40 frames; the build benchmark's mug): from its first steady
    frame alone the mug came out 10-163 deg off from run to run (a flipped or turned mug, ICP
    fitness 0.98, depth agreement 0.92-0.96 < ``views_below_fitness``); with six other
    steady frames 0.5 deg / 0.7 mm (measured)."""
    from graspcap.synth import config_for, generate_session
    from graspcap.synth.evaluate import load_truth

    d = generate_session(tmp_path, [11, 0], config_for("easy", 40))
    res: dict = {}
    for name in UPSTREAM:
        res[name] = run_stage(STAGES[name], d, configs_for()[name], res)
    truth = load_truth(d)
    steady = res["select_steady"].steady_from
    T_true = inv_T(truth["T_w_c"][steady - int(truth["steady_from"])]) @ (
        truth["T_adj"] @ truth["T_w_o_stage1"]
    )
    default = PRESETS["default"]
    single = run_stage(STAGES["estimate_adjustment"], d,
                       default.model_copy(update={"other_views": 0}), res)  # fmt: skip
    # one view: a wrong mug that the depth agrees with too little, or (estimate_adjustment/14:
    # the mug turned about its body's axis, handle hidden, fitness 0.999) an ambiguous one:
    # the views' triggers
    assert single.views == 1 and pose_error(single.T_w_o, T_true)[0] >= 10.0
    assert single.fitness < default.views_below_fitness or single.ambiguous
    adj = run_stage(STAGES["estimate_adjustment"], d, default, res)
    rot, trans = pose_error(adj.T_w_o, T_true)
    assert adj.views == 1 + default.other_views
    assert rot < 1.0 and trans < 0.003, (rot, trans, pose_error(single.T_w_o, T_true))
