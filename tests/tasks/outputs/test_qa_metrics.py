"""qa_metrics: every limit flips the verdict with its reason; hand-object metrics measured on
a box and a pyramid whose penetration and contact are known by construction."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from graspcap.tasks.hand.surface import contact_agreement
from graspcap.tasks.outputs.qa_metrics import (
    METRICS,
    PRESETS,
    QaMetricsConfig,
    Verdict,
    qa_metrics,
    window_outlier_share,
)

HALF_M = 0.05  # the object: a 10 cm cube, top face at z = 0.05


def object_mesh() -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=(2 * HALF_M,) * 3)
    V, F = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.004)
    return np.asarray(V, float), np.asarray(F, np.int64)


def pyramid(depth_m: float, x_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A 'hand': a square pyramid, apex down ``depth_m`` into the top face at x = ``x_m``."""
    top = HALF_M - depth_m
    V = np.array([[x_m, 0, top], [x_m - .01, -.01, top + .02], [x_m + .01, -.01, top + .02],
                  [x_m + .01, .01, top + .02], [x_m - .01, .01, top + .02]])
    F = np.array([[0, 2, 1], [0, 3, 2], [0, 4, 3], [0, 1, 4], [1, 2, 3], [1, 3, 4]])
    return V, F


def near_hand(V: np.ndarray, hand: tuple[np.ndarray, np.ndarray], mm: float) -> np.ndarray:
    """Object vertices within ``mm`` of the hand surface (trimesh, independent of Open3D)."""
    _, dist, _ = trimesh.proximity.closest_point(trimesh.Trimesh(*hand, process=False), V)
    return dist * 1000.0 <= mm


def good_results(V: np.ndarray, contact: np.ndarray | None = None) -> dict:
    """Stage results of a session that passes every default limit."""
    observed = V[:, 2] > -HALF_M + 1e-6  # the face it stood on is unobserved
    contact = np.zeros(len(V)) if contact is None else contact
    return {
        "reconstruct_hand": SimpleNamespace(reproj_rmse_px=2.0, inlier_ratio=0.95,
                                            inlier=np.ones((20, 21), bool),
                                            residuals_px=np.ones((20, 21))),
        "crosscheck_sfm": SimpleNamespace(max_joint_discrepancy_m=0.0002,
                                          max_camera_rotation_deg=0.01,
                                          max_rgbd_joint_discrepancy_m=0.004, flagged=False,
                                          reason=""),
        "register_object": SimpleNamespace(fitness=0.99, inlier_rmse_m=0.001, ambiguous=False),
        "estimate_adjustment": SimpleNamespace(
            fitness=0.99, inlier_rmse_m=0.001, ambiguous=False,
            average=SimpleNamespace(T_w_o=np.eye(4), spread_deg=0.3, reason=None)),
        "register_scan": SimpleNamespace(fitness=0.99, inlier_rmse_m=0.001, ambiguous=False),
        "fit_hand": SimpleNamespace(rmse_mm=2.0),
        "propagate_poses": SimpleNamespace(n_behind=0),
        "build_contactmap": SimpleNamespace(contact=contact, observed=observed,
                                            coverage=float(observed.mean()), all_ambient=False,
                                            n_degenerate_faces=0),
    }


@pytest.fixture(scope="module")
def scene():
    V, F = object_mesh()
    hand = pyramid(0.0005)
    contact = near_hand(V, hand, 2.0).astype(float)
    return V, F, hand, contact


def run(results, scene, config=PRESETS["default"], hand=None):
    V, F, default_hand, _ = scene
    return qa_metrics(results, config, object_mesh=(V, F), hand_mesh_o=hand or default_hand)


def test_a_good_session_is_ok_with_every_metric(scene):
    V, F, hand, contact = scene
    report = run(good_results(V, contact), scene)
    assert report.verdict == Verdict.OK, report.summary()
    assert report.reasons == () and report.error is None
    assert set(report.metrics) == set(METRICS) and report.missing == {}
    assert report.metrics["penetration_max_mm"] == pytest.approx(0.5, abs=0.05)
    assert report.metrics["penetration_mean_mm"] == pytest.approx(0.5, abs=0.05)  # apex only
    assert report.metrics["contact_agreement"] == pytest.approx(1.0)
    # vertices within 3 mm of the hand, contacted where within 2 mm (both by trimesh)
    near3 = near_hand(V, hand, 3.0) & good_results(V)["build_contactmap"].observed
    expected = contact[near3].mean()
    assert 0.2 < expected < 0.9
    assert report.metrics["hand_contact_agreement"] == pytest.approx(expected, abs=0.03)
    assert report.metrics["reproj_rmse_px"] == 2.0 and report.metrics["crosscheck_mm"] == 0.2


