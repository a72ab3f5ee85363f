"""estimate_adjustment/14's extra candidates: the rotation one depth view leaves free (a mug's
body with its handle hidden, held-out mug [9900, 4]: 178-180 deg off) and the model's own
near-symmetries (the mug's principal axes are arbitrary, held-out mug [9900, 7]: 180 deg off)."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.synth.objects import procedural_object
from graspcap.tasks.core.geometry import from_rotvec, rotation_error_deg
from graspcap.tasks.object_pose.registration.engine import RegistrationConfig, prepare_model
from graspcap.tasks.object_pose.registration.free_rotation import (
    FreeAxis,
    free_axis,
    free_starts,
    nearest_turn,
    turned,
)
from graspcap.tasks.object_pose.registration.symmetry import axes_ill_defined, self_flip_axes


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two lines (sign of the directions ignored)."""
    c = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(min(c, 1.0))))


def _cylinder_patch(rng, axis, point, radius=0.04, height=0.09, n=3000):
    """Points and outward normals of the half of a cylinder facing -z (seen by a camera at
    the origin looking along +z), axis ``axis`` through ``point``."""
    axis = axis / np.linalg.norm(axis)
    u = np.cross(axis, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u)
    w = np.cross(axis, u)
    if w[2] > 0:
        w = -w  # w points towards the camera
    phi = rng.uniform(-np.pi / 2, np.pi / 2, n)
    h = rng.uniform(-height / 2, height / 2, n)
    normals = np.cos(phi)[:, None] * w + np.sin(phi)[:, None] * u
    return point + radius * normals + h[:, None] * axis, normals


def test_free_axis_of_a_cylinder_patch_is_its_axis():
    rng = np.random.default_rng(0)
    axis = np.array([0.3, 0.9, 0.2])
    point = np.array([0.05, -0.02, 0.6])
    pts, normals = _cylinder_patch(rng, axis, point)
    free = free_axis(pts + rng.normal(scale=0.0005, size=pts.shape), normals)
    assert _angle_deg(free.axis, axis) <= 1.0
    off = free.point - point
    assert np.linalg.norm(off - (off @ axis) * axis / (axis @ axis)) <= 0.002  # on the axis
    assert free.weakness <= 1e-3


def test_free_axis_of_a_box_corner_is_constrained():
    """Three faces of a box pin every rotation: the weakest is far stronger than a cylinder's."""
    rng = np.random.default_rng(1)
    pts, normals = [], []
    for k in range(3):
        p = rng.uniform(0.0, 0.08, (1000, 3))
        p[:, k] = 0.0
        pts.append(p)
        normals.append(np.tile(-np.eye(3)[k], (1000, 1)))
    free = free_axis(np.concatenate(pts) + [0.0, 0.0, 0.5], np.concatenate(normals))
    assert free.weakness >= 0.05


def test_nearest_turn_is_the_closest_rotation_about_the_axis():
    rng = np.random.default_rng(2)
    for _ in range(5):
        axis = rng.normal(size=3)
        free = FreeAxis(axis / np.linalg.norm(axis), rng.normal(size=3) * 0.1, 0.0)
        T = from_rotvec(rng.normal(size=3), rng.normal(size=3) * 0.1)
        R_ref = from_rotvec(rng.normal(size=3), np.zeros(3))[:3, :3]
        best = nearest_turn(T, free, R_ref)
        grid = [
            rotation_error_deg(turned(T, free.axis, free.point, a)[:3, :3], R_ref)
            for a in np.radians(np.arange(0.0, 360.0, 0.25))
        ]
        assert rotation_error_deg(best[:3, :3], R_ref) <= min(grid) + 1e-3
        # a turn about the axis through the point: the point stays put
        assert np.allclose(best[:3, :3] @ np.linalg.solve(T[:3, :3], free.point - T[:3, 3])
                           + best[:3, 3], free.point, atol=1e-9)  # fmt: skip


