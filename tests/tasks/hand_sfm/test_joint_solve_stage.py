"""The joint_solve stage in the pipeline: ``mode`` picks the path, and reconstruct_hand and
fit_hand pass the joint solve's result on in the staged path's types."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import evaluate
from graspcap.tasks.hand.fit_hand import HandFit
from graspcap.tasks.hand_sfm.joint_solve import HandPath, JointSolve, noisy
from graspcap.tasks.hand_sfm.result import HandReconstruction
from graspcap.tasks.pipeline import STAGES, configs_for, preset_stages, run_stage

CONFIGS = configs_for()


@pytest.fixture(scope="module")
def upstream(tmp_path_factory):
    config = config_for("easy", 40).model_copy(update={"write_steady_from": True})
    session = generate_session(tmp_path_factory.mktemp("joint"), [7, 0], config)
    results: dict = {}
    for name in ("load_session", "detect_keypoints", "select_steady"):
        results[name] = run_stage(STAGES[name], session, CONFIGS[name], results)
    return session, results


def _path(session, upstream, mode: HandPath, **update) -> dict:
    results = dict(upstream)
    config = CONFIGS["joint_solve"].model_copy(update={"mode": mode, **update})
    results["joint_solve"] = run_stage(STAGES["joint_solve"], session, config, results)
    for name in ("reconstruct_hand", "fit_hand"):
        results[name] = run_stage(STAGES[name], session, CONFIGS[name], results)
    return results


def _errors(session, results) -> dict[str, float]:
    rec = results["reconstruct_hand"]
    return evaluate(session, {
        "steady_from": results["select_steady"].steady_from, "joints_w": rec.joints_w,
        "T_w_c": rec.T_w_c, "camera_solved": rec.pose_valid,
        "joints_fit_w": results["fit_hand"].joints_fit_w,
    })  # fmt: skip


def test_the_dag_and_presets():
    assert STAGES["joint_solve"].upstream == ("load_session", "detect_keypoints",
                                              "select_steady")
    assert "joint_solve" in STAGES["reconstruct_hand"].upstream
    assert "joint_solve" in STAGES["fit_hand"].upstream
    assert CONFIGS["joint_solve"].mode is HandPath.AUTO
    assert configs_for("staged")["joint_solve"].mode is HandPath.OFF
    assert configs_for("paper")["joint_solve"].mode is HandPath.OFF
    assert configs_for("joint")["joint_solve"].mode is HandPath.ALWAYS
    assert configs_for("joint_fallback")["joint_solve"].mode is HandPath.FALLBACK
    assert preset_stages("joint") == ("joint_solve",)


def test_modes_pick_the_path(upstream):
    session, results = upstream
    off = _path(session, results, HandPath.OFF)
    assert off["joint_solve"] is None
    assert isinstance(off["reconstruct_hand"], HandReconstruction)

    fallback = _path(session, results, HandPath.FALLBACK)
    js = fallback["joint_solve"]
    assert isinstance(js, JointSolve) and js.path == "staged" and js.staged_error == ""
    assert fallback["reconstruct_hand"] is js.reconstruction and fallback["fit_hand"] is js.fit
    np.testing.assert_allclose(js.reconstruction.joints_w, off["reconstruct_hand"].joints_w)

    joint = _path(session, results, HandPath.ALWAYS)
    js = joint["joint_solve"]
    assert js.path == "joint" and js.start == "staged"
    assert joint["reconstruct_hand"] is js.reconstruction
    assert isinstance(joint["fit_hand"], HandFit) and joint["fit_hand"] is js.fit
    rec = js.reconstruction
    assert rec.frames.tolist() == off["reconstruct_hand"].frames.tolist()
    assert np.allclose(rec.T_w_c[0], np.eye(4))
    assert not js.frame_rejected.any()  # an easy session: every frame is one hand
    errors = _errors(session, joint)
    assert errors["camera_rot_deg"] < 1.0 and errors["camera_trans_mm"] < 5.0
    assert errors["joints_mpjpe_mm"] < 5.0
    assert errors["fit_joints_mm"] == errors["joints_mpjpe_mm"]  # the SfM joints are the hand's
    # downstream stages take the joint result as they take the staged one
    cross = run_stage(STAGES["crosscheck_sfm"], session, CONFIGS["crosscheck_sfm"], joint)
    assert np.isfinite(cross.max_joint_discrepancy_m)


def test_auto_takes_the_staged_result_on_clean_detections_and_the_joint_solve_on_noisy(upstream):
    """``auto`` decides by the noise the staged solve measured: the easy session's detections
    are clean (well under 2.5 % of the hand), so the staged result stands; with a limit below
    any measured noise the same session goes to the joint solve, from the cameras the depth
    surfaces chain (``chain_start``: noisy detections do not start the cameras)."""
    session, results = upstream
    clean = _path(session, results, HandPath.AUTO)["joint_solve"]
    diag = clean.reconstruction.diagnostics
    assert diag.noise_sigma_px < 0.025 * diag.hand_size_px
    assert clean.path == "staged" and clean.staged_error == ""
    strict = _path(session, results, HandPath.AUTO, auto_noise_share=0.0)["joint_solve"]
    assert strict.path == "joint" and strict.start == "chain"
    staged = _path(session, results, HandPath.AUTO, auto_noise_share=0.0,
                   chain_start=False)["joint_solve"]
    assert staged.path == "joint" and staged.start == "staged"


@pytest.mark.parametrize(("sigma", "hand", "share", "expected"), [
    (3.0, 100.0, 0.025, True), (2.0, 100.0, 0.025, False), (2.5, 100.0, 0.025, False),
    (float("nan"), 100.0, 0.025, False), (3.0, float("nan"), 0.025, False),
    (3.0, 0.0, 0.025, False),
])  # fmt: skip
def test_noisy_compares_the_measured_noise_with_the_hand(sigma, hand, share, expected):
    """Unmeasured noise (or hand size) counts as clean: the staged result stands."""
    assert noisy(sigma, hand, share) is expected


def test_the_staged_start_is_the_builds_reconstruct_and_fit_config():
    """joint_solve runs the staged path itself (reconstruct_hand and fit_hand pass its result
    on), so the preset's and ``--set``'s reconstruct_hand and fit_hand configs must be the ones
    it runs, and be in its cache key."""
    from graspcap.flows.build import resolve_configs
    from graspcap.tasks.pipeline import settings_overrides

    openpose = configs_for("openpose")
    assert openpose["reconstruct_hand"] != CONFIGS["reconstruct_hand"]  # else this proves nothing
    assert openpose["joint_solve"].staged == openpose["reconstruct_hand"]
    assert openpose["joint_solve"].fit == openpose["fit_hand"]
    overrides = settings_overrides(["reconstruct_hand.sigma_px=3.5"], "openpose")
    configs = resolve_configs("openpose", overrides)
    assert configs["reconstruct_hand"].sigma_px == 3.5
    assert configs["joint_solve"].staged == configs["reconstruct_hand"]
    assert configs["joint_solve"].canonical_json() != openpose["joint_solve"].canonical_json()


def test_a_chain_start_whose_solve_fails_falls_back_to_the_staged_start(upstream, monkeypatch):
    """A chain that slid can place the hand where no depth reading agrees with it ("no metric
    scale"): the solve is then run once more from the start it would have had without the
    chain, and the session builds."""
    import graspcap.tasks.hand_sfm.joint_solve as js_module
    from graspcap.tasks.hand_sfm.joint_starts import Start

    session, results = upstream

    def slid(*args, **kwargs):
        start = real(*args, **kwargs)
        assert start is not None  # the easy session's surfaces chain
        T_c_p = start.T_c_p.copy()
        T_c_p[:, :3, 3] += [0.0, 0.0, 0.5]  # every camera half a metre off in depth
        return Start(T_c_p, start.angles, start.scale, start.name)

    outcomes: list = []

    def recorded(*args, **kwargs):
        try:
            out = real_solve(*args, **kwargs)
        except js_module.StageError as exc:
            outcomes.append(exc.reason)
            raise
        outcomes.append(out.start)
        return out

    real, real_solve = js_module.chain_start, js_module.solve_from_start
    monkeypatch.setattr(js_module, "chain_start", slid)
    monkeypatch.setattr(js_module, "solve_from_start", recorded)
    solved = _path(session, results, HandPath.AUTO, auto_noise_share=0.0)["joint_solve"]
    assert solved.path == "joint" and solved.start == "staged"
    assert len(outcomes) == 2 and outcomes[1] == "staged"  # the chain's solve failed first
    assert any(w in outcomes[0] for w in ("no metric scale", "implausible", "too few"))


def test_the_depth_refinement_moves_the_noisy_paths_hand_and_nothing_else_when_off(upstream):
    """``depth_refine`` runs where the joint solve's result is used on noisy detections (here
    forced by ``auto_noise_share = 0``): the cameras stay, the hand (pose, scale, angles, the
    joints of the reconstruction and the fit) moves, and the report records it. Disabled, the
    result is the unrefined solve's, the hand the report names as ``joints_w_before``."""
    session, results = upstream
    off_cfg = CONFIGS["joint_solve"].depth_refine.model_copy(update={"enabled": False})
    off = _path(session, results, HandPath.AUTO, auto_noise_share=0.0,
                depth_refine=off_cfg)["joint_solve"]
    on = _path(session, results, HandPath.AUTO, auto_noise_share=0.0)["joint_solve"]
    assert off.path == on.path == "joint" and off.depth_refine is None
    report = on.depth_refine
    assert report is not None and report.kept, report.note
    assert report.points >= CONFIGS["joint_solve"].depth_refine.min_points
    assert np.isfinite(report.offset_m)
    np.testing.assert_allclose(report.joints_w_before, off.fit.joints_fit_w, atol=1e-12)
    np.testing.assert_allclose(on.reconstruction.T_w_c, off.reconstruction.T_w_c, atol=1e-12)
    assert np.array_equal(on.frame_rejected, off.frame_rejected)
    assert not np.allclose(on.fit.joints_fit_w, off.fit.joints_fit_w, atol=1e-5)
    assert not np.allclose(on.fit.angles_rad, off.fit.angles_rad)
    # the refined hand is the result's everywhere the solve's hand was
    np.testing.assert_array_equal(on.reconstruction.joints_w, on.fit.joints_fit_w)
    from graspcap.tasks.hand.model import HandModel

    posed = HandModel(on.fit.side).keypoints(on.fit.angles_rad, on.fit.T_w_p, on.fit.scale,
                                             on.bone_scale)
    np.testing.assert_allclose(posed, on.fit.joints_fit_w, atol=1e-9)
    # the staged result of clean detections does not run it
    assert _path(session, results, HandPath.AUTO)["joint_solve"].depth_refine is None