# (metric, stage, attribute, factor from the metric's unit to the attribute's)
READ_OFF = [
    ("reproj_rmse_px", "reconstruct_hand", "reproj_rmse_px", 1.0),
    ("inlier_ratio", "reconstruct_hand", "inlier_ratio", 1.0),
    ("crosscheck_mm", "crosscheck_sfm", "max_joint_discrepancy_m", 1e-3),
    ("crosscheck_camera_deg", "crosscheck_sfm", "max_camera_rotation_deg", 1.0),
    ("rgbd_discrepancy_mm", "crosscheck_sfm", "max_rgbd_joint_discrepancy_m", 1e-3),
    ("registration_fitness", "register_object", "fitness", 1.0),
    ("registration_rmse_mm", "register_object", "inlier_rmse_m", 1e-3),
    ("adjustment_fitness", "estimate_adjustment", "fitness", 1.0),
    ("adjustment_rmse_mm", "estimate_adjustment", "inlier_rmse_m", 1e-3),
    ("scan_fitness", "register_scan", "fitness", 1.0),
    ("scan_rmse_mm", "register_scan", "inlier_rmse_m", 1e-3),
    ("fit_residual_mm", "fit_hand", "rmse_mm", 1.0),
    ("contact_coverage", "build_contactmap", "coverage", 1.0),
]


def _beyond(limit: float, name: str, margin: float) -> float:
    return limit * (1 + margin) if METRICS[name].higher_is_worse else limit * (1 - margin)


@pytest.mark.parametrize("preset", ["default", "strict"])
@pytest.mark.parametrize("name, stage, attr, factor", READ_OFF)
def test_each_limit_flips_the_verdict_with_its_reason(scene, preset, name, stage, attr, factor):
    V, F, hand, contact = scene
    config = PRESETS[preset]
    bound = getattr(config, name)
    label = METRICS[name].label
    op = ">" if METRICS[name].higher_is_worse else "<"
    for level, limit, verdict in (("flag", bound.flag, Verdict.FLAGGED),
                                  ("fail", bound.fail, Verdict.FAILED)):
        if limit is None:  # fit_residual_mm has no flag (a model misfit is not evidence)
            assert name == "fit_residual_mm" and level == "flag"
            continue
        results = good_results(V, contact)
        inside = _beyond(limit, name, -0.02)  # just on the good side: no effect
        setattr(results[stage], attr, inside * factor)
        if level == "flag":
            assert run(results, scene, config).verdict == Verdict.OK, (name, inside)
        value = _beyond(limit, name, 0.05)
        setattr(results[stage], attr, value * factor)
        report = run(results, scene, config)
        assert report.verdict == verdict, report.summary()
        reasons = report.failures if level == "fail" else report.flags
        spec = METRICS[name]
        assert reasons == (f"{label} {value:.2f}{' ' + spec.unit if spec.unit else ''} {op} "
                           f"{limit:.2f}{' ' + spec.unit if spec.unit else ''}",)
        if level == "fail":
            assert report.error.startswith("qa_metrics: ") and label in report.error


@pytest.mark.parametrize("preset", ["default", "strict", "lenient"])
def test_window_outlier_limits_flip_the_verdict(scene, preset):
    V, F, hand, contact = scene
    config = PRESETS[preset]
    bound = config.window_outlier_share
    k = config.outlier_window_frames
    for limit, verdict in ((bound.flag, Verdict.FLAGGED), (bound.fail, Verdict.FAILED)):
        for n_out, expected in ((int(np.floor(0.97 * limit * k * 21)), None),
                                (int(np.ceil(1.03 * limit * k * 21)), verdict)):
            results = good_results(V, contact)
            inlier = np.ones((20, 21), bool)
            inlier[5:5 + k].reshape(-1)[:n_out] = False
            results["reconstruct_hand"].inlier = inlier
            report = run(results, scene, config)
            share = n_out / (k * 21)
            assert report.metrics["window_outlier_share"] == pytest.approx(share)
            if expected is None:
                assert report.verdict in ((Verdict.OK,) if verdict == Verdict.FLAGGED
                                          else (Verdict.FLAGGED,)), report.summary()
                continue
            assert report.verdict == expected
            reason = (f"keypoint outliers in the worst frame window {share:.2f} > "
                      f"{limit:.2f}")
            assert reason in (report.failures if expected == Verdict.FAILED else report.flags)


