"""qa_metrics: every limit flips the verdict with its reason; hand-object metrics measured on
a box and a pyramid whose penetration and contact are known by construction."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from graspcap.tasks.qa_metrics import METRICS, PRESETS, QaMetricsConfig, Verdict, qa_metrics

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
        "reconstruct_hand": SimpleNamespace(reproj_rmse_px=2.0, inlier_ratio=0.95),
        "crosscheck_sfm": SimpleNamespace(max_joint_discrepancy_m=0.002, flagged=False,
                                          reason=""),
        "register_object": SimpleNamespace(fitness=0.95, inlier_rmse_m=0.001, ambiguous=False),
        "estimate_adjustment": SimpleNamespace(fitness=0.95, inlier_rmse_m=0.001,
                                               ambiguous=False),
        "register_scan": SimpleNamespace(fitness=0.95, inlier_rmse_m=0.001, ambiguous=False),
        "fit_hand": SimpleNamespace(rmse_mm=2.0),
        "propagate_poses": SimpleNamespace(n_behind=0),
        "build_contactmap": SimpleNamespace(contact=contact, observed=observed,
                                            coverage=float(observed.mean()), all_ambient=False,
                                            n_degenerate_faces=0),
    }


@pytest.fixture(scope="module")
def scene():
    V, F = object_mesh()
    hand = pyramid(0.001)
    contact = near_hand(V, hand, 4.0).astype(float)
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
    assert report.metrics["penetration_max_mm"] == pytest.approx(1.0, abs=0.05)
    assert report.metrics["penetration_mean_mm"] == pytest.approx(1.0, abs=0.05)  # apex only
    assert report.metrics["contact_agreement"] == pytest.approx(1.0)
    # vertices within 5 mm of the hand, contacted where within 4 mm (both by trimesh)
    near5 = near_hand(V, hand, 5.0) & good_results(V)["build_contactmap"].observed
    expected = contact[near5].mean()
    assert report.metrics["hand_contact_agreement"] == pytest.approx(expected, abs=0.03)
    assert report.metrics["reproj_rmse_px"] == 2.0 and report.metrics["crosscheck_mm"] == 2.0


# (metric, stage, attribute, factor from the metric's unit to the attribute's)
READ_OFF = [
    ("reproj_rmse_px", "reconstruct_hand", "reproj_rmse_px", 1.0),
    ("inlier_ratio", "reconstruct_hand", "inlier_ratio", 1.0),
    ("crosscheck_mm", "crosscheck_sfm", "max_joint_discrepancy_m", 1e-3),
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


def test_limits_come_from_the_preset(scene):
    V, F, hand, contact = scene
    results = good_results(V, contact)
    results["reconstruct_hand"].reproj_rmse_px = 4.0  # between strict's and default's flag
    assert PRESETS["strict"].reproj_rmse_px.flag < 4.0 < PRESETS["default"].reproj_rmse_px.flag
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
    assert report.failures[0].startswith("hand-object penetration (max) 22.00 mm > 20.00 mm")


def test_contact_agreement_both_directions(scene):
    V, F, hand, contact = scene
    # contact on the side face, far from the hand: neither direction agrees
    far = (np.abs(V[:, 0] - HALF_M) < 1e-6) & (np.abs(V[:, 2]) < 0.01)
    report = run(good_results(V, far.astype(float)), scene)
    assert report.metrics["contact_agreement"] == 0.0
    assert report.metrics["hand_contact_agreement"] == 0.0
    assert report.verdict == Verdict.FLAGGED
    assert "contacted vertices near the hand 0.00 < 0.50" in report.flags
    assert "hand-touching vertices contacted 0.00 < 0.10" in report.flags
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
        ("register_object", "ambiguous", True): "register_object: symmetric object",
        ("estimate_adjustment", "ambiguous", True): "estimate_adjustment: ambiguous",
        ("register_scan", "ambiguous", True): "register_scan: symmetric object",
        ("build_contactmap", "all_ambient", True): "build_contactmap: no contact anywhere",
        ("build_contactmap", "n_degenerate_faces", 3): "object mesh has 3 zero-area face(s)",
        ("propagate_poses", "n_behind", 2): "propagate_poses: 2 joint(s) at or behind",
    }
    for (stage, attr, value), reason in cases.items():
        results = good_results(V, contact)
        setattr(results[stage], attr, value)
        report = run(results, scene)
        assert report.verdict == Verdict.FLAGGED and len(report.flags) == 1
        assert reason in report.flags[0]
        quiet = run(results, scene, PRESETS["default"].model_copy(update={"stage_flags": False}))
        assert quiet.verdict == Verdict.OK
    results = good_results(V, contact)
    results["crosscheck_sfm"].flagged = True
    results["crosscheck_sfm"].reason = "joint 12 differs by 4.9 mm"
    assert run(results, scene).flags == ("crosscheck_sfm: joint 12 differs by 4.9 mm",)
    results = good_results(V, contact)
    results["refine_grasp"] = SimpleNamespace(accepted=False, reason="penetrates deeper")
    assert "refinement rejected" in run(results, scene).flags[0]
