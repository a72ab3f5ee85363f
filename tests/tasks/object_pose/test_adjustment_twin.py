"""estimate_adjustment on a carton lifted and turned in the hand: its 180 deg twin explains
nearly every depth point near the hand (fitness 0.99) but not the depth image (agreement
0.91-0.99), so candidates are ranked by fitness times depth agreement, probed again from a
best pose the depth does not fully agree with, and the pose nearest stage 1 wins only among
near-exact ties (realistic session s9400 #5 was 180 deg off, QA failed it by contacts)."""

from __future__ import annotations

import pytest

from graspcap.tasks.core.geometry import pose_error
from graspcap.tasks.object_pose.estimate_adjustment import AdjustmentPath, estimate_adjustment
from tests.registration_rig import K, lifted_procedural

ROT_DEG, TRANS_M = 1.0, 0.003


@pytest.mark.parametrize(
    "seed,angle_deg,ambiguous",
    [
        (1, 60.0, False),  # before: 180 deg off, depth agreement 0.906, not ambiguous
        (3, 120.0, True),  # before: 180 deg off at 0.988 (nearer stage 1), not ambiguous
        (3, 170.0, False),  # before: 180 deg off at 0.966
    ],
)
def test_lifted_carton_is_not_its_twin(seed, angle_deg, ambiguous):
    mesh, T_w_o1, depth, mask, T_true = lifted_procedural("carton", seed, angle_deg)
    asked: list[int] = []
    r = estimate_adjustment(
        depth, K, *mesh, T_w_o1, mask, other_views=lambda *_: asked.append(1) or []
    )
    assert r.path is AdjustmentPath.NEAR_HAND_GLOBAL
    rot, trans = pose_error(r.T_w_o, T_true)
    assert rot <= ROT_DEG and trans <= TRANS_M, (rot, trans)
    assert r.fitness >= 0.99
    assert r.ambiguous is ambiguous
    # other views are asked for when the tie is not the carton's own symmetry: its half turns
    # move the spout and ridge (7-13 % of its surface more than 3 mm), which another view may
    # show (estimate_adjustment/24; before, only with ill-defined principal axes)
    assert bool(asked) is (ambiguous and not r.symmetric_tie)
    assert not r.symmetric_tie


@pytest.mark.slow
def test_realistic_carton_s9000_0_is_not_its_twin(tmp_path):
    """Synth session [9000, 0] (realistic, 120 frames), upstream stages run fresh: every
    RANSAC start was the carton's 180 deg twin at fitness 0.87, a symmetry probe refined one to
    1.0 (depth agreement 0.999) and the probes never turned that new best, so the truth (1.0 x
    1.0) was never a candidate: 179.9 deg / 160 mm off at estimate_adjustment/12."""
    from graspcap.synth import config_for, generate_session
    from graspcap.synth.evaluate import load_truth
    from graspcap.tasks.core.geometry import inv_T
    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

    d = generate_session(tmp_path, [9000, 0], config_for("realistic", 120))
    res: dict = {}
    for name in ("load_session", "register_object", "detect_keypoints", "select_steady",
                 "reconstruct_hand", "fit_hand"):  # fmt: skip
        res[name] = run_stage(STAGES[name], d, configs_for()[name], res)
    truth = load_truth(d)
    i = res["select_steady"].steady_from - int(truth["steady_from"])
    T_true = inv_T(truth["T_w_c"][max(i, 0)]) @ truth["T_adj"] @ truth["T_w_o_stage1"]
    adj = run_stage(STAGES["estimate_adjustment"], d, configs_for()["estimate_adjustment"], res)
    rot, trans = pose_error(inv_T(res["reconstruct_hand"].T_w_c[0]) @ adj.T_w_o, T_true)
    assert rot <= ROT_DEG and trans <= TRANS_M, (rot, trans)
    assert adj.fitness >= 0.99