def test_limits_come_from_the_preset(scene):
    V, F, hand, contact = scene
    results = good_results(V, contact)
    results["reconstruct_hand"].reproj_rmse_px = 5.0  # between strict's and default's flag
    assert PRESETS["strict"].reproj_rmse_px.flag < 5.0 < PRESETS["default"].reproj_rmse_px.flag
    assert run(results, scene, PRESETS["default"]).verdict == Verdict.OK
    assert run(results, scene, PRESETS["strict"]).verdict == Verdict.FLAGGED
    results["reconstruct_hand"].reproj_rmse_px = 10.0
    assert run(results, scene, PRESETS["default"]).verdict == Verdict.FAILED
    assert run(results, scene, PRESETS["lenient"]).verdict == Verdict.FLAGGED
    custom = QaMetricsConfig(reproj_rmse_px={"flag": None, "fail": None})
    assert run(results, scene, custom).verdict == Verdict.OK


def test_penetration_limits(scene):
    V, F, _, contact = scene
    config = PRESETS["default"]
    flag_mm, fail_mm = config.penetration_max_mm.flag, config.penetration_max_mm.fail
    deep = pyramid((flag_mm + 1.0) / 1000)
    report = run(good_results(V, contact), scene, hand=deep)
    assert report.metrics["penetration_max_mm"] == pytest.approx(flag_mm + 1.0, abs=0.05)
    assert report.verdict == Verdict.FLAGGED
    assert f"hand-object penetration (max) {flag_mm + 1:.2f} mm > {flag_mm:.2f} mm" in \
        report.flags
    assert any(r.startswith("hand-object penetration (mean)") for r in report.flags)
    report = run(good_results(V, contact), scene, hand=pyramid((fail_mm + 2.0) / 1000))
    assert report.verdict == Verdict.FAILED
    assert report.failures[0].startswith(
        f"hand-object penetration (max) {fail_mm + 2:.2f} mm > {fail_mm:.2f} mm")


def test_contact_agreement_both_directions(scene):
    V, F, hand, contact = scene
    # contact on the side face, far from the hand: neither direction agrees
    far = (np.abs(V[:, 0] - HALF_M) < 1e-6) & (np.abs(V[:, 2]) < 0.01)
    report = run(good_results(V, far.astype(float)), scene)
    assert report.metrics["contact_agreement"] == 0.0
    assert report.metrics["hand_contact_agreement"] == 0.0
    assert report.verdict == Verdict.FAILED
    assert report.failures == ("contacted vertices near the hand 0.00 < 0.30",)
    assert report.flags == ("contacted vertices near the fitted hand 0.00 < 0.30",
                            "hand-touching vertices contacted 0.00 < 0.30")
    # the hand elsewhere on the top face: nothing contacted is near it, nothing near is warm
    report = run(good_results(V, contact), scene, hand=pyramid(0.001, x_m=0.03))
    assert report.metrics["contact_agreement"] == 0.0
    assert report.metrics["hand_contact_agreement"] == 0.0


def test_missing_stages_are_missing_not_failures(scene):
    V, F, hand, contact = scene
    results = good_results(V, contact)
    del results["crosscheck_sfm"]
    results["fit_hand"] = None
    report = run(results, scene)
    assert report.verdict == Verdict.OK
    assert report.missing == {"crosscheck_mm": "crosscheck_sfm did not run",
                              "crosscheck_camera_deg": "crosscheck_sfm did not run",
                              "rgbd_discrepancy_mm": "crosscheck_sfm did not run",
                              "fit_residual_mm": "fit_hand did not run"}
    results = good_results(V, contact)
    del results["build_contactmap"]
    report = qa_metrics(results, object_mesh=None, hand_mesh_o=None)
    assert report.verdict == Verdict.OK
    assert {"contact_coverage", "penetration_max_mm", "contact_agreement"} <= set(report.missing)
    results["reconstruct_hand"].reproj_rmse_px = float("nan")
    report = qa_metrics(results)
    assert "reproj_rmse_px" in report.missing and report.verdict == Verdict.OK


