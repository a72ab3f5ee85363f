"""One ray cast per synthetic image, keeping what the sensors need (which triangle, where on it).

Like :func:`graspcap.tasks.render.render`, plus the hit triangle and its
barycentric coordinates (to interpolate per-vertex values such as contact).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from graspcap.tasks.geometry import transform_points
from graspcap.tasks.render import pixel_rays


@dataclass(frozen=True)
class Hits:
    """What every pixel sees.

    Attributes
    ----------
    depth_m : (h, w) float32
        z in the camera frame; 0 where nothing is hit.
    mesh_index : (h, w) int32
        Index into the list of meshes; -1 for no hit.
    cos_incidence : (h, w) float32
        |cos| of the angle between the ray and the face normal.
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


def _cast(meshes: list[tuple[np.ndarray, np.ndarray]], T_c_m: list[np.ndarray],
          dirs: np.ndarray) -> Hits:
    """Cast rays from the camera centre along unit ``dirs`` (h, w, 3) float32."""
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
    return Hits(
        depth_m=np.where(hit, t_hit * dirs[..., 2], 0.0).astype(np.float32),
        mesh_index=index,
        cos_incidence=np.where(hit, np.abs((normals * dirs).sum(-1)), 0.0).astype(np.float32),
        triangle=np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), -1),
        bary=np.where(hit[..., None], bary, 0.0).astype(np.float32),
    )


def cast(
    meshes: list[tuple[np.ndarray, np.ndarray]],
    T_c_m: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
) -> Hits:
    """Ray-cast meshes (vertices (n, 3), faces (m, 3)) posed by ``T_c_m`` through pinhole ``K``."""
    return _cast(meshes, T_c_m, pixel_rays(K, width, height).astype(np.float32))


class StaticCamera:
    """A fixed pinhole camera over a static background (platter, table).

    The background is cast once; each :meth:`render` casts only the moving
    meshes, only inside their projected bounding box, and composites by depth.
    Mesh indices: the moving meshes first (0 .. n-1), then the background's.
    """

    def __init__(self, K: np.ndarray, width: int, height: int,
                 background: list[tuple[np.ndarray, np.ndarray]], T_c_b: list[np.ndarray]):
        self.K, self.width, self.height = np.asarray(K, float), width, height
        self.dirs = pixel_rays(self.K, width, height).astype(np.float32)
        self.background = _cast(background, T_c_b, self.dirs)

    def render(self, meshes: list[tuple[np.ndarray, np.ndarray]], T_c_m: list[np.ndarray]) -> Hits:
        """What the camera sees with ``meshes`` (posed by ``T_c_m``) in front of the background."""
        n = len(meshes)
        bg = self.background
        out = {
            "depth_m": bg.depth_m.copy(),
            "mesh_index": np.where(bg.mesh_index >= 0, bg.mesh_index + n, -1).astype(np.int32),
            "cos_incidence": bg.cos_incidence.copy(),
            "triangle": bg.triangle.copy(),
            "bary": bg.bary.copy(),
        }
        pts = np.concatenate([transform_points(T, v) for (v, _), T in zip(meshes, T_c_m,
                                                                          strict=True)])
        if np.all(pts[:, 2] > 1e-3):
            uv = pts[:, :2] / pts[:, 2:3] * [self.K[0, 0], self.K[1, 1]] + self.K[:2, 2]
            u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 2, 0, [self.width, self.height])
            u1, v1 = np.clip(np.ceil(uv.max(0)).astype(int) + 3, 0, [self.width, self.height])
        else:
            u0, v0, u1, v1 = 0, 0, self.width, self.height
        if u1 <= u0 or v1 <= v0:
            return Hits(**out)
        fg = _cast(meshes, T_c_m, np.ascontiguousarray(self.dirs[v0:v1, u0:u1]))
        win = (slice(v0, v1), slice(u0, u1))
        bg_d = out["depth_m"][win]
        take = (fg.mesh_index >= 0) & ((bg_d <= 0) | (fg.depth_m < bg_d))
        for key in out:
            out[key][win][take] = getattr(fg, key)[take]
        return Hits(**out)
