"""Symmetry-aware object pose errors (``graspcap.synth.symmetry``) and their use in the
evaluation's per-frame object errors."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from graspcap.synth.evaluate import (
    _contact_metrics,
    _per_frame_object_errors,
    _refinement_metrics,
    grasp_symmetry,
)
from graspcap.synth.objects import procedural_object, scaled_object, write_object
from graspcap.synth.symmetry import (
    closest_symmetry,
    find_symmetries,
    find_symmetries_of,
    rotation_error_sym_deg,
    surface_errors_mm,
    surface_scene,
    sym_pose_metrics,
)
from graspcap.tasks.core.geometry import from_rotvec, make_T, pose_error


def _about(sym, rotvec) -> np.ndarray:
    """The rotation ``rotvec`` about the mesh's centroid as an object-frame transform."""
    R = from_rotvec(np.asarray(rotvec, float), np.zeros(3))[:3, :3]
    return make_T(R, sym.centroid - R @ sym.centroid)


T_TRUE = from_rotvec(np.array([0.4, -0.3, 1.1]), np.array([0.05, -0.02, 0.6]))


@pytest.fixture(scope="module")
def meshes():
    def mesh(name, extent):
        o = scaled_object(procedural_object(name), extent)
        return o, find_symmetries_of(o.vertices, o.faces)

    box = trimesh.creation.box(extents=(0.09, 0.06, 0.035))
    return {"ball": mesh("ball", 0.08), "can": mesh("can", 0.125), "mug": mesh("mug", 0.13),
            "box": (box, find_symmetries_of(box.vertices, box.faces))}


def test_symmetries_are_found_in_the_mesh(meshes):
    """Ball (valve bump): a sphere; can (pull tab): its axis and the flip end for end; a box:
    its three half turns; a mug (handle): none."""
    assert meshes["ball"][1].sphere
    can = meshes["can"][1]
    assert not can.sphere and abs(abs(can.axis[2]) - 1) < 1e-2 and len(can.discrete) == 2
    box = meshes["box"][1]
    assert box.axis is None and not box.sphere and len(box.discrete) == 4
    mug = meshes["mug"][1]
    assert mug.axis is None and not mug.sphere and len(mug.discrete) == 1


@pytest.mark.parametrize("name, rotvec", [
    ("ball", [1.2, -0.5, 0.8]),  # any turn
    ("can", [0.0, 0.0, 1.3]),  # a spin about its axis
    ("can", [np.pi, 0.0, 0.0]),  # upside down
    ("box", [0.0, np.pi, 0.0]),  # a half turn
])
def test_a_turn_the_mesh_maps_onto_itself_is_no_symmetry_aware_error(meshes, name, rotvec):
    _, sym = meshes[name]
    T_est = T_TRUE @ _about(sym, rotvec)
    raw_deg, _ = pose_error(T_est, T_TRUE)
    assert raw_deg > 60  # the raw error is as large as it used to be
    m = sym_pose_metrics("x", T_est, T_TRUE, sym)
    assert m["x_rot_sym_deg"] < 0.01 and m["x_trans_sym_mm"] < 1e-6
    assert m["x_mssd_mm"] < 0.05


def test_the_spin_is_forgiven_not_the_tilt(meshes):
    """About an axis of revolution the error left is the angle between the axis as each pose
    places it; a box turned a quarter (no symmetry of a 9 x 6 cm box) keeps its error."""
    _, can = meshes["can"]
    tilt = _about(can, [np.radians(10.0), 0.0, 0.0])
    T_est = T_TRUE @ tilt @ _about(can, [0.0, 0.0, 0.9])
    assert abs(rotation_error_sym_deg(T_est, T_TRUE, can) - 10.0) < 1e-3  # the fitted axis
    assert pose_error(T_est, T_TRUE)[0] > 45
    _, box = meshes["box"]
    T_est = T_TRUE @ _about(box, [0.0, 0.0, np.pi / 2])
    assert abs(rotation_error_sym_deg(T_est, T_TRUE, box) - 90.0) < 1e-6
    assert surface_errors_mm(T_est, T_TRUE, box)["mssd_mm"] > 10