def test_stage_warnings_flag_the_session(scene):
    V, F, hand, contact = scene
    cases = {
        ("register_object", "ambiguous", True): "register_object: near-symmetric object",
        ("register_scan", "ambiguous", True): "register_scan: symmetric object",
        ("register_scan", "note", "18 % of the posed mesh lies where the scan views see empty"):
            "register_scan: 18 % of the posed mesh",
        ("build_contactmap", "all_ambient", True): "build_contactmap: no contact anywhere",
        ("build_contactmap", "n_degenerate_faces", 3): "object mesh has 3 zero-area face(s)",
        ("propagate_poses", "n_behind", 2): "propagate_poses: 2 joint(s) at or behind",
        ("reconstruct_hand", "pose_valid", (False,) + (True,) * 19): "first steady frame, whose",
    }
    for (stage, attr, value), reason in cases.items():
        results = good_results(V, contact)
        setattr(results[stage], attr, value)
        if stage == "reconstruct_hand":  # a flag only without the mean over tracked frames
            results["estimate_adjustment"].average = None
        report = run(results, scene)
        assert report.verdict == Verdict.FLAGGED and len(report.flags) == 1
        assert reason in report.flags[0]
        quiet = run(results, scene, PRESETS["default"].model_copy(update={"stage_flags": False}))
        assert quiet.verdict == Verdict.OK
    results = good_results(V, contact)
    results["crosscheck_sfm"].flagged = True  # by crosscheck's own limits: judged here instead
    results["crosscheck_sfm"].reason = "joint 12 differs by 4.9 mm"
    assert run(results, scene).verdict == Verdict.OK
    results = good_results(V, contact)
    results["refine_grasp"] = SimpleNamespace(accepted=False, reason="penetrates deeper")
    report = run(results, scene)  # a note: the stage-3 fit is judged by its own agreement
    assert report.verdict == Verdict.OK and "refinement rejected" in report.notes[0]
    # the first steady frame's copied camera: a flag while T_adj rests on that frame's
    # registration, a note once T_w_o is the mean over the tracked frames
    results = good_results(V, contact)
    results["reconstruct_hand"].pose_valid = (False,) + (True,) * 19
    report = run(results, scene)
    assert report.verdict == Verdict.OK and report.flags == ()
    assert any("first steady frame has no pose of its own" in n for n in report.notes)
    results["estimate_adjustment"].average = SimpleNamespace(  # too few tracked
        T_w_o=None, spread_deg=float("nan"), reason="3 tracked frames, fewer than 5")
    assert run(results, scene).verdict == Verdict.FLAGGED
    for stage, note in (("estimate_adjustment", "estimate_adjustment: ambiguous"),):
        results = good_results(V, contact)  # resolved by the pipeline: a note, not a flag
        results[stage].ambiguous = True
        report = run(results, scene)
        assert report.verdict == Verdict.OK and report.flags == ()
        assert len(report.notes) == 1 and note in report.notes[0]
    results = good_results(V, contact)  # the last resort for a small object in the fist
    results["estimate_adjustment"].path, results["estimate_adjustment"].views = (
        "frame_consensus", 4)
    report = run(results, scene)
    assert report.verdict == Verdict.OK and report.flags == ()
    assert report.notes == ("estimate_adjustment: the object found alone in 4 steady frames "
                            "that agree (too few depth pixels beside the hand in any one frame)",)


def test_window_outlier_share_finds_the_worst_window():
    rng = np.random.default_rng(3)
    m = 40
    residuals = rng.normal(0, 2.0, (m, 21))
    residuals[rng.random((m, 21)) < 0.05] = np.nan  # missed detections
    inlier = rng.random((m, 21)) > 0.1  # detector outliers spread evenly
    spread = window_outlier_share(inlier, residuals, 8)
    assert 0.05 < spread < 0.3
    moving = inlier.copy()
    moving[:8] = rng.random((8, 21)) > 0.7  # a hand still moving in the first 8 frames
    share = window_outlier_share(moving, residuals, 8)
    detected = np.isfinite(residuals[:8])
    assert share == pytest.approx(np.mean(~moving[:8][detected]))
    assert share > PRESETS["default"].window_outlier_share.fail
    assert np.isnan(window_outlier_share(inlier, np.full((m, 21), np.nan), 8))
    assert window_outlier_share(inlier[:3], residuals[:3], 8) == pytest.approx(
        np.mean(~inlier[:3][np.isfinite(residuals[:3])]))  # fewer frames than a window


