"""The contact map of a symmetric object carried into the grasp's frame
(``graspcap.tasks.contact.symmetric_contact``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from graspcap.synth.objects import procedural_object, scaled_object
from graspcap.tasks.contact.build_contactmap import ContactMap
from graspcap.tasks.contact.symmetric_contact import align_to_hand, symmetric_motions
from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.object_pose.registration.engine import RegistrationConfig, prepare_model
from graspcap.tasks.object_pose.registration.symmetry import about_axis

ALIGN = {"tolerance_m": 0.005, "near_mm": 10.0, "margin": 0.15, "ratio": 2.0,
         "contact_threshold": 0.4}


def _object(name: str, extent_m: float):
    o = scaled_object(procedural_object(name), extent_m)
    return np.asarray(o.vertices, float), np.asarray(o.faces, np.int64)


@pytest.mark.parametrize("name, kind", [
    ("can", "axis"), ("ball", "sphere"), ("mug", "none"), ("remote", "discrete"),
])
def test_the_turns_that_map_an_object_onto_itself(name, kind):
    """A can spins about its axis (and flips end for end), a ball turns every way, a remote
    has its half turns, a mug (handle) has none but the identity, which always comes first."""
    V, F = _object(name, {"ball": 0.07, "remote": 0.16}.get(name, 0.12))
    found, motions = symmetric_motions(V, F, 0.005)
    assert found == kind
    assert np.allclose(motions[0], np.eye(4))
    if kind == "axis":
        assert len(motions) == 2 * 72  # 5 deg spins, both ends
    if kind == "discrete":
        assert 2 <= len(motions) <= 8


def _map_and_hand(V, F, spin_deg: float):
    """A contact patch on one side of the object as the scan registered it, and a hand (the
    patch's points with 2 mm of noise) where the grasp's frame, turned ``spin_deg`` about the
    object's vertical principal axis, puts it."""
    model = prepare_model(V, F, RegistrationConfig())
    axis = model.axes[:, int(np.argmax(np.abs(model.axes[2])))]
    c = model.centroid
    patch = (V[:, 0] - c[0] > 0.8 * np.ptp(V[:, 0]) / 2) & (np.abs(V[:, 2] - c[2]) < 0.03)
    contact = np.where(patch, 0.9, 0.0).astype(np.float32)
    observed = np.ones(len(V), bool)
    cmap = ContactMap(contact=contact, observed=observed, n_views_seen=observed.astype(int),
                      temperature_k=295.0 + 4 * contact, ambient_k=295.0, full_rise_k=4.0,
                      all_ambient=False, per_view_visible=np.array([len(V)]), coverage=1.0,
                      n_degenerate_faces=0)  # fmt: skip
    S = about_axis(model, axis, np.radians(spin_deg))  # the grasp's frame into the scan's
    rng = np.random.default_rng(0)
    hand = transform_points(inv_T(S), V[patch]) + rng.normal(0, 0.002, (patch.sum(), 3))
    return cmap, hand


def _on_hand(cmap: ContactMap, V, hand, within_m=0.005) -> float:
    on = cmap.contact >= 0.4
    return float(np.mean(cKDTree(hand).query(V[on])[0] <= within_m))


def test_a_cans_map_is_turned_to_the_hand():
    V, F = _object("can", 0.125)
    cmap, hand = _map_and_hand(V, F, 120.0)
    assert _on_hand(cmap, V, hand) < 0.2
    out = align_to_hand(V, F, cmap, hand, **ALIGN)
    assert abs(out.turned_deg - 120.0) <= 5.0
    assert _on_hand(out, V, hand) > 0.9
    assert out.notes and "turned 120 deg" in out.notes[-1]
    assert out.observed.all() and np.allclose(out.temperature_k, 295.0 + 4 * out.contact)


def test_a_map_already_on_the_hand_and_an_asymmetric_object_stay():
    V, F = _object("can", 0.125)
    cmap, hand = _map_and_hand(V, F, 0.0)
    assert align_to_hand(V, F, cmap, hand, **ALIGN) is cmap
    V, F = _object("mug", 0.13)
    cmap, hand = _map_and_hand(V, F, 0.0)
    assert align_to_hand(V, F, cmap, hand + [0.0, 0.05, 0.0], **ALIGN) is cmap


def test_a_balls_map_finds_the_hand():
    V, F = _object("ball", 0.07)
    cmap, hand = _map_and_hand(V, F, 120.0)
    out = align_to_hand(V, F, cmap, hand, **ALIGN)
    assert out.turned_deg > 90
    assert _on_hand(out, V, hand, within_m=0.008) > 0.8


@pytest.mark.parametrize("path, kind", [
    ("ycb_meshes/YcbTomatoSoupCan/textured_simple_reoriented.obj", "axis"),
    ("meshes_trimesh/bunny.ply", "none"),
])
def test_scanned_meshes(shared_data, path, kind):
    """Real scans: YCB's soup can is a body of revolution within 5 mm, the Stanford bunny has
    no symmetry."""
    import trimesh

    mesh = trimesh.load(shared_data / path, force="mesh", process=False)
    found, _ = symmetric_motions(np.asarray(mesh.vertices, float), np.asarray(mesh.faces), 0.005)
    assert found == kind
