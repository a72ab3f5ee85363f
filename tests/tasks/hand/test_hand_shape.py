"""Per-subject hand shape: exact bone lengths in the model, mesh and capsules that follow the
shape, the anatomical prior, and fit_hand recovering a known shape (and keeping a template hand
near the template)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from graspcap.tasks.core.geometry import from_rotvec
from graspcap.tasks.hand.fit_hand import PRESETS, fit_hand
from graspcap.tasks.hand.ik import central_jacobian
from graspcap.tasks.hand.model import (
    PART_BONES,
    SKELETON,
    SURFACE_OFFSET_M,
    TEMPLATE_BONE_LENGTHS_M,
    HandModel,
    HandSide,
)
from graspcap.tasks.hand.shape import (
    BONE_NAMES,
    PRIOR_COVARIANCE,
    PRIOR_SQRT_INFORMATION,
    bone_lengths_m,
    bone_scale_from_lengths,
    check_shape,
    prior_jacobian,
    prior_residuals,
)
from graspcap.tasks.outputs.qa_metrics import stage_notes

SIDES = [HandSide.RIGHT, HandSide.LEFT]
GRASP = np.array([0.5, 0.2, 0.3, 0.3] + [0.0, 0.6, 0.7, 0.4] * 4)


def _lengths(kp: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm(kp[k] - kp[p]) for p, k in SKELETON])


@pytest.mark.parametrize("side", SIDES, ids=lambda s: s.value)
def test_bone_lengths_are_exact_and_the_surface_follows(side):
    model = HandModel(side)
    rng = np.random.default_rng(3)
    for _ in range(5):
        angles = rng.uniform(model.lower_rad, model.upper_rad)
        T = from_rotvec(rng.normal(size=3), rng.uniform(-0.5, 0.5, 3))
        scale, b = rng.uniform(0.8, 1.2), np.exp(rng.normal(0.0, 0.12, 20))
        kp = model.keypoints(angles, T, scale, b)
        np.testing.assert_allclose(_lengths(kp), scale * b * TEMPLATE_BONE_LENGTHS_M, rtol=1e-12)
        np.testing.assert_allclose(_lengths(kp), bone_lengths_m(scale, b), rtol=1e-12)
        np.testing.assert_allclose(model.keypoints_batch(angles[None], T, scale, b[None])[0], kp)
        mesh, plain = model.mesh(angles, T, scale, b), model.mesh(angles, T, scale)
        assert mesh.vertices.shape == plain.vertices.shape
        np.testing.assert_array_equal(mesh.faces, plain.faces)
        # every phalanx: its skin is its radius from its (stretched) bone, ends included
        for k, (s, e) in enumerate(PART_BONES):
            V = mesh.vertices[mesh.part == k + 1]
            A, B = kp[s], kp[e]
            t = np.clip((V - A) @ (B - A) / ((B - A) @ (B - A)), 0.0, 1.0)
            d = np.linalg.norm(V - (A + t[:, None] * (B - A)), axis=1)
            r = scale * (SURFACE_OFFSET_M[s] * (1 - t) + SURFACE_OFFSET_M[e] * t)
            assert np.abs(d - r).max() < 0.02 * scale * SURFACE_OFFSET_M[s], k
        # the palm's knuckle spheres sit on the moved bases: a base is one radius under it
        palm = mesh.vertices[mesh.part == 0]
        for base in (1, 5, 9, 13, 17):
            gap = np.linalg.norm(palm - kp[base], axis=1).min()
            assert gap == pytest.approx(scale * SURFACE_OFFSET_M[base], rel=0.03), base
        for k in range(16):  # every part stays a closed surface
            faces = mesh.faces[np.isin(mesh.faces[:, 0], np.flatnonzero(mesh.part == k))]
            part = trimesh.Trimesh(mesh.vertices, faces, process=False)
            part.remove_unreferenced_vertices()
            assert part.is_watertight and part.volume > 0, k
        caps = model.capsules(angles, T, scale, b)
        np.testing.assert_allclose(caps.end[5:], kp[np.array(PART_BONES)[:, 1]], atol=1e-12)
        np.testing.assert_allclose(caps.end[:5], kp[[1, 5, 9, 13, 17]], atol=1e-12)
    np.testing.assert_array_equal(model.mesh(GRASP, bone_scale=np.ones(20)).vertices,
                                  model.mesh(GRASP).vertices)
    with pytest.raises(ValueError, match="bone_scale"):
        model.keypoints(GRASP, bone_scale=np.r_[np.ones(19), -1.0])


def test_prior_is_whitened_and_checks_plausibility():
    W = PRIOR_SQRT_INFORMATION
    np.testing.assert_allclose(W @ PRIOR_COVARIANCE @ W.T, np.eye(20), atol=1e-10)
    np.testing.assert_array_equal(prior_residuals(np.ones(20)), np.zeros(20))
    rng = np.random.default_rng(4)
    b = np.exp(rng.normal(0.0, 0.05, 20))
    jac = central_jacobian(lambda X: np.stack([prior_residuals(x) for x in X]), b,
                           np.full(20, 1e-7))
    np.testing.assert_allclose(jac, prior_jacobian(b), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(bone_scale_from_lengths(bone_lengths_m(1.1, b), 1.1), b)
    # draws from the prior are plausible (99.9 % quantile: at most a few of 400 flagged)
    draws = np.exp(rng.multivariate_normal(np.zeros(20), PRIOR_COVARIANCE, 400))
    assert sum(not check_shape(d).plausible for d in draws) <= 4
    long_tip = np.ones(20)
    long_tip[BONE_NAMES.index("index_distal")] = 1.6
    check = check_shape(long_tip)
    assert not check.plausible
    assert any(r.startswith("index_distal is 1.60 x") for r in check.reasons), check.reasons
    assert any(r.startswith("index_middle/distal ratio") for r in check.reasons), check.reasons
    assert check_shape(np.ones(20)).reasons == ()


def _hand(rng, bone_scale, noise_m, side=HandSide.RIGHT):
    model = HandModel(side)
    angles = model.clip(GRASP + rng.normal(0.0, 0.15, 20))
    T = from_rotvec(rng.normal(size=3), rng.uniform(-0.3, 0.3, 3) + [0.0, 0.0, 0.6])
    scale = rng.uniform(0.9, 1.1)
    truth = model.keypoints(angles, T, scale, bone_scale)
    return truth, truth + rng.normal(0.0, noise_m, (21, 3)), scale


@pytest.mark.parametrize("side", SIDES, ids=lambda s: s.value)
def test_fit_recovers_a_known_shape_from_noisy_joints(side):
    """Metacarpals and proximal phalanges 8-10 % off the template, 0.5 mm joint noise:
    fit_hand (told that noise level) gets those bones within 6 % each and 4 % RMS (the
    template's are 8-10 % off; one pose does not separate every bone from the angles, and the
    prior pulls) and the joints within 1 mm, which the template's proportions miss."""
    truth_b = np.ones(20)
    changed = [5, 9, 13, 17, 6, 10, 14]
    truth_b[changed] = [1.10, 0.92, 1.08, 0.90, 0.90, 1.10, 0.92]
    config = PRESETS["default"].model_copy(update={"shape_noise_mm": 0.5})
    template = config.model_copy(update={"estimate_shape": False})
    rng = np.random.default_rng(5)
    for _ in range(3):
        truth, joints, scale = _hand(rng, truth_b, 0.0005, side)
        fit = fit_hand(joints, side, config)
        rel = fit.bone_lengths_m / (scale * truth_b * TEMPLATE_BONE_LENGTHS_M) - 1.0
        assert np.abs(rel[changed]).max() < 0.06, np.round(rel, 3)
        assert np.sqrt(np.mean(rel[changed] ** 2)) < 0.04, np.round(rel, 3)
        err_mm = 1e3 * np.linalg.norm(fit.joints_fit_w - truth, axis=1).mean()
        plain = fit_hand(joints, side, template)
        plain_mm = 1e3 * np.linalg.norm(plain.joints_fit_w - truth, axis=1).mean()
        assert err_mm < 1.0 < plain_mm, (err_mm, plain_mm)
        assert fit.shape_check.plausible and fit.shape_note == "" and fit.shape_chi2 > 45.3
        np.testing.assert_array_equal(plain.bone_scale, np.ones(20))
        np.testing.assert_allclose(_lengths(fit.joints_fit_w), fit.bone_lengths_m)