def test_refined_hand_metrics_are_read_off_refine_grasp(scene):
    """With a refinement, penetration and agreement are its own before/after numbers."""
    V, F, hand, contact = scene
    results = good_results(V, contact)
    before = SimpleNamespace(penetration_max_mm=0.4, penetration_mean_mm=0.2,
                             contact_near_share=0.3, touch_contacted_share=0.2)
    after = SimpleNamespace(penetration_max_mm=0.1, penetration_mean_mm=0.05,
                            contact_near_share=0.9, touch_contacted_share=float("nan"))
    results["refine_grasp"] = SimpleNamespace(accepted=True, reason="", before=before,
                                              after=after)
    report = qa_metrics(results)  # no meshes needed
    assert report.metrics["penetration_max_mm"] == 0.1
    assert report.metrics["contact_agreement"] == 0.9
    assert report.metrics["fit_contact_agreement"] == 0.3
    assert "hand_contact_agreement" in report.missing
    assert report.verdict == Verdict.FLAGGED
    assert report.flags == ("contacted vertices near the hand 0.90 < 0.92",)
    before.contact_near_share = 0.2
    assert qa_metrics(results).flags == ("contacted vertices near the fitted hand 0.20 < 0.30",
                                         "contacted vertices near the hand 0.90 < 0.92")


def test_qa_and_refine_share_one_contact_agreement(scene):
    """qa_metrics without a refinement measures the final hand with hand_surface's function,
    which agrees with an independent trimesh count (vertices inside a part count as near)."""
    V, F, hand, contact = scene
    observed = good_results(V)["build_contactmap"].observed
    deep = pyramid(0.008)  # apex 8 mm deep: vertices inside it are > 3 mm from its surface
    near, touch = contact_agreement(V, contact, observed, *deep, near_mm=3.0,
                                    contact_threshold=0.4)
    mesh = trimesh.Trimesh(*deep, process=False)
    touched = observed & (near_hand(V, deep, 3.0) | mesh.contains(V))
    assert (mesh.contains(V) & ~near_hand(V, deep, 3.0)).any()  # the inside case happens
    contacted = observed & (contact >= 0.4)
    assert near == pytest.approx(touched[contacted].mean())
    assert touch == pytest.approx(contacted[touched].mean())
    report = run(good_results(V, contact), scene, hand=deep)
    assert report.metrics["contact_agreement"] == near
    assert report.metrics["hand_contact_agreement"] == touch
    assert report.metrics["fit_contact_agreement"] == near


@pytest.fixture(scope="module")
def early_onset_session(tmp_path_factory):
    """A realistic session whose manifest names frame 0 as steady although the hand closes
    over the first 30 % of the video: a wrong-by-construction onset."""
    import json

    from graspcap.synth import config_for, generate_session

    cfg = config_for("realistic", 40).model_copy(
        update={"adjust_fraction": (0.3, 0.3), "write_steady_from": True})
    d = generate_session(tmp_path_factory.mktemp("early"), [31, 0], cfg)
    manifest = json.loads((d / "session.json").read_text())
    true_onset = manifest["grasp"]["steady_from"]
    manifest["grasp"]["steady_from"] = 0
    (d / "session.json").write_text(json.dumps(manifest))
    return d, true_onset


@pytest.mark.slow
def test_a_hand_that_moved_after_the_onset_is_flagged(early_onset_session):
    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

    d, true_onset = early_onset_session
    assert true_onset >= 10
    configs, results = configs_for(), {}
    for name in ("load_session", "detect_keypoints", "select_steady", "reconstruct_hand",
                 "crosscheck_sfm", "fit_hand"):
        results[name] = run_stage(STAGES[name], d, configs[name], results)
    report = qa_metrics(results)
    assert report.verdict != Verdict.OK, report.summary()
    assert any(r.startswith("keypoint outliers in the worst frame window")
               for r in report.reasons), report.summary()