def test_an_object_without_symmetry_scores_as_raw(meshes):
    _, mug = meshes["mug"]
    rng = np.random.default_rng(3)
    for _ in range(5):
        T_est = T_TRUE @ from_rotvec(rng.normal(0, 0.5, 3), rng.normal(0, 0.01, 3))
        raw_deg, _ = pose_error(T_est, T_TRUE)
        assert abs(rotation_error_sym_deg(T_est, T_TRUE, mug) - raw_deg) < 1e-6
        # MSSD of a lone identity is the largest displacement of a sample
        moved = np.linalg.norm((T_est[:3, :3] - T_TRUE[:3, :3]) @ mug.points[:1000].T
                               + (T_est[:3, 3] - T_TRUE[:3, 3])[:, None], axis=0)
        m = surface_errors_mm(T_est, T_TRUE, mug)
        assert abs(m["mssd_mm"] - 1e3 * moved.max()) < 1e-6


def test_per_frame_errors_forgive_a_cans_spin_and_keep_the_raw_ones(tmp_path):
    """The evaluation's per-frame object errors, raw and symmetry-aware, on a can whose pose
    is found spun about its axis in every frame and 2 mm off."""
    can = scaled_object(procedural_object("can"), 0.125)
    write_object(can, tmp_path / "object.ply")
    sym = find_symmetries(tmp_path / "object.ply")
    assert find_symmetries(tmp_path / "object.ply") is sym  # cached per file
    rng = np.random.default_rng(4)
    T_w_c = np.stack([from_rotvec(rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3))
                      for _ in range(6)])  # fmt: skip
    truth = {"steady_from": 10, "T_w_c": T_w_c, "T_adj": np.eye(4), "T_w_o_stage1": T_TRUE}
    shift = make_T(np.eye(3), [0.002, 0.0, 0.0])
    T_c_o = np.stack([np.linalg.inv(T) @ T_TRUE @ shift @ _about(sym, [0.0, 0.0, 2.0])
                      for T in T_w_c])  # fmt: skip
    out = _per_frame_object_errors(np.arange(10, 16), T_c_o, truth,
                                   (sym, surface_scene(tmp_path / "object.ply")))
    # the raw rotation error is the spin; the can's origin (its base's centre) is on its axis
    assert out["frame_object_rot_deg"] > 100 and abs(out["frame_object_trans_mm"] - 2.0) < 0.05
    assert out["frame_object_rot_sym_deg"] < 0.01
    assert abs(out["frame_object_trans_sym_mm"] - 2.0) < 1e-6
    assert 1.9 < out["frame_object_mssd_mm"] < 2.1 and out["frame_object_adds_mm"] < 2.0
    assert "frame_object_rot_sym_p95_deg" in out and "frame_object_trans_sym_p95_mm" in out


@pytest.mark.parametrize("name, rotvec", [
    ("can", [0.0, 0.0, 1.3]), ("can", [np.pi, 0.0, 0.0]), ("box", [0.0, np.pi, 0.0]),
    ("ball", [1.2, -0.5, 0.8]), ("mug", [0.0, 0.0, 0.4]),
])
def test_closest_symmetry_is_the_turn_the_estimate_made(meshes, name, rotvec):
    """The element that carries the estimate's frame into the truth's: the turn itself where
    it is a symmetry (a small tilt on top is left out), the identity for a mug's spin."""
    _, sym = meshes[name]
    tilt = _about(sym, [0.0, np.radians(2.0), 0.0])
    T_est = T_TRUE @ _about(sym, rotvec) @ tilt
    R = closest_symmetry(T_est, T_TRUE, sym)
    expected = np.eye(3) if name == "mug" else _about(sym, rotvec)[:3, :3]
    if name == "ball":  # every rotation is a symmetry: the tilt is part of it
        expected = expected @ tilt[:3, :3]
    assert np.abs(R - expected).max() < 1e-6
    assert abs(rotation_error_sym_deg(T_est, T_TRUE, sym)
               - (2.0 if name in ("can", "box") else 0.0 if name == "ball"
                  else pose_error(T_est, T_TRUE)[0])) < 1e-3  # fmt: skip


