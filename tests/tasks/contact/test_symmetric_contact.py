"""The contact map of a symmetric object carried into the grasp's frame
(``graspcap.tasks.contact.symmetric_contact``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from graspcap.synth.objects import procedural_object, scaled_object
from graspcap.tasks.contact import symmetric_contact
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


def test_the_depth_sees_the_surface_bare_where_the_hand_is_not():
    """A can 0.6 m in front of the camera with a finger-sized box across its front: the
    vertices behind the box are covered, the rest of its front bare, its back never seen, and
    the window keeps the front's vertices beside the box from counting bare (nor covered)."""
    import trimesh

    from graspcap.tasks.core.geometry import make_T
    from graspcap.tasks.core.render import render

    V, F = _object("can", 0.125)
    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    c = V.mean(axis=0)
    # the can's axis (object z) along the image's y, its centre 0.6 m away on the optical axis
    R = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    T = make_T(R, np.array([0.0, 0.0, 0.6]) - R @ c)
    box = trimesh.creation.box([0.2, 0.015, 0.01])
    finger = make_T(np.eye(3), [0.0, 0.0, 0.6 - 0.033 - 0.006])  # just in front of the can
    hits = render([(V, F), (np.asarray(box.vertices), np.asarray(box.faces))], [T, finger],
                  K, 640, 480)
    share = symmetric_contact.bare_share(V, F, [T], [hits.depth_m], K, bare_m=0.006)
    P = transform_points(T, V)
    front = P[:, 2] < 0.6 - 0.02  # facing the camera, well before the silhouette
    behind = front & (np.abs(P[:, 1]) < 0.004)  # hidden by the finger
    assert np.all(share[behind] == 0.0)
    bare = front & (np.abs(P[:, 1]) > 0.02)
    seen = share[bare][~np.isnan(share[bare])]  # grazing rims may go unseen
    assert np.all(seen == 1.0) and len(seen) > 0.85 * bare.sum()
    assert np.all(np.isnan(share[P[:, 2] > 0.6 + 0.01]))  # the back
    windowed = symmetric_contact.bare_share(V, F, [T], [hits.depth_m], K, bare_m=0.006,
                                            window_px=3)
    beside = front & (np.abs(P[:, 1]) > 0.009) & (np.abs(P[:, 1]) < 0.011)  # 1-3 px away
    assert np.mean(share[beside] == 1.0) > 0.9 and np.all(np.isnan(windowed[beside]))


def test_the_bare_surface_places_a_map_the_hand_cannot():
    """A hand wrapped all round a can is as near every spin of its contact patch: the hand
    alone leaves the map as the scan registered it; the grasp's depth, bare everywhere but
    under the patch's true place (and never seeing the can's ends), turns it there."""
    V, F = _object("can", 0.125)
    cmap, hand = _map_and_hand(V, F, 120.0)
    model = prepare_model(V, F, RegistrationConfig())
    c = model.centroid
    band = np.abs(V[:, 2] - c[2]) < 0.03
    ring = V[band]  # the hand: every side of the patch's height
    assert align_to_hand(V, F, cmap, ring, **ALIGN) is cmap
    patch_grasp = cKDTree(hand).query(V)[0] <= 0.006  # under the patch, the grasp's frame
    bare = np.where(patch_grasp, 0.0, 1.0)
    bare[np.abs(V[:, 2] - c[2]) > 0.05] = np.nan  # the ends never seen
    out = align_to_hand(V, F, cmap, ring, **ALIGN, bare=lambda: bare)
    assert out.turned_deg > 90  # 120 deg, or the end-for-end flip that lands it there too
    assert _on_hand(out, V, hand) > 0.8