def test_a_hand_our_model_does_not_fit_is_not_flagged(scene):
    """The wild rig's hands leave 4.6-9.4 mm of fit residual with every output good: the
    residual of our model on another hand is no evidence against the session (issue 18)."""
    V, F, hand, contact = scene
    results = good_results(V, contact)
    results["fit_hand"].rmse_mm = 9.4
    assert run(results, scene, PRESETS["default"]).verdict == Verdict.OK
    results["fit_hand"].rmse_mm = 24.0  # the SfM hand itself is wrong
    assert run(results, scene, PRESETS["default"]).verdict == Verdict.FAILED


def test_noisy_detections_are_judged_by_what_does_not_depend_on_the_pixels(scene):
    """A real detector's reprojection RMSE (10 % of a 200 px hand) and what follows from it
    (a pixels-only cross-check far off, the joint solve's ray residual) are one flag, not
    failures: the session is usable, but nothing vouches for its cameras; beyond
    ``noisy_fail_share`` no hand explains the detections and it fails; a registration off
    still fails it."""
    V, F, hand, contact = scene
    noisy = good_results(V, contact)
    noisy["reconstruct_hand"].reproj_rmse_px = 20.0
    noisy["reconstruct_hand"].inlier_ratio = 0.8
    noisy["crosscheck_sfm"].max_rgbd_joint_discrepancy_m = 0.05
    noisy["fit_hand"].rmse_mm = 19.0
    clean_size = run(noisy, scene)  # without the hand's size: judged as before
    assert clean_size.verdict == Verdict.FAILED
    default_hand = scene[2]
    report = qa_metrics(noisy, PRESETS["default"], object_mesh=(V, F), hand_mesh_o=default_hand,
                        hand_size_px=200.0)
    assert report.verdict == Verdict.FLAGGED, report.summary()  # usable, never vouched ok
    assert report.failures == () and len(report.flags) == 1
    assert report.flags[0].startswith("noisy detections: reprojection RMSE 20.0 px is 10.0%")
    assert report.metrics["reproj_rmse_px"] == 20.0  # still measured and stored
    big = qa_metrics(noisy, PRESETS["default"], object_mesh=(V, F), hand_mesh_o=default_hand,
                     hand_size_px=60.0)  # 33 % of the hand
    assert big.verdict == Verdict.FAILED and "no one hand explains" in big.failures[0]
    wrong = good_results(V, contact)  # noisy and the scan registration is off: still caught
    wrong["reconstruct_hand"].reproj_rmse_px = 20.0
    wrong["register_scan"].fitness = 0.5
    caught = qa_metrics(wrong, PRESETS["default"], object_mesh=(V, F), hand_mesh_o=default_hand,
                        hand_size_px=200.0)
    assert caught.verdict == Verdict.FAILED and any("scan" in f for f in caught.failures)


def test_object_spread_flags_cameras_the_depth_disagrees_with(scene):
    """The object's pose in the hand's world over the tracked frames: a spread beyond the flag
    limit flags the session with its value; without a tracked mean the metric is missing with
    the stage's reason and changes nothing."""
    V, F, hand, contact = scene
    limit = QaMetricsConfig().object_spread_deg.flag
    for spread, verdict in ((0.3, Verdict.OK), (1.5 * limit, Verdict.FLAGGED)):
        results = good_results(V, contact)
        results["estimate_adjustment"].average = SimpleNamespace(
            T_w_o=np.eye(4), spread_deg=spread, reason=None)
        report = qa_metrics(results, object_mesh=(V, F), hand_mesh_o=hand)
        assert report.metrics["object_spread_deg"] == spread
        assert report.verdict == verdict, report.reasons
        if verdict == Verdict.FLAGGED:
            assert report.flags == (
                f"spread of the object's pose over the tracked frames {spread:.2f} deg > "
                f"{limit:.2f} deg",)
    results = good_results(V, contact)
    results["estimate_adjustment"].average = SimpleNamespace(
        T_w_o=None, spread_deg=float("nan"), reason="3 tracked frames, fewer than 5")
    report = qa_metrics(results, object_mesh=(V, F), hand_mesh_o=hand)
    assert report.verdict == Verdict.OK
    assert report.missing["object_spread_deg"] == (
        "no mean over the tracked frames: 3 tracked frames, fewer than 5")