def test_a_template_hand_stays_near_the_template():
    """A template hand's joints with 2 mm noise (the default's assumed level): the
    likelihood-ratio test finds no shape (every fit keeps the template exactly). Forced to keep
    its shape (``shape_test_p`` 1), the fit moves a bone by at most 15 % (a 20 mm bone's length
    is measured to about 14 % at that noise), 6 % RMS, stays plausible, and its joints are no
    worse than 0.6 mm over the template fit's."""
    rng = np.random.default_rng(6)
    template = PRESETS["default"].model_copy(update={"estimate_shape": False})
    forced = PRESETS["default"].model_copy(update={"shape_test_p": 1.0})
    for _ in range(4):
        truth, joints, scale = _hand(rng, None, 0.002)
        fit = fit_hand(joints, HandSide.RIGHT)
        np.testing.assert_array_equal(fit.bone_scale, np.ones(20))
        assert 0.0 < fit.shape_chi2 < 45.3  # chi-square(20) 99.9 % quantile
        fit = fit_hand(joints, HandSide.RIGHT, forced)
        log_b = np.log(fit.bone_lengths_m / (scale * TEMPLATE_BONE_LENGTHS_M))
        assert np.abs(log_b).max() < 0.15 and np.sqrt(np.mean(log_b**2)) < 0.06, log_b
        assert fit.shape_check.plausible
        err = np.linalg.norm(fit.joints_fit_w - truth, axis=1).mean()
        plain = fit_hand(joints, HandSide.RIGHT, template)
        assert err < np.linalg.norm(plain.joints_fit_w - truth, axis=1).mean() + 0.0006


def test_joints_no_hand_explains_keep_the_template():
    """Joints 15 mm off at random: the template's fit leaves more than max_shape_rmse_mm, so
    the shape is not fitted to the noise, and the fit (and QA's notes) say why."""
    rng = np.random.default_rng(7)
    _, joints, _ = _hand(rng, None, 0.015)
    fit = fit_hand(joints, HandSide.RIGHT)
    np.testing.assert_array_equal(fit.bone_scale, np.ones(20))
    assert "the template's proportions kept" in fit.shape_note
    assert f"fit_hand: {fit.shape_note}" in stage_notes({"fit_hand": fit})
    good = fit_hand(_hand(rng, None, 0.001)[1], HandSide.RIGHT)
    assert good.shape_note == "" and not any(n.startswith("fit_hand") for n in
                                             stage_notes({"fit_hand": good}))