def test_free_starts_turn_and_flip():
    """The flipped start turns the body's axis over (180 deg) and both are nearest the
    reference among turns about the free axis."""
    free = FreeAxis(np.array([0.0, 0.0, 1.0]), np.zeros(3), 0.0)
    T = from_rotvec(np.array([0.0, 0.0, 0.5]), np.zeros(3))
    starts = dict(free_starts(T, free, np.eye(3), np.array([0.0, -0.05, 0.02])))
    assert rotation_error_deg(starts["free:turn"][:3, :3], np.eye(3)) <= 1e-3
    z = starts["free:flip"][:3, :3] @ [0.0, 0.0, 1.0]
    assert z[2] <= -1 + 1e-9


def test_self_flip_axes_of_the_mug_are_its_handle_and_body_axes():
    """The procedural mug (handle towards +x, body along z): its principal axes are mixed
    (two spreads within 3 %), the self-matching half turns are about x and z."""
    mug = procedural_object("mug")
    model = prepare_model(mug.vertices, mug.faces, RegistrationConfig(coarse_model_points=5000))
    axes = self_flip_axes(model)
    assert _angle_deg(axes[0], np.array([1.0, 0.0, 0.0])) <= 3.0
    assert _angle_deg(axes[1], np.array([0.0, 0.0, 1.0])) <= 3.0
    principal_to_x = min(_angle_deg(model.axes[:, i], np.array([1.0, 0, 0])) for i in range(3))
    assert principal_to_x >= 20.0  # why the principal-axis probes missed the handle flip
    assert self_flip_axes(model) is axes  # cached per model


@pytest.mark.parametrize("kind", ["carton"])
def test_self_flip_axes_of_a_carton_are_principal(kind):
    obj = procedural_object(kind)
    model = prepare_model(obj.vertices, obj.faces, RegistrationConfig(coarse_model_points=5000))
    for a in self_flip_axes(model):
        assert min(_angle_deg(a, model.axes[:, i]) for i in range(3)) <= 2.0



@pytest.mark.parametrize(
    "kind,ill_defined",
    [("mug", True), ("bottle", True), ("carton", False), ("spray_bottle", False),
     ("drill", False)],
)  # fmt: skip
def test_principal_axes_are_ill_defined_for_the_mug_and_bottle_only(kind, ill_defined):
    """Two principal spreads within 10 %: the mug's two largest (0.968), the bottle's two
    smallest (0.968); carton 0.78, spray bottle 0.71, drill 0.65 (estimate_adjustment/15 runs
    the flip probes, free turns and views-if-ambiguous only for the former)."""
    obj = procedural_object(kind)
    model = prepare_model(obj.vertices, obj.faces, RegistrationConfig(coarse_model_points=5000))
    assert axes_ill_defined(model, 0.9) is ill_defined
    assert axes_ill_defined(model, 0.99) is False  # no two spreads within 1 %
    assert axes_ill_defined(model, 0.5)  # every pair of these within a factor 2


@pytest.mark.parametrize("seed,angle_deg", [(2, 60.0), (2, 120.0)])
def test_lifted_mug_is_not_its_handle_flip(seed, angle_deg):
    """The procedural mug lifted and turned in the rig's hand: /13 (no self-flip probes, no
    free turns) came out 180.0 / 175.3 deg off at fitness 0.83 / 0.86, the half turn about the
    handle's axis never probed; now the truth at 0.999."""
    from graspcap.tasks.core.geometry import pose_error
    from graspcap.tasks.object_pose.estimate_adjustment import PRESETS, estimate_adjustment
    from tests.registration_rig import K, lifted_procedural

    mesh, T_w_o1, depth, mask, T_true = lifted_procedural("mug", seed, angle_deg)
    r = estimate_adjustment(depth, K, *mesh, T_w_o1, mask)
    rot, trans = pose_error(r.T_w_o, T_true)
    assert rot <= 1.0 and trans <= 0.003, (rot, trans)
    assert r.fitness >= 0.99
    if angle_deg == 60.0:  # the case needs the new candidates
        old = PRESETS["default"].model_copy(
            update={"flip_probes": False, "free_turns": False, "grid_group": ""}
        )  # the grid starts (estimate_adjustment/16) find it too
        r_old = estimate_adjustment(depth, K, *mesh, T_w_o1, mask, old)
        assert pose_error(r_old.T_w_o, T_true)[0] >= 90.0

