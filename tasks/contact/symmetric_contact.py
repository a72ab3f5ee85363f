"""The contact map of a symmetric object carried into the grasp's object frame.

The thermal scan and the grasp are registered separately (``register_scan``,
``register_object`` and ``estimate_adjustment``). On an object that a turn maps onto itself
(a bulb, a glass, a ball, a can, a box's half turn), the depth of each cannot tell the turn,
so the two registrations may settle on different ones: the contact map then lies where the
hand is not (wild ``[94397, 4]``, a bulb: the grasp spun 109 deg, the map right in the mesh's
own frame, so its IoU with the true contact in the grasp's frame 0.03; tuning). Every relation a
user trains on (which vertex the hand touches) needs both in one frame.

:func:`symmetric_motions` finds the turns about the object's centroid that map its surface
onto itself (within ``tolerance_m``: spins about an axis of revolution, the tracking's test;
half turns about its own flip axes and n-fold turns about its principal axes; every rotation
for a ball); :func:`align_to_hand` scores each by the
contacted vertices' nearness to the fitted hand, less how often the grasp's depth saw them
bare (:func:`bare_share`: a vertex under a finger is never seen without the hand in front of
it), and, where the best turn beats the scan's own frame clearly (by ``margin``, and ``ratio``
times), carries the map (every per-vertex field, each vertex taking the value of the vertex
nearest its image) into the grasp's frame. An object without such a turn is left as the scan
made it.

The fitted hand alone is a weak witness at real-detector noise: its joints are ~10 mm off,
about a quarter turn of a 7 cm glass's rim, and a hand wrapped round the object is near most
of it. The depth's bare surface is measured, not fitted, and says where the hand is not (wild,
20 symmetric objects held out, ``[52817, i]``: contact IoU median 0.11 -> 0.36, 8 better, none
worse; ``docs/benchmarks.md``, "Session 29").
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from graspcap.tasks.contact.build_contactmap import ContactMap
from graspcap.tasks.core.geometry import inv_T, make_T, rotation_error_deg, transform_points
from graspcap.tasks.core.render import mesh_scene
from graspcap.tasks.object_pose.registration.engine import (
    RegistrationConfig,
    prepare_model,
    strided,
    surface_distance,
)
from graspcap.tasks.object_pose.registration.symmetry import about_axis, self_flip_axes

# scipy: imported where used

SPIN_STEP_DEG = 5.0
"""Turns about an axis of revolution tried every this many degrees."""
SPHERE_ROTATIONS = 4000
"""Rotations tried for a ball (uniform over all rotations, pseudo-random with a fixed seed:
half of all rotations lie within 8.5 deg of one of them); the best one is then refined by
turns of 4, 2 and 1 deg about the three axes."""
MAX_SCORED_POINTS = 600
"""Contacted vertices scored per turn (an even stride of them)."""


def _keeps(model, T: np.ndarray, tolerance_m: float, pts: np.ndarray) -> bool:
    return float(surface_distance(model, transform_points(T, pts)).max()) <= tolerance_m


def symmetric_motions(vertices: np.ndarray, faces: np.ndarray, tolerance_m: float
                      ) -> tuple[str, list[np.ndarray]]:
    """(kind, motions): the object-frame motions (4, 4) about the surface's centroid that move
    no sampled surface point more than ``tolerance_m`` off the surface, the identity first;
    kind is ``"sphere"``, ``"axis"``, ``"discrete"`` or ``"none"`` (only the identity)."""
    from scipy.spatial.transform import Rotation

    model = prepare_model(vertices, faces, RegistrationConfig())
    pts = np.asarray(strided(model.dense, 800).points)
    c = model.centroid
    turns = np.radians(np.arange(30.0, 360.0, 30.0))
    axes = [model.axes[:, k] / np.linalg.norm(model.axes[:, k]) for k in range(3)]
    revolving = [a for a in axes
                 if all(_keeps(model, about_axis(model, a, t), tolerance_m, pts) for t in turns)]
    if len(revolving) >= 2:
        R = Rotation.random(SPHERE_ROTATIONS, random_state=0).as_matrix()
        return "sphere", [np.eye(4)] + [make_T(r, c - r @ c) for r in R]
    half_turns = [about_axis(model, f, np.pi) for f in self_flip_axes(model, count=3)]
    flips = [T for T in half_turns if _keeps(model, T, tolerance_m, pts)]
    if revolving:
        a = revolving[0]
        ends = [np.eye(4)] + [T for T in flips if abs(_axis_of(T) @ a) < 0.2][:1]
        spins = [about_axis(model, a, np.radians(t)) for t in np.arange(0.0, 360.0, SPIN_STEP_DEG)]
        return "axis", [S @ D for D in ends for S in spins]
    group = [np.eye(4)] + flips
    for a in axes:  # n-fold turns about a principal axis (a glass whose foot breaks the spin)
        for n in (3, 4, 6):
            T = about_axis(model, a, 2 * np.pi / n)
            if _keeps(model, T, tolerance_m, pts):
                group += [np.linalg.matrix_power(T, k) for k in range(1, n)]
    while True:  # closed under products (a box's third half turn)
        new = [A @ B for A in group for B in group]
        new = [T for T in new if all(rotation_error_deg(T[:3, :3], G[:3, :3]) > 1.0
                                     for G in group)]
        if not new or len(group) >= 48:
            break
        group.append(new[0])
    return ("discrete" if len(group) > 1 else "none"), group


def _axis_of(T: np.ndarray) -> np.ndarray:
    """The unit axis of the rotation of ``T`` (4, 4)."""
    from scipy.spatial.transform import Rotation

    v = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _refined(score, S: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``S`` turned about the centroid by 4, 2, then 1 deg about each axis while the score
    grows (a ball's best rotation between the sampled ones)."""
    from scipy.spatial.transform import Rotation

    best = score(S)
    for step in np.radians([4.0, 2.0, 1.0]):
        grew = True
        while grew:
            grew = False
            for axis in np.eye(3):
                for sign in (1.0, -1.0):
                    r = Rotation.from_rotvec(sign * step * axis).as_matrix()
                    T = make_T(r, c - r @ c) @ S
                    s = score(T)
                    if s > best:
                        S, best, grew = T, s, True
    return S


