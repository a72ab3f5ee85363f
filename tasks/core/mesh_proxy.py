"""A coarser stand-in for a very fine object mesh, for stages that only need its surface.

Registration samples the surface and ray casts it; the contact map projects and ray casts
every vertex. On a 2-million-face scan that is minutes of work for no better answer: the depth
and thermal images resolve millimetres, not the scan's tenths. :func:`mesh_proxy` clusters the
vertices on a voxel grid (one vertex per occupied voxel, at the mean of its vertices; faces
whose corners fall in fewer than three voxels dropped, duplicates merged), with the voxel chosen
so that about ``max_faces`` faces remain, and says which proxy vertex stands for each original
vertex (so a per-vertex result can be given for every vertex of the session's mesh, in file
order). A mesh at or below ``max_faces`` is its own proxy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PROXY_FACES = 200_000
"""The default face count above which a stage works on a proxy (the stages' ``proxy_faces``).
``estimate_adjustment`` gets the mesh itself: on a 979200-face mug its proxy of 200000 faces
registered at fitness 0.988 in 23 s where the mesh took 11.6 s at 0.999."""


@dataclass(frozen=True)
class MeshProxy:
    """vertices (k, 3), faces (l, 3); ``of_vertex`` (n,): the proxy vertex of each original
    vertex; ``voxel_m``: the grid's cell (0 when the mesh is its own proxy)."""

    vertices: np.ndarray
    faces: np.ndarray
    of_vertex: np.ndarray
    voxel_m: float

    @property
    def is_original(self) -> bool:
        return self.voxel_m == 0.0

    def note(self, n_faces: int, what: str) -> str:
        """A sentence for QA notes: the proxy used for ``what``."""
        return (f"object mesh of {n_faces} faces: {what} on a proxy of {len(self.faces)} "
                f"faces (vertices clustered on a {1000 * self.voxel_m:.2f} mm grid)")


def _cluster(vertices: np.ndarray, faces: np.ndarray, voxel_m: float):
    cell = np.floor((vertices - vertices.min(0)) / voxel_m).astype(np.int64)
    span = cell.max(0) + 1
    key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]  # callers keep it < 2^63
    _, of_vertex, counts = np.unique(key, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, of_vertex, vertices)
    proxy_v = sums / counts[:, None]
    f = of_vertex[faces]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    # one face per corner set, in the orientation of its first occurrence
    s, k = np.sort(f, axis=1), len(counts)
    if k < 2**21:  # a key per corner set fits in int64
        _, first = np.unique((s[:, 0] * k + s[:, 1]) * k + s[:, 2], return_index=True)
    else:
        _, first = np.unique(s, axis=0, return_index=True)
    return proxy_v, f[np.sort(first)], of_vertex


def mesh_proxy(vertices: np.ndarray, faces: np.ndarray, max_faces: int) -> MeshProxy:
    """A proxy of at most ``max_faces`` faces (the mesh itself when it has no more)."""
    V = np.asarray(vertices, dtype=float)
    F = np.asarray(faces, dtype=np.int64)
    if len(F) <= max_faces:
        return MeshProxy(V, F, np.arange(len(V)), 0.0)
    tri = V[F]
    area = 0.5 * float(np.linalg.norm(
        np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
    extent = float(np.ptp(V, axis=0).max())
    # a closed surface clustered on a grid keeps about 2.3 faces per cell area; no coarser
    # grid than 2^20 cells a side, so the cell and face keys fit in int64
    voxel = max(np.sqrt(2.5 * area / max_faces), extent / 2**20, 1e-12)
    while True:
        proxy_v, proxy_f, of_vertex = _cluster(V, F, voxel)
        if len(proxy_f) == 0:  # nothing left at this grid: the mesh itself
            return MeshProxy(V, F, np.arange(len(V)), 0.0)
        if len(proxy_f) <= max_faces:
            return MeshProxy(proxy_v, proxy_f, of_vertex, float(voxel))
        voxel *= 1.3