def _held_out_mug(tmp_path, seed: list[int], onset: int | None = None, first: bool = False):
    """Synth session ``seed`` (realistic, 120 frames), upstream stages run fresh (from
    ``onset`` when given), estimate_adjustment's ``T_c_o`` at the first steady frame against
    the truth's: (rotation deg, translation m, result). ``first``: the pose registered in the
    first steady frame(s) (``Adjustment.T_w_o_first``, where ``T_w_o`` is the mean over the
    tracked frames since estimate_adjustment/22, which carries stage 2's camera errors)."""
    from dataclasses import replace

    from graspcap.synth import config_for, generate_session
    from graspcap.synth.evaluate import load_truth
    from graspcap.tasks.core.geometry import inv_T, pose_error
    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

    d = generate_session(tmp_path, seed, config_for("realistic", 120))
    res: dict = {}
    for name in ("load_session", "register_object", "detect_keypoints", "select_steady",
                 "reconstruct_hand", "fit_hand"):  # fmt: skip
        if name == "reconstruct_hand" and onset is not None:
            res["select_steady"] = replace(res["select_steady"], steady_from=onset)
        res[name] = run_stage(STAGES[name], d, configs_for()[name], res)
    truth = load_truth(d)
    i = res["select_steady"].steady_from - int(truth["steady_from"])
    T_true = inv_T(truth["T_w_c"][max(i, 0)]) @ truth["T_adj"] @ truth["T_w_o_stage1"]
    adj = run_stage(STAGES["estimate_adjustment"], d, configs_for()["estimate_adjustment"], res)
    T_w_o = adj.T_w_o_first if first and adj.T_w_o_first is not None else adj.T_w_o
    rot, trans = pose_error(inv_T(res["reconstruct_hand"].T_w_c[0]) @ T_w_o, T_true)
    return rot, trans, adj


@pytest.mark.slow
def test_held_out_mug_handle_seen_is_not_its_flip(tmp_path):
    """[9900, 7]: the handle is seen, its half turn about the handle's axis (agreement 0.71)
    was kept, the truth (1.0) never a candidate: 179.7 deg off at estimate_adjustment/13. The
    first steady frame's registration is judged (0.65 deg / 1.5 mm at /24): the mean over the
    tracked frames that replaced it as ``T_w_o`` at /22 is 2.39 deg off here, its frames'
    object poses spread 2.8 deg by stage 2's cameras (QA's ``object_spread_deg`` flags it)."""
    rot, trans, adj = _held_out_mug(tmp_path, [9900, 7], first=True)
    assert rot <= 1.0 and trans <= 0.003, (rot, trans)
    assert adj.fitness >= 0.99


@pytest.mark.slow
def test_held_out_mug_handle_hidden_is_upright_and_flagged(tmp_path):
    """[9900, 4] from its true onset (26): the handle hidden behind the body, the truth, poses
    turned about the body's axis and the upside-down twin explain the frame alike; /13 kept
    the twin (178 deg off). Now the turn nearest stage 1, ambiguous, so the other views are
    registered too (the handle is seen in one of them; cameras ~4 deg off): ~5 deg (the turn
    about the body is barely observable, hence the tolerance), upright."""
    rot, trans, adj = _held_out_mug(tmp_path, [9900, 4], onset=26)
    assert rot <= 10.0 and trans <= 0.01, (rot, trans)
    assert adj.ambiguous and adj.views > 1