def bare_share(vertices: np.ndarray, faces: np.ndarray, T_c_o: Sequence[np.ndarray],
               depths: Sequence[np.ndarray], K: np.ndarray, *, bare_m: float,
               window_px: int = 0, visible_m: float = 0.002) -> np.ndarray:
    """Per vertex (n,), the share of the frames that saw it in which the depth saw it bare:
    of the frames where the vertex faces the camera unhidden by the object itself (the ray to
    it first hits the mesh within ``visible_m`` of it) and the depth has a reading at its pixel,
    those where the reading lies within ``bare_m`` of it and no reading within ``window_px``
    pixels lies more than ``bare_m`` in front of it (the rim of a finger lying on the surface
    reads within ``bare_m`` of it), against those where the reading lies more than ``bare_m`` in
    front (the hand, or anything else, covers it); NaN where no frame saw it.

    ``T_c_o`` (m, 4, 4): the object's pose in each frame's colour camera, ``depths``: those
    frames' depth (h, w) metres aligned to it (ideal pixels, 0 = none), ``K`` (3, 3)."""
    import open3d as o3d

    V = np.asarray(vertices, dtype=float)
    scene = mesh_scene(V, faces)
    bare, covered = np.zeros(len(V)), np.zeros(len(V))
    for T, depth in zip(T_c_o, depths, strict=True):
        depth = np.asarray(depth, dtype=np.float32)
        h, w = depth.shape
        nearest = depth
        if window_px > 0:  # the nearest reading around each pixel (no reading: none)
            import cv2

            size = 2 * window_px + 1
            nearest = cv2.erode(np.where(depth > 0, depth, np.inf).astype(np.float32),
                                np.ones((size, size), np.uint8))
        eye = inv_T(T)[:3, 3]  # the camera centre, object frame
        ray = V - eye
        dist = np.linalg.norm(ray, axis=1)
        rays = np.hstack([np.broadcast_to(eye, V.shape), ray / dist[:, None]])
        hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
        P = transform_points(T, V)
        z = P[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(P[:, 0] / z * K[0, 0] + K[0, 2])
            v = np.round(P[:, 1] / z * K[1, 1] + K[1, 2])
        seen = (np.abs(hit - dist) <= visible_m) & (z > 0) & (u >= 0) & (u < w) & (v >= 0) \
            & (v < h)
        reading, near = np.zeros(len(V)), np.zeros(len(V))
        px = v[seen].astype(int), u[seen].astype(int)
        reading[seen], near[seen] = depth[px], nearest[px]
        seen &= reading > 0
        bare += seen & (np.abs(reading - z) <= bare_m) & (near >= z - bare_m)
        covered += seen & (reading < z - bare_m)
    looked = bare + covered
    with np.errstate(invalid="ignore"):
        return np.where(looked > 0, bare / looked, np.nan)


def tracked_bare_share(vertices: np.ndarray, faces: np.ndarray, T_c_o: np.ndarray,
                       tracked: np.ndarray, K: np.ndarray, read_depth: Callable[[int], np.ndarray],
                       *, frames: int, bare_m: float, window_px: int) -> np.ndarray | None:
    """:func:`bare_share` over up to ``frames`` of the steady frames the object was tracked in
    (their poses supported by their own depth), evenly spread: ``T_c_o`` (m, 4, 4) and
    ``tracked`` (m,) per steady frame, ``read_depth(j)`` steady frame ``j``'s depth (ideal
    pixels). None when ``frames`` is 0 or no frame was tracked."""
    rows = np.flatnonzero(tracked)
    if frames <= 0 or len(rows) == 0:
        return None
    rows = rows[np.unique(np.linspace(0, len(rows) - 1, frames).round().astype(int))]
    return bare_share(vertices, faces, np.asarray(T_c_o)[rows], [read_depth(j) for j in rows],
                      K, bare_m=bare_m, window_px=window_px)


def align_to_hand(vertices: np.ndarray, faces: np.ndarray, contact_map: ContactMap,
                  hand_vertices_o: np.ndarray, *, tolerance_m: float, near_mm: float,
                  margin: float, ratio: float, contact_threshold: float,
                  bare: Callable[[], np.ndarray | None] | None = None) -> ContactMap:
    """``contact_map`` carried into the frame of the hand ``hand_vertices_o`` (k, 3, object
    frame, the fitted hand) by the object's symmetry that scores best, where that score beats
    the scan's own frame's by ``margin`` and is ``ratio`` times it; else ``contact_map`` itself
    (module docstring). A turn's score is the mean over the contacted observed vertices, carried
    into the grasp's frame, of their nearness to the hand (1 on it, falling to 0 at
    ``near_mm``) less, with ``bare`` (called only for a symmetric object; (n,) or None), the share
    of the grasp's frames that saw the vertex there bare (:func:`bare_share`, grasp's object
    frame; NaN counts 0)."""
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, dtype=float)
    on = np.flatnonzero(contact_map.observed & (contact_map.contact >= contact_threshold))
    if len(on) == 0 or len(hand_vertices_o) == 0:
        return contact_map
    kind, motions = symmetric_motions(V, faces, tolerance_m)
    if kind == "none":
        return contact_map
    hand = cKDTree(np.asarray(hand_vertices_o, dtype=float))
    vertex = cKDTree(V)
    seen = None if bare is None else bare()
    seen_bare = np.zeros(len(V)) if seen is None else np.nan_to_num(np.asarray(seen, float))
    y = V[on][:: -(-len(on) // MAX_SCORED_POINTS)]  # the contacted vertices, scan frame

    def score(S: np.ndarray) -> float:
        # S maps the grasp's frame into the scan's: a contact at y sits at S^-1 y for the hand;
        # each counts 1 on the hand's surface samples, falling to 0 at near_mm, less how often
        # the depth saw the vertex there bare
        x = (y - S[:3, 3]) @ S[:3, :3]
        d = hand.query(x, distance_upper_bound=1e-3 * near_mm)[0]
        near = np.clip(1.0 - d / (1e-3 * near_mm), 0.0, 1.0)
        return float(np.mean(near - seen_bare[vertex.query(x)[1]]))

    scores = np.array([score(S) for S in motions])
    best = int(np.argmax(scores))
    S = motions[best]
    if kind == "sphere":
        S = _refined(score, S, prepare_model(V, faces, RegistrationConfig()).centroid)
    own, found = float(scores[0]), score(S)
    if found < own + margin or found < ratio * own:
        return contact_map
    turned = rotation_error_deg(np.eye(3), S[:3, :3])
    src = vertex.query(transform_points(S, V))[1]  # each vertex's image, scan frame
    witness = ("" if seen is None else
               ", less the share of the grasp's depth frames that saw them bare")
    note = (f"the object is symmetric ({kind}): the scan's contact map turned {turned:.0f} deg "
            f"into the grasp's frame, where its contacted vertices score {found:.2f} against "
            f"the fitted hand ({own:.2f} as the scan registered it; their nearness to it, 1 on "
            f"it, 0 beyond {near_mm:g} mm{witness})")
    return replace(
        contact_map, contact=contact_map.contact[src], observed=contact_map.observed[src],
        n_views_seen=contact_map.n_views_seen[src], temperature_k=contact_map.temperature_k[src],
        turned_deg=float(turned), notes=contact_map.notes + (note,),
    )  # fmt: skip
