"""Depth rendering by ray casting (Open3D ``RaycastingScene``).

Used by the synthetic rig to render what a depth camera sees, and by stages
that need visibility (which mesh a pixel sees, how grazing the view is).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.geometry import transform_points

# open3d: imported where used, so that importing the stage table stays cheap


@dataclass(frozen=True)
class RayHits:
    """What every pixel of a pinhole camera sees.

    Attributes
    ----------
    depth_m : (h, w) float32
        z of the hit in the camera frame; 0 where a ray hits nothing.
    mesh_index : (h, w) int32
        Index into the list of meshes given to :func:`render`; -1 for no hit.
    cos_incidence : (h, w) float32
        |cos| of the angle between the ray and the surface normal (1 = head on).
    triangle : (h, w) int64
        Hit triangle within its mesh; -1 for no hit.
    bary : (h, w, 3) float32
        Barycentric weights of the hit triangle's three vertices.
    """

    depth_m: np.ndarray
    mesh_index: np.ndarray
    cos_incidence: np.ndarray
    triangle: np.ndarray
    bary: np.ndarray

    def interpolate(self, index: int, faces: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Per-vertex ``values`` (n,) of mesh ``index`` at its hit pixels; 0 elsewhere. (h, w)."""
        out = np.zeros(self.depth_m.shape, dtype=np.float64)
        mask = self.mesh_index == index
        tri = faces[self.triangle[mask]]
        out[mask] = (values[tri] * self.bary[mask]).sum(axis=1)
        return out


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit ray directions (h, w, 3) in the camera frame through every pixel centre."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def cast_rays(
    meshes: list[tuple[np.ndarray, np.ndarray]], T_c_m: list[np.ndarray], dirs: np.ndarray
) -> RayHits:
    """Cast rays from the camera centre along unit ``dirs`` (h, w, 3) float32 against meshes
    (vertices (n, 3), faces (m, 3)) posed in the camera frame by ``T_c_m``."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = []
    for (vertices, faces), T in zip(meshes, T_c_m, strict=True):
        v = transform_points(T, vertices).astype(np.float32)
        ids.append(scene.add_triangles(v, np.asarray(faces, dtype=np.uint32)))
    rays = np.concatenate([np.zeros_like(dirs), dirs], axis=-1)
    ans = scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
    t_hit = ans["t_hit"].numpy()
    hit = np.isfinite(t_hit)
    geom = ans["geometry_ids"].numpy().astype(np.int64)
    index = np.full(geom.shape, -1, dtype=np.int32)
    for i, gid in enumerate(ids):
        index[hit & (geom == gid)] = i
    normals = ans["primitive_normals"].numpy()
    uv = ans["primitive_uvs"].numpy()
    bary = np.stack([1.0 - uv[..., 0] - uv[..., 1], uv[..., 0], uv[..., 1]], axis=-1)
    return RayHits(
        depth_m=np.where(hit, t_hit * dirs[..., 2], 0.0).astype(np.float32),
        mesh_index=index,
        cos_incidence=np.where(hit, np.abs((normals * dirs).sum(-1)), 0.0).astype(np.float32),
        triangle=np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), -1),
        bary=np.where(hit[..., None], bary, 0.0).astype(np.float32),
    )


def render(
    meshes: list[tuple[np.ndarray, np.ndarray]],
    T_c_m: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
) -> RayHits:
    """Ray-cast triangle meshes placed in a camera's frame through every pixel of a pinhole
    camera ``K`` of ``width`` x ``height`` (meshes in their own frames, metres)."""
    return cast_rays(meshes, T_c_m, pixel_rays(K, width, height).astype(np.float32))
