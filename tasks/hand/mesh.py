"""Closed, outward-facing template surfaces for the hand model's parts.

Every part of :mod:`graspcap.tasks.hand.model` is the convex hull of a few
spheres: a phalanx is a tapered capsule (the hull of one sphere at each joint),
the palm a rounded slab (the hull of spheres at the wrist, the thumb base, the
mid palm and the knuckles). A convex hull is closed and its faces point
outwards, which ray casting and signed distances need. Templates are built once
in the part's own frame; posing a hand only transforms them.
"""

from __future__ import annotations

import numpy as np

# trimesh: imported where used, so that importing the stage table stays cheap


def _unit_sphere(subdivisions: int) -> np.ndarray:
    """Vertices (n, 3) of an icosphere of radius 1, circumscribing its faces.

    The vertices are pushed out so that the flat faces, not only the vertices,
    sit at about the sphere's radius (at ``subdivisions=2`` the inscribed faces
    would lie up to 1% of the radius inside).
    """
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    centres = sphere.triangles_center
    mean_face_radius = float(np.linalg.norm(centres, axis=1).mean())
    return np.asarray(sphere.vertices) / mean_face_radius


def sphere_hull(
    centres: np.ndarray, radii: np.ndarray, subdivisions: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of spheres: a closed, outward-facing, rounded solid.

    Parameters
    ----------
    centres : (k, 3) float
        Sphere centres, metres.
    radii : (k,) float
        Sphere radii, metres.
    subdivisions : int
        Icosphere subdivision level of each sampled sphere.

    Returns
    -------
    vertices : (n, 3) float
    faces : (m, 3) int
        Counter-clockwise seen from outside (positive volume).
    """
    import trimesh

    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    radii = np.asarray(radii, dtype=float).reshape(-1)
    unit = _unit_sphere(subdivisions)
    samples = (centres[:, None, :] + radii[:, None, None] * unit[None]).reshape(-1, 3)
    hull = trimesh.convex.convex_hull(samples)
    trimesh.repair.fix_normals(hull)
    return np.asarray(hull.vertices, dtype=float), np.asarray(hull.faces, dtype=np.int64)


def tapered_capsule(
    length_m: float, radius_start_m: float, radius_end_m: float, subdivisions: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """A capsule along +y from the origin to ``(0, length_m, 0)`` with a radius per end.

    The hull of two spheres: the distance from either end point to the surface
    is that end's radius, which is what makes a joint centre lie exactly one
    radius under the skin.

    Returns
    -------
    vertices : (n, 3) float
    faces : (m, 3) int
    """
    centres = np.array([[0.0, 0.0, 0.0], [0.0, float(length_m), 0.0]])
    return sphere_hull(centres, np.array([radius_start_m, radius_end_m]), subdivisions)
