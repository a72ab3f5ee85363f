"""Cheap, batched distances between the hand model's surface and an object (for refine_grasp).

The hand model's surface (``HandModel.mesh``) is 16 closed convex parts: each phalanx the hull
of two spheres at its joints (a tapered capsule whose radii are ``SURFACE_OFFSET_M``), and the
palm the hull of a few spheres, rigid in the palm frame. So:

- the signed distance of a point to a phalanx is the distance to its bone minus the radius
  interpolated at the closest point of the bone (exact up to the taper's tilt);
- the signed distance to the palm is read from a grid in the palm frame, built once per side
  from the palm hull's face planes (inside: exact; outside: the largest plane distance, within
  about 1 % of the true distance for the finely tessellated hull);
- the object's signed distance is a grid in the object frame around the hand: sign from
  Open3D's occupancy, magnitude exact (Open3D ``compute_distance``) in a band near the surface
  and the nearest-vertex distance (an upper bound) beyond.

All lookups are trilinear; a point outside a grid gets the boundary value plus its distance to
the grid's box. Everything is deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from graspcap.tasks.hand.model import PART_BONES, SURFACE_OFFSET_M, HandModel, HandSide

# open3d, scipy: imported where used, so that importing the stage table stays cheap

BONES = np.array(PART_BONES)  # (15, 2) keypoints at the ends of each phalanx
_PALM_GRID_MARGIN_M = 0.02
_PALM_GRID_STEP_M = 0.003


@dataclass(frozen=True)
class Grid:
    """Values on a regular grid: ``values`` (nx, ny, nz) at ``origin + step * (i, j, k)``."""

    origin: np.ndarray
    step: float
    values: np.ndarray

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Trilinear lookup (...,) at ``points`` (..., 3); outside the box: boundary value plus
        the distance to the box."""
        from scipy.ndimage import map_coordinates

        p = np.asarray(points, dtype=float)
        shape = p.shape[:-1]
        p = p.reshape(-1, 3)
        hi = self.origin + self.step * (np.array(self.values.shape) - 1)
        clamped = np.clip(p, self.origin, hi)
        idx = ((clamped - self.origin) / self.step).T
        v = map_coordinates(self.values, idx, order=1, mode="nearest")
        return (v + np.linalg.norm(p - clamped, axis=1)).reshape(shape)


