"""refine_grasp (stage 5): a perturbed true grasp comes back, penetration is undone, bad input
is refused. Grasps come from the synthetic rig's autograsp on a procedural object."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from graspcap.synth import PRESETS as SYNTH_PRESETS
from graspcap.synth import procedural_object
from graspcap.synth.grasp import hand_contact, plan_grasp
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import from_rotvec, make_T, transform_points
from graspcap.tasks.hand.fit_hand import HandFit
from graspcap.tasks.hand.model import HandModel, HandSide
from graspcap.tasks.hand.refine_grasp import PRESETS, refine_grasp
from graspcap.tasks.hand.surface import HandSurface, palm_grid

T_W_O = from_rotvec(np.array([0.3, -0.2, 0.5]), np.array([0.05, 0.02, 0.6]))
MODEL = HandModel(HandSide.RIGHT)


@pytest.fixture(scope="module")
def grasp():
    obj = procedural_object("bottle", 8000)
    g = plan_grasp(obj, MODEL, 1.0, np.array([0.0, 0.0, 1.0]), SYNTH_PRESETS["realistic"],
                   np.random.default_rng(1))
    mesh = MODEL.mesh(g.angles_rad, g.T_o_p, g.scale)
    contact = hand_contact(obj, mesh.vertices, mesh.faces, mesh.part)
    return obj, g, contact


def _fit(T_o_p: np.ndarray, angles: np.ndarray, scale: float) -> HandFit:
    T_w_p = T_W_O @ T_o_p
    return HandFit(side=HandSide.RIGHT, T_w_p=T_w_p, scale=scale, angles_rad=angles,
                   joints_fit_w=MODEL.keypoints(angles, T_w_p, scale), residual_mm=np.zeros(21),
                   rmse_mm=0.0, palm_rmse_mm=0.0, at_limit=np.zeros(20, bool))


def _run(grasp, T_o_p, angles, contact=None, config=PRESETS["default"]):
    obj, g, true_contact = grasp
    c = true_contact if contact is None else contact
    return refine_grasp(_fit(T_o_p, angles, g.scale), HandSide.RIGHT, T_W_O, obj.vertices,
                        obj.faces, c, np.ones(len(c), bool), config)


def test_perturbed_true_grasp_comes_back(grasp):
    obj, g, contact = grasp
    opened = MODEL.clip(g.angles_rad - np.tile(np.radians([0.0, 5.0, 4.0, 4.0]), 5))  # ~13 deg
    T_o_p = g.T_o_p @ from_rotvec(np.array([0.0, 0.03, 0.0]), np.array([0.003, -0.002, -0.002]))
    r = _run(grasp, T_o_p, opened)
    true_joints = MODEL.keypoints(g.angles_rad, g.T_o_p, g.scale)
    err_fit_mm = 1e3 * np.linalg.norm(MODEL.keypoints(opened, T_o_p, g.scale) - true_joints, axis=1)
    err_ref_mm = 1e3 * np.linalg.norm(r.joints_o - true_joints, axis=1)
    assert r.accepted and r.reason == ""
    assert r.before.contact_near_share < 0.5  # the perturbation really lost the contact
    assert r.after.contact_near_share >= 0.9
    assert r.after.penetration_max_mm <= 2.0
    assert r.after.penetration_max_mm <= r.before.penetration_max_mm  # never deeper than the fit
    assert err_ref_mm.mean() < 0.6 * err_fit_mm.mean()  # measured: 7.0 -> 2.6 mm
    # frames agree with each other, angles inside the limits
    np.testing.assert_allclose(r.T_w_p, T_W_O @ r.T_o_p, atol=1e-12)
    np.testing.assert_allclose(r.joints_w, transform_points(T_W_O, r.joints_o), atol=1e-12)
    np.testing.assert_allclose(r.joints_o, MODEL.keypoints(r.angles_rad, r.T_o_p, g.scale),
                               atol=1e-12)
    assert np.all((r.angles_rad >= MODEL.lower_rad) & (r.angles_rad <= MODEL.upper_rad))
    assert r.hand_vertices_o.shape == (len(MODEL.mesh(r.angles_rad).vertices), 3)
    assert 0.0 < r.after.contact_agreement <= 1.0


def test_penetrating_hand_is_pushed_out(grasp):
    _, g, _ = grasp
    T_in = g.T_o_p @ make_T(np.eye(3), [0.0, 0.0, 0.006])  # palm 6 mm into the object
    r = _run(grasp, T_in, g.angles_rad, config=PRESETS["fast"])
    assert r.before.penetration_max_mm > 4.0
    assert r.accepted
    assert r.after.penetration_max_mm <= 2.0
    again = _run(grasp, T_in, g.angles_rad, config=PRESETS["fast"])  # deterministic
    np.testing.assert_array_equal(again.T_o_p, r.T_o_p)
    np.testing.assert_array_equal(again.angles_rad, r.angles_rad)


def test_never_deeper_than_the_fit(grasp):
    """Without its penetration term the optimum of an opened hand sinks into the object; the
    stage scales the move back until the hand is no deeper than the fit (here: not inside at
    all), keeping most of the move and of the contact it regained."""
    _, g, _ = grasp
    opened = MODEL.clip(g.angles_rad - np.tile(np.radians([0.0, 5.0, 4.0, 4.0]), 5))
    config = PRESETS["fast"].model_copy(update={"penetration_weight": 0.0})
    r = _run(grasp, g.T_o_p, opened, config=config)
    assert r.accepted
    assert r.before.penetration_max_mm == 0.0
    assert 0.3 < r.kept_share < 1.0  # measured: 0.77
    assert r.after.penetration_max_mm == 0.0
    assert r.after.contact_near_share > r.before.contact_near_share + 0.3  # 0.40 -> 0.86


def test_no_contact_keeps_the_fit(grasp):
    _, g, contact = grasp
    r = _run(grasp, g.T_o_p, g.angles_rad, contact=np.zeros_like(contact))
    assert not r.accepted and "no observed vertex has contact" in r.reason
    np.testing.assert_array_equal(r.angles_rad, g.angles_rad)
    np.testing.assert_allclose(r.T_o_p, g.T_o_p, atol=1e-12)
    assert r.after == r.before and r.iterations == 0


@pytest.mark.parametrize(
    "field, change",
    [
        ("contact", lambda c, o: (c[:-1], o)),
        ("observed", lambda c, o: (c, o[:-3])),
        ("contact", lambda c, o: (np.where(np.arange(len(c)) == 5, np.nan, c), o)),
    ],
)
def test_bad_inputs_name_the_field(grasp, field, change):
    obj, g, contact = grasp
    c, o = change(contact, np.ones(len(contact), bool))
    with pytest.raises(StageError, match=field):
        refine_grasp(_fit(g.T_o_p, g.angles_rad, g.scale), HandSide.RIGHT, T_W_O, obj.vertices,
                     obj.faces, c, o)


def test_bad_side_and_pose(grasp):
    obj, g, contact = grasp
    fit = _fit(g.T_o_p, g.angles_rad, g.scale)
    obs = np.ones(len(contact), bool)
    with pytest.raises(StageError, match="side"):
        refine_grasp(fit, HandSide.LEFT, T_W_O, obj.vertices, obj.faces, contact, obs)
    with pytest.raises(StageError, match="T_w_o"):
        refine_grasp(fit, HandSide.RIGHT, np.full((4, 4), np.nan), obj.vertices, obj.faces,
                     contact, obs)


@pytest.mark.parametrize("side", [HandSide.RIGHT, HandSide.LEFT])
def test_model_distance_matches_the_hand_mesh(side):
    """The optimiser's surface distance vs Open3D's distance to the posed hand mesh."""
    model = HandModel(side)
    rng = np.random.default_rng(3)
    angles = model.clip(rng.uniform(-0.2, 1.0, 20))
    T = from_rotvec(rng.normal(size=3), rng.normal(scale=0.05, size=3))
    scale = 1.1
    mesh = model.mesh(angles, T, scale)
    # points 1-15 mm outside the surface, along vertex directions from the part centres
    idx = rng.choice(len(mesh.vertices), 400, replace=False)
    centre = np.stack([mesh.vertices[mesh.part == p].mean(0) for p in range(16)])
    out = mesh.vertices[idx] - centre[mesh.part[idx]]
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    pts = mesh.vertices[idx] + rng.uniform(0.001, 0.015, (400, 1)) * out
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    inside = np.zeros(len(pts), bool)
    for p in range(16):  # a point inside another part has no outside distance to compare
        part = o3d.t.geometry.RaycastingScene()
        f = mesh.faces[mesh.part[mesh.faces[:, 0]] == p]
        part.add_triangles(mesh.vertices.astype(np.float32), f.astype(np.uint32))
        inside |= part.compute_occupancy(o3d.core.Tensor(pts.astype(np.float32))).numpy() > 0
    exact = scene.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    kp = model.keypoints(angles, T, scale)[None]
    d = HandSurface(side, scale).distance(pts, kp, T[None, :3, :3], T[None, :3, 3])[0]
    err_mm = 1e3 * np.abs(d - exact)[~inside]
    assert (~inside).sum() > 200
    assert np.percentile(err_mm, 95) < 0.5 and err_mm.max() < 1.0


def test_refinement_keeps_and_uses_the_fitted_shape(grasp):
    """A fit with a per-bone shape: the refined hand keeps it (bone lengths exact), its mesh is
    the shaped model's and its surface distances are to the shaped hand."""
    import dataclasses

    from graspcap.tasks.hand.model import SKELETON, TEMPLATE_BONE_LENGTHS_M

    obj, g, contact = grasp
    b = np.exp(np.random.default_rng(8).normal(0.0, 0.06, 20))
    fit = dataclasses.replace(_fit(g.T_o_p, g.angles_rad, g.scale), bone_scale=b)
    r = refine_grasp(fit, HandSide.RIGHT, T_W_O, obj.vertices, obj.faces, contact,
                     np.ones(len(contact), bool), PRESETS["fast"])
    np.testing.assert_array_equal(r.bone_scale, b)
    lengths = [np.linalg.norm(r.joints_o[k] - r.joints_o[p]) for p, k in SKELETON]
    np.testing.assert_allclose(lengths, g.scale * b * TEMPLATE_BONE_LENGTHS_M, rtol=1e-10)
    np.testing.assert_allclose(
        r.hand_vertices_o, MODEL.mesh(r.angles_rad, r.T_o_p, g.scale, b).vertices, atol=1e-12)
    # the distances are to the shaped hand: its palm vertices lie on the shaped palm's surface
    mesh = MODEL.mesh(MODEL.rest_angles(), bone_scale=b)
    palm_p = mesh.vertices[mesh.part == 0]
    assert np.abs(palm_grid(HandSide.RIGHT, b)(palm_p)).max() < 2.5e-3  # concave: within 2.5 mm
    surface = HandSurface(HandSide.RIGHT, g.scale, 5, b)
    np.testing.assert_allclose(surface.palm_samples_p, palm_p * g.scale)