def _spun_session(tmp_path, name, spin_rad):
    """A session folder with ``name``'s mesh, its true contact on one side, and an estimate
    whose object frame is the truth's turned ``spin_rad`` about the vertical axis (grasp poses,
    contact map and hand all in that frame): what a pipeline that resolved every relation but
    an unseen spin returns."""
    obj = scaled_object(procedural_object(name), 0.12)
    write_object(obj, tmp_path / "object.ply")
    (tmp_path / "session.json").write_text('{"object_mesh": "object.ply"}')
    sym = find_symmetries(tmp_path / "object.ply")
    V = np.asarray(obj.vertices, float)
    truth_contact = (V[:, 0] - sym.centroid[0] > 0.02).astype(float)
    (tmp_path / "ground_truth").mkdir()
    np.save(tmp_path / "ground_truth" / "contact.npy", truth_contact)
    S = _about(sym, [0.0, 0.0, spin_rad])  # a point x of the estimate's frame is S x of the truth
    T_w_c = np.stack([from_rotvec([0.1 * k, 0.0, 0.0], [0.0, 0.0, 0.0]) for k in range(4)])
    truth = {"steady_from": 5, "T_w_c": T_w_c, "T_adj": np.eye(4), "T_w_o_stage1": T_TRUE}
    T_c_o = np.stack([np.linalg.inv(T) @ T_TRUE @ S for T in T_w_c])
    from scipy.spatial import cKDTree
    est_contact = truth_contact[cKDTree(V).query((V - sym.centroid) @ S[:3, :3].T
                                                 + sym.centroid)[1]]  # fmt: skip
    return sym, truth, T_c_o, est_contact, S


def test_contact_is_scored_in_the_estimates_frame_of_a_symmetric_object(tmp_path):
    """A can found spun 90 deg about its axis, its contact map and grasp in the same spun frame:
    the contact IoU under the grasp's symmetry is whole, the raw one is not; the contacted
    vertices carried into the estimate's frame lie on a hand placed there."""
    sym, truth, T_c_o, est_contact, S = _spun_session(tmp_path, "can", np.pi / 2)
    found = grasp_symmetry(np.arange(5, 9), T_c_o, truth, sym)
    assert found is not None and np.abs(found - S).max() < 1e-6
    observed = np.ones(len(est_contact), bool)
    aligned = _contact_metrics(est_contact, observed, tmp_path, found)
    raw = _contact_metrics(est_contact, observed, tmp_path)
    assert aligned["contact_iou"] > 0.95 and raw["contact_iou"] < 0.3
    # a "hand" that is the contacted surface itself, moved into the estimate's frame
    obj = trimesh.load(tmp_path / "object.ply", process=False)
    hand = obj.copy()
    hand.apply_transform(np.linalg.inv(S))
    keep = np.load(tmp_path / "ground_truth" / "contact.npy")[hand.faces].min(1) > 0.4
    est = {"hand_vertices_o": hand.vertices, "hand_faces": hand.faces[keep]}
    assert _refinement_metrics(est, tmp_path, found)["contact_near_hand_refined"] > 0.99
    assert _refinement_metrics(est, tmp_path)["contact_near_hand_refined"] < 0.5


def test_an_object_without_symmetry_is_scored_in_its_own_frame(tmp_path):
    sym, truth, T_c_o, _, _ = _spun_session(tmp_path, "mug", 0.3)
    assert grasp_symmetry(np.arange(5, 9), T_c_o, truth, sym) is None