def _grid_points(lo: np.ndarray, hi: np.ndarray, step: float) -> tuple[np.ndarray, tuple]:
    n = np.maximum(np.ceil((hi - lo) / step).astype(int) + 1, 2)
    axes = [lo[i] + step * np.arange(n[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    return grid.reshape(-1, 3), tuple(n)


def palm_grid(side: HandSide, bone_scale: np.ndarray | None = None) -> Grid:
    """Signed distance (m) to the palm part of the ``side`` model at scale 1, palm frame, for
    the shape ``bone_scale`` (20,) (None: the template's; only the palm's five factors matter)."""
    palm = None if bone_scale is None else tuple(float(v) for v in np.asarray(bone_scale)[::4])
    return _palm_grid(HandSide(side), None if palm == (1.0,) * 5 else palm)


@lru_cache(maxsize=16)
def _palm_grid(side: HandSide, palm: tuple[float, ...] | None) -> Grid:
    from scipy.spatial import ConvexHull

    model = HandModel(side)
    bone_scale = None
    if palm is not None:
        bone_scale = np.ones(20)
        bone_scale[::4] = palm
    mesh = model.mesh(model.rest_angles(), bone_scale=bone_scale)
    palm_v = mesh.vertices[mesh.part == 0]
    if bone_scale is None:  # the template's palm is a convex hull: its own faces' planes
        faces = mesh.faces[mesh.part[mesh.faces[:, 0]] == 0]
        tri = mesh.vertices[faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        offsets = np.einsum("ij,ij->i", normals, tri[:, 0])
    else:  # a shaped palm's moved spheres need not stay convex: the planes of its hull
        hull = ConvexHull(palm_v)
        normals, offsets = hull.equations[:, :3], -hull.equations[:, 3]
    lo = palm_v.min(0) - _PALM_GRID_MARGIN_M
    hi = palm_v.max(0) + _PALM_GRID_MARGIN_M
    pts, shape = _grid_points(lo, hi, _PALM_GRID_STEP_M)
    values = np.empty(len(pts))
    for s in range(0, len(pts), 20000):
        values[s : s + 20000] = (pts[s : s + 20000] @ normals.T - offsets).max(axis=1)
    values = values.reshape(shape)
    values.setflags(write=False)
    return Grid(lo, _PALM_GRID_STEP_M, values)


def penetration_mm(
    object_vertices: np.ndarray, object_faces: np.ndarray, points: np.ndarray
) -> tuple[float, float]:
    """How deep ``points`` (k, 3) lie inside a closed mesh, by Open3D's signed distance with a
    3-ray vote on the sign: (deepest, mean over the points inside; 0 when none is), in mm."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(object_vertices, np.float32),
                        np.asarray(object_faces, np.uint32))
    q = o3d.core.Tensor(np.asarray(points, np.float32))
    depth_mm = np.maximum(-1e3 * scene.compute_signed_distance(q, nsamples=3).numpy()
                          .astype(float), 0.0)
    inside = depth_mm > 0
    return float(depth_mm.max(initial=0.0)), float(depth_mm[inside].mean()) if inside.any() else 0.0


def _parts(faces: np.ndarray) -> list[np.ndarray]:
    """The faces (index arrays) of each connected part of a mesh."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, np.int64)
    n = int(f.max()) + 1 if len(f) else 0
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    face_label = label[f[:, 0]]
    return [np.flatnonzero(face_label == k) for k in np.unique(face_label)]


def contact_agreement(
    object_vertices: np.ndarray, contact: np.ndarray, observed: np.ndarray,
    hand_vertices: np.ndarray, hand_faces: np.ndarray, *, near_mm: float,
    contact_threshold: float, candidates: np.ndarray | None = None,
) -> tuple[float, float]:
    """How well a contact map and a hand mesh (both in the object frame) agree, both ways.

    An object vertex is *touched* when it lies within ``near_mm`` of the hand mesh's surface
    (Open3D's unsigned distance) or inside one of the mesh's closed parts (each connected
    part's own ray-parity occupancy, so that overlapping parts do not cancel); *contacted*
    when observed and its contact is at least ``contact_threshold``. Only observed vertices
    count. This is the one definition ``refine_grasp`` (before / after) and ``qa_metrics`` use.

    Parameters
    ----------
    object_vertices : (n, 3) float
    contact : (n,) float in [0, 1]
    observed : (n,) bool
    hand_vertices : (k, 3) float
    hand_faces : (l, 3) int
    near_mm : float
    contact_threshold : float
    candidates : (n,) bool, optional
        Vertices that may be touched, a conservative pre-selection for speed (e.g. by a cheaper
        distance); None: every observed vertex is measured.

    Returns
    -------
    contact_near_share : float
        Contacted vertices that are touched (NaN when none is contacted).
    touch_contacted_share : float
        Touched observed vertices that are contacted (NaN when the hand touches none).
    """
    import open3d as o3d

    V = np.asarray(object_vertices, float)
    observed = np.asarray(observed, bool)
    contacted = observed & (np.asarray(contact, float) >= contact_threshold)
    cand = observed if candidates is None else observed & np.asarray(candidates, bool)
    touched = np.zeros(len(V), bool)
    idx = np.flatnonzero(cand)
    if len(idx):
        hv = np.asarray(hand_vertices, np.float32)
        hf = np.asarray(hand_faces, np.uint32)
        hand = o3d.t.geometry.RaycastingScene()
        hand.add_triangles(hv, hf)
        q = V[idx].astype(np.float32)
        d_mm = 1e3 * hand.compute_distance(o3d.core.Tensor(q)).numpy()
        touched[idx] = d_mm <= near_mm
        lo, hi = hv.min(0), hv.max(0)
        far = np.flatnonzero(~touched[idx] & np.all((q >= lo) & (q <= hi), axis=1))
        for part in _parts(hf) if len(far) else []:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(hv, hf[part])
            inside = scene.compute_occupancy(o3d.core.Tensor(q[far]), nsamples=3).numpy() > 0
            touched[idx[far[inside]]] = True
    near_share = float(touched[contacted].mean()) if contacted.any() else float("nan")
    touch_share = float(contacted[touched].mean()) if touched.any() else float("nan")
    return near_share, touch_share


def object_sdf_grid(
    vertices: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray, step_m: float,
    band_m: float,
) -> Grid:
    """Signed distance (negative inside) of a closed mesh on a grid over the box ``lo..hi``.

    Exact (Open3D) within ``band_m`` of the surface, the nearest-vertex distance beyond.
    """
    import open3d as o3d
    from scipy.spatial import cKDTree

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(vertices.astype(np.float32), faces.astype(np.uint32))
    pts, shape = _grid_points(np.asarray(lo, float), np.asarray(hi, float), step_m)
    nn_m, _ = cKDTree(vertices).query(pts)
    edges = vertices[faces] - vertices[faces[:, [1, 2, 0]]]
    max_edge_m = float(np.linalg.norm(edges, axis=2).max())
    near = nn_m < band_m + max_edge_m
    dist = nn_m.copy()
    if near.any():
        q = o3d.core.Tensor(pts[near].astype(np.float32))
        dist[near] = scene.compute_distance(q).numpy()
    q_all = o3d.core.Tensor(pts.astype(np.float32))
    inside = scene.compute_occupancy(q_all, nsamples=3).numpy() > 0.5  # vote: one ray can leak
    values = np.where(inside, -dist, dist).reshape(shape)
    values.setflags(write=False)
    return Grid(np.asarray(lo, float), float(step_m), values)


class HandSurface:
    """Signed distances to the posed hand model's surface and penetration samples, batched.

    Poses are given as keypoints ``kp`` (b, 21, 3), palm rotations ``R`` (b, 3, 3) and origins
    ``t`` (b, 3) in one frame (the object's); ``scale`` and the shape ``bone_scale`` (20,)
    (None: the template's) are fixed.
    """

    def __init__(self, side: HandSide, scale: float, samples_per_bone: int = 5,
                 bone_scale: np.ndarray | None = None):
        self.scale = float(scale)
        r = SURFACE_OFFSET_M * self.scale
        self.r_start, self.r_end = r[BONES[:, 0]], r[BONES[:, 1]]
        self.palm = palm_grid(HandSide(side), bone_scale)
        model = HandModel(side)
        mesh = model.mesh(model.rest_angles(), bone_scale=bone_scale)
        self.palm_samples_p = mesh.vertices[mesh.part == 0] * self.scale  # palm frame, scaled
        self.t = np.linspace(0.0, 1.0, samples_per_bone)
        # (15 * s,) sphere radii along the bones
        self.sample_r = (self.r_start[:, None] * (1 - self.t) + self.r_end[:, None] * self.t)
        self.sample_r = self.sample_r.reshape(-1)

    def distance(self, points: np.ndarray, kp: np.ndarray, R: np.ndarray, t: np.ndarray
                 ) -> np.ndarray:
        """Signed distance (b, n) of ``points`` (n, 3) to the hand surface (negative inside)."""
        A, B = kp[:, BONES[:, 0]], kp[:, BONES[:, 1]]  # (b, 15, 3)
        centre = points.mean(axis=0)
        P, A, B = points - centre, A - centre, B - centre
        AB = B - A
        L2 = np.maximum((AB * AB).sum(-1), 1e-12)  # (b, 15)
        PA = np.matmul(P[None], A.transpose(0, 2, 1))  # (b, n, 15)
        dot = np.matmul(P[None], AB.transpose(0, 2, 1)) - (A * AB).sum(-1)[:, None]
        u = np.clip(dot / L2[:, None], 0.0, 1.0)
        AP2 = (P * P).sum(-1)[None, :, None] - 2.0 * PA + (A * A).sum(-1)[:, None]
        d = np.sqrt(np.maximum(AP2 - 2.0 * u * dot + u * u * L2[:, None], 0.0))
        d -= self.r_start + u * (self.r_end - self.r_start)
        local = np.matmul(points[None] - t[:, None], R) / self.scale
        d_palm = self.palm(local) * self.scale
        return np.minimum(d.min(axis=2), d_palm)

    def samples(self, kp: np.ndarray, R: np.ndarray, t: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Penetration probes: sphere centres (b, 15 s, 3) along the bones with radii
        ``sample_r``, and palm surface points (b, p, 3)."""
        A, B = kp[:, BONES[:, 0]], kp[:, BONES[:, 1]]
        centres = A[:, :, None] + self.t[None, None, :, None] * (B - A)[:, :, None]
        palm = np.einsum("bij,pj->bpi", R, self.palm_samples_p) + t[:, None]
        return centres.reshape(len(kp), -1, 3), self.sample_r, palm


__all__ = [
    "BONES", "Grid", "HandSurface", "contact_agreement", "object_sdf_grid", "palm_grid",
    "penetration_mm",
]
