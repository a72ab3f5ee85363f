"""Symmetries of an object mesh, found from the mesh itself, and pose errors that do not count
a pose one of them maps onto the truth (synthetic evaluation only).

A ball whose centre is right but whose spin is not looks the same to every sensor; an error
on it is not one the pipeline could avoid. The pose-estimation field scores such objects
over their symmetry group (the BOP challenge's MSSD and symmetry-aware rotation error; ADD-S
of the YCB benchmarks), with the symmetries declared within a tolerance even where a small
feature (a ball's valve, a can's pull tab) breaks them. This module does that without object
labels (a session may come from another generator): :func:`find_symmetries` tests rotations
about the mesh's principal axes through its centroid and keeps those that leave the surface
within :data:`SYMMETRY_TOLERANCE_M`.

A symmetry here is a rotation ``S`` about the centroid ``c`` (``x -> c + R_S (x - c)``) with
``S(M) ~ M``; the group is ``{R_a(theta) D_j}``: a continuous rotation about one axis ``a``
(a body of revolution) composed with a finite set ``D`` (the identity, a flip of a can's
axis, a box's half turns), or every rotation (a sphere).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.tasks.core.geometry import inv_T, rotation_error_deg, transform_points

# trimesh, open3d, scipy: imported where used (the evaluation module stays cheap to import)

SYMMETRY_TOLERANCE_M = 0.005
"""A rotation is a symmetry when it moves no sampled surface point farther than this from the
surface (BOP's maximum surface distance of the rotated mesh against itself). 5 mm, fixed rather
than relative to the object's size, because what hides a feature is the depth sensor's noise,
which does not scale with the object: 5 mm is 2 sigma of the wild profile's axial depth noise
(2.5 mm), and under ``GOOD_IF``'s per-frame translation tolerance (6 mm), so a pose a symmetry
maps onto the truth is within the good tolerance on every surface point anyway. Measured on the
procedural objects over their extent ranges: ball (valve) 3.0-4.6 mm about every axis, bulb
(seal, nub) 2.3-4.1 mm and can (tab) 1.4-2.3 mm about their axes (the can also flips end for
end), glass (chipped foot) 3.9-5.5 mm, remote (button pad) 1.1-2.2 mm for its half turns,
small box (flap) 3.3-5.3 mm for its half turn about its height: symmetric, mostly; bottle
(cap 6 mm off its axis, label) 6-11 mm, carton (spout) 9-17 mm, mug (handle) > 15 mm: not. A
size-relative tolerance cannot separate them (ball 4.6 % of its extent, bottle 3.8 %)."""

N_SAMPLES = 4000
"""Surface samples (area-uniform, fixed seed) the symmetry test and the surface distances use."""

MSSD_SAMPLES = 1000
"""The first this many samples (a uniform subset) give MSSD and ADD-S (once per frame)."""

_DISCRETE_ORDERS = (2, 3, 4, 6)
"""n-fold turns tested about each principal axis that is not an axis of revolution."""


@dataclass(frozen=True)
class Symmetries:
    """The symmetry group of a mesh (module docstring).

    Attributes
    ----------
    centroid : (3,) float
        Area-weighted centroid of the surface, object frame, metres: every symmetry fixes it.
    axis : (3,) float or None
        Unit axis of the continuous rotation (a body of revolution), object frame.
    sphere : bool
        Every rotation about the centroid is a symmetry.
    discrete : (k, 3, 3) float
        Rotations ``D_j`` composed after the continuous one, the identity first.
    points : (n, 3) float
        Surface samples, object frame, metres (for MSSD).
    """

    centroid: np.ndarray
    axis: np.ndarray | None
    sphere: bool
    discrete: np.ndarray
    points: np.ndarray

    def describe(self) -> str:
        """A short text: ``sphere``, ``axis (x, y, z) + 2 discrete``, ``4 discrete``, ``none``."""
        if self.sphere:
            return "sphere"
        extra = f"{len(self.discrete)} discrete" if len(self.discrete) > 1 else ""
        if self.axis is not None:
            return f"axis {np.round(self.axis, 2).tolist()}" + (f" + {extra}" if extra else "")
        return extra or "none"


def _skew(a: np.ndarray) -> np.ndarray:
    """(3, 3) cross-product matrix of ``a`` (3,): ``_skew(a) @ x == np.cross(a, x)``."""
    return np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])


def _rot(axis: np.ndarray, angle_rad: float | np.ndarray) -> np.ndarray:
    """(3, 3) rotation(s) about unit ``axis`` (Rodrigues); a vector of angles gives (m, 3, 3)."""
    K = _skew(np.asarray(axis, dtype=float))
    th = np.asarray(angle_rad, dtype=float)[..., None, None]
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def _deviation_m(scene: Any, points: np.ndarray, centroid: np.ndarray, R: np.ndarray) -> float:
    """Largest distance from the samples rotated by ``R`` about ``centroid`` to the surface."""
    import open3d as o3d

    moved = ((points - centroid) @ R.T + centroid).astype(np.float32)
    return float(scene.compute_distance(o3d.core.Tensor(moved)).numpy().max())


def find_symmetries_of(vertices: np.ndarray, faces: np.ndarray,
                       tolerance_m: float = SYMMETRY_TOLERANCE_M) -> Symmetries:
    """The symmetries of a triangle mesh (vertices (n, 3) m, faces (m, 3)): candidate axes are
    the principal axes of the surface about its centroid; an axis is one of revolution when
    turns of 15, 30, ... 345 deg about it all keep the surface within ``tolerance_m``; three
    such axes make a sphere; about an axis of revolution a half turn about a perpendicular
    principal axis is tested (a can's flip); otherwise 2, 3, 4 and 6-fold turns about each
    principal axis, the closest first, each joining with the products it makes with those kept
    when all of them keep the surface (so the result is a group)."""
    import open3d as o3d
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64),
                           process=False)
    points = np.asarray(trimesh.sample.sample_surface(mesh, N_SAMPLES, seed=0)[0], float)
    centroid, axes = _principal_axes(mesh.vertices[mesh.faces])
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(vertices, np.float32), np.asarray(faces, np.uint32))

    def keeps(R: np.ndarray) -> bool:
        return _deviation_m(scene, points, centroid, R) <= tolerance_m

    turns = np.radians(np.arange(15, 360, 15))
    revolving = [k for k in range(3) if all(keeps(R) for R in _rot(axes[:, k], turns))]
    if len(revolving) == 3:
        return Symmetries(centroid, None, True, np.eye(3)[None], points)
    axis = _refined_axis(scene, points, centroid, axes[:, revolving[0]]) if revolving else None
    if axis is not None:
        # the principal axis of revolution is the one whose moment differs; any perpendicular
        # axis is equivalent for the flip (the body is the same about all of them)
        other = axes[:, (revolving[0] + 1) % 3]
        other = other - (other @ axis) * axis
        other /= np.linalg.norm(other)
        flip = _rot(other, np.pi)
        return Symmetries(centroid, axis, False,
                          np.stack([np.eye(3)] + ([flip] if keeps(flip) else [])), points)
    candidates = [R for k in range(3) for n in _DISCRETE_ORDERS
                  for R in _rot(axes[:, k], 2 * np.pi * np.arange(1, n) / n)]
    deviation = [_deviation_m(scene, points, centroid, R) for R in candidates]
    group = [np.eye(3)]
    for i in np.argsort(deviation):  # the closest turns first; a turn joins with its products
        if deviation[i] > tolerance_m or _known(candidates[i], group):
            continue
        grown = _closure(group + [candidates[i]])
        if all(keeps(R) for R in grown[len(group):]):
            group = grown
    return Symmetries(centroid, None, False, np.stack(group), points)


def _principal_axes(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centroid (3,), principal axes as columns (3, 3)) of a surface's triangles (m, 3, 3),
    exact: a triangle's second moment is ``area / 12 (sum v v^T + s s^T)``, ``s`` the sum of
    its vertices."""
    tri = np.asarray(triangles, dtype=float)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    s = tri.sum(axis=1)
    centroid = (area[:, None] * s / 3).sum(axis=0) / area.sum()
    second = (area[:, None, None] * (np.einsum("mvi,mvj->mij", tri, tri)
                                     + np.einsum("mi,mj->mij", s, s))).sum(axis=0) / 12
    cov = second / area.sum() - np.outer(centroid, centroid)
    return centroid, np.linalg.eigh(cov)[1]


def _refined_axis(scene: Any, points: np.ndarray, centroid: np.ndarray, axis: np.ndarray
                  ) -> np.ndarray:
    """The axis of revolution near ``axis`` that best keeps the surface under turns of 60,
    120 and 180 deg about the centroid (least mean of the 90 % smallest sample distances:
    the feature that breaks the symmetry tilts the principal axis, not this fit)."""
    import open3d as o3d
    from scipy.optimize import minimize

    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    sample = (points[:1500] - centroid)

    def cost(p: np.ndarray) -> float:
        a = axis + p[0] * u + p[1] * v
        a /= np.linalg.norm(a)
        moved = np.concatenate([sample @ R.T for R in _rot(a, np.radians([60.0, 120.0, 180.0]))])
        d = scene.compute_distance(o3d.core.Tensor((moved + centroid).astype(np.float32)))
        d = np.sort(d.numpy())
        return float(d[: int(0.9 * len(d))].mean())

    p = minimize(cost, np.zeros(2), method="Nelder-Mead",
                 options={"xatol": 1e-5, "fatol": 1e-9, "initial_simplex": [[0, 0], [0.01, 0],
                                                                           [0, 0.01]]}).x
    a = axis + p[0] * u + p[1] * v
    return a / np.linalg.norm(a)


def _known(R: np.ndarray, group: list[np.ndarray]) -> bool:
    return any(rotation_error_deg(R, G) < 1e-3 for G in group)


def _closure(group: list[np.ndarray], limit: int = 48) -> list[np.ndarray]:
    """``group`` (its elements first, in order) with every product of its elements, up to
    ``limit`` elements."""
    out = list(group)
    grew = True
    while grew and len(out) < limit:
        grew = False
        for A in list(out):
            for B in list(out):
                if not _known(A @ B, out):
                    out.append(A @ B)
                    grew = True
    return out


@lru_cache(maxsize=32)
def _symmetries_cached(path: str, mtime_ns: int, size: int, tolerance_m: float) -> Symmetries:
    import trimesh

    mesh = trimesh.load(path, force="mesh", process=False)
    return find_symmetries_of(np.asarray(mesh.vertices), np.asarray(mesh.faces), tolerance_m)


def find_symmetries(mesh_path: Path, tolerance_m: float = SYMMETRY_TOLERANCE_M) -> Symmetries:
    """:func:`find_symmetries_of` for a mesh file, cached per file (path, time, size)."""
    p = Path(mesh_path).resolve()
    st = p.stat()
    return _symmetries_cached(str(p), st.st_mtime_ns, st.st_size, float(tolerance_m))


def closest_symmetry(R_est: np.ndarray, R_true: np.ndarray, sym: Symmetries) -> np.ndarray:
    """The element ``R_S`` (3, 3) of the group for which ``R_true R_S`` is closest to ``R_est``
    (largest ``tr(R_est^T R_true R_S)``): the symmetry that maps the estimated object frame
    onto the true one, a point ``x`` of the estimate's frame being ``c + R_S (x - c)`` of the
    truth's. A sphere's is the error's own rotation; about an axis of revolution ``a`` in
    closed form (``tr(M R_a(theta))`` is ``a^T M a + A cos theta + B sin theta``, largest at
    ``theta = atan2(B, A)``)."""
    R_est, R_true = np.asarray(R_est)[:3, :3], np.asarray(R_true)[:3, :3]
    if sym.sphere:
        return R_true.T @ R_est
    best, best_R = -np.inf, np.eye(3)
    for D in sym.discrete:
        M = D @ R_est.T @ R_true  # tr(R_est^T R_true R_a D) = tr(M R_a)
        if sym.axis is None:
            trace, R = float(np.trace(M)), D
        else:
            a = sym.axis
            along = float(a @ M @ a)
            A, B = float(np.trace(M)) - along, float(np.trace(M @ _skew(a)))
            trace, R = along + float(np.hypot(A, B)), _rot(a, float(np.arctan2(B, A))) @ D
        if trace > best:
            best, best_R = trace, R
    return best_R


def rotation_error_sym_deg(R_est: np.ndarray, R_true: np.ndarray, sym: Symmetries) -> float:
    """min over the group of the angle of ``R_est^T R_true R_S`` (deg) (:func:`closest_symmetry`;
    0 for a sphere), which about an axis of revolution is the angle between the axis as each
    pose maps it."""
    R_est, R_true = np.asarray(R_est)[:3, :3], np.asarray(R_true)[:3, :3]
    return rotation_error_deg(R_est, R_true @ closest_symmetry(R_est, R_true, sym))


def _worst_m(moved: np.ndarray, x: np.ndarray, c: np.ndarray, G: np.ndarray) -> np.ndarray:
    """(g,) largest distance (m) between ``moved`` (n, 3) and ``x`` (n, 3) turned by each
    rotation of ``G`` (g, 3, 3) about ``c``."""
    ref = (x - c)[None] @ np.transpose(G, (0, 2, 1)) + c
    return np.sqrt(((moved[None] - ref) ** 2).sum(axis=2).max(axis=1))


def _mssd_m(moved: np.ndarray, x: np.ndarray, sym: Symmetries) -> float:
    """min over the group (not a sphere's) of the largest distance between ``moved`` and the
    samples ``x`` as the element places them; about an axis of revolution by turns every 5 deg
    on 200 samples, then every 0.5 and 0.05 deg about the best on all of them."""
    c = sym.centroid
    if sym.axis is None:
        return float(_worst_m(moved, x, c, sym.discrete).min())
    best = (np.inf, 0, 0.0)
    coarse = np.radians(np.arange(0.0, 360.0, 5.0))
    for j, D in enumerate(sym.discrete):
        w = _worst_m(moved[:200], x[:200], c, _rot(sym.axis, coarse) @ D)
        if w.min() < best[0]:
            best = (float(w.min()), j, float(coarse[w.argmin()]))
    D, theta, value = sym.discrete[best[1]], best[2], np.inf
    for half, step in ((5.0, 0.5), (0.5, 0.05)):
        turns = theta + np.radians(np.arange(-half, half + step / 2, step))
        w = _worst_m(moved, x, c, _rot(sym.axis, turns) @ D)
        theta, value = float(turns[w.argmin()]), float(w.min())
    return value


def surface_errors_mm(T_est: np.ndarray, T_true: np.ndarray, sym: Symmetries,
                      scene: Any | None = None) -> dict[str, float]:
    """Symmetry-aware errors of the pose ``T_est`` (object -> any frame) against ``T_true``:
    ``mssd_mm`` (BOP's maximum symmetry-aware surface distance: min over the group of the
    largest distance between a surface sample as each pose places it; :func:`_mssd_m`),
    ``adds_mm`` (ADD-S: mean distance from each sample as ``T_est`` places it to the surface as
    ``T_true`` places it; needs the mesh's raycasting ``scene``, else omitted) and
    ``trans_sym_mm`` (distance between the centroid as each pose places it: every symmetry
    fixes the centroid)."""
    E = inv_T(np.asarray(T_true)) @ np.asarray(T_est)  # the estimate in the true object frame
    c = sym.centroid
    moved = transform_points(E, sym.points)
    x, moved_x = sym.points[:MSSD_SAMPLES], moved[:MSSD_SAMPLES]
    out = {"trans_sym_mm": 1e3 * float(np.linalg.norm(transform_points(E, c[None])[0] - c))}
    # a sphere's best element is the error's own rotation: what is left is the centroid's shift
    out["mssd_mm"] = out["trans_sym_mm"] if sym.sphere else 1e3 * _mssd_m(moved_x, x, sym)
    if scene is not None:
        import open3d as o3d

        d = scene.compute_distance(o3d.core.Tensor(moved_x.astype(np.float32))).numpy()
        out["adds_mm"] = 1e3 * float(d.mean())
    return out


@lru_cache(maxsize=8)
def _scene_cached(path: str, mtime_ns: int, size: int) -> Any:
    import open3d as o3d
    import trimesh

    mesh = trimesh.load(path, force="mesh", process=False)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))
    return scene


def surface_scene(mesh_path: Path) -> Any:
    """An open3d raycasting scene of the mesh file (object frame), cached per file."""
    p = Path(mesh_path).resolve()
    st = p.stat()
    return _scene_cached(str(p), st.st_mtime_ns, st.st_size)


def sym_pose_metrics(prefix: str, T_est: np.ndarray, T_true: np.ndarray, sym: Symmetries,
                     scene: Any | None = None) -> dict[str, float]:
    """``{prefix}_rot_sym_deg``, ``{prefix}_trans_sym_mm``, ``{prefix}_mssd_mm`` and (given the
    scene) ``{prefix}_adds_mm`` of one pose (:func:`rotation_error_sym_deg`,
    :func:`surface_errors_mm`)."""
    surf = surface_errors_mm(T_est, T_true, sym, scene)
    out = {f"{prefix}_rot_sym_deg": rotation_error_sym_deg(T_est, T_true, sym),
           f"{prefix}_trans_sym_mm": surf["trans_sym_mm"], f"{prefix}_mssd_mm": surf["mssd_mm"]}
    if "adds_mm" in surf:
        out[f"{prefix}_adds_mm"] = surf["adds_mm"]
    return out
