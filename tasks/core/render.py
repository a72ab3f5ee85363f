"""Depth rendering by ray casting (Open3D ``RaycastingScene``).

Used by the synthetic rig to render what a depth camera sees, and by stages
that need visibility (which mesh a pixel sees, how grazing the view is).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

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
    x = (np.arange(width, dtype=float) - K[0, 2]) / K[0, 0]
    y = (np.arange(height, dtype=float) - K[1, 2]) / K[1, 1]
    norm = np.sqrt((x * x)[None, :] + (y * y)[:, None] + 1.0)  # the same sums, in order
    out = np.empty((height, width, 3))
    np.divide(x[None, :], norm, out=out[..., 0])
    np.divide(y[:, None], norm, out=out[..., 1])
    np.divide(1.0, norm, out=out[..., 2])
    return out


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
    return _hits(ans, ids, dirs, dirs)


def _hits(ans: dict, ids: list[int], dirs: np.ndarray, dirs_scene: np.ndarray) -> RayHits:
    """``RayHits`` of a ``RaycastingScene.cast_rays`` answer: ``ids`` the meshes' geometry
    ids in order, ``dirs`` (h, w, 3) the rays in the camera, ``dirs_scene`` the same rays in
    the scene's frame (its normals' frame)."""
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
        cos_incidence=np.where(hit, np.abs((normals * dirs_scene).sum(-1)), 0.0).astype(
            np.float32),
        triangle=np.where(hit, ans["primitive_ids"].numpy().astype(np.int64), -1),
        bary=np.where(hit[..., None], bary, 0.0).astype(np.float32),
    )


_SCENES: OrderedDict[bytes, Any] = OrderedDict()
_SCENES_LOCK = threading.Lock()
_SCENES_MAX = 8


def mesh_scene(vertices: np.ndarray, faces: np.ndarray) -> Any:
    """A ``RaycastingScene`` of one mesh in its own frame, built once per mesh content (the
    last ``_SCENES_MAX`` kept): building the BVH costs ~3x a cast of a few hundred pixels
    square, and the stages render the same object and hand in every frame."""
    import open3d as o3d

    v = np.ascontiguousarray(vertices, dtype=np.float32)
    f = np.ascontiguousarray(faces, dtype=np.uint32)
    key = hashlib.blake2b(v.tobytes() + f.tobytes(), digest_size=16).digest()
    with _SCENES_LOCK:
        if key in _SCENES:
            _SCENES.move_to_end(key)
            return _SCENES[key]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(v, f)
    # the BVH is built lazily by the first cast: build it before another thread can see it
    scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], dtype=np.float32)))
    with _SCENES_LOCK:
        _SCENES[key] = scene
        while len(_SCENES) > _SCENES_MAX:
            _SCENES.popitem(last=False)
    return scene


def render(
    meshes: list[tuple[np.ndarray, np.ndarray]],
    T_c_m: list[np.ndarray],
    K: np.ndarray,
    width: int,
    height: int,
) -> RayHits:
    """Ray-cast triangle meshes placed in a camera's frame through every pixel of a pinhole
    camera ``K`` of ``width`` x ``height`` (meshes in their own frames, metres).

    One mesh is cast in its own frame (the rays moved by ``T_c_m``'s inverse) against a scene
    built once for it (:func:`mesh_scene`); several are placed in the camera's frame and cast
    as :func:`cast_rays` does."""
    dirs = pixel_rays(K, width, height).astype(np.float32)
    if len(meshes) != 1:
        return cast_rays(meshes, T_c_m, dirs)
    import open3d as o3d

    T = np.asarray(T_c_m[0], dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    dirs_m = (dirs @ R).astype(np.float32)  # each ray R^T d in the mesh frame
    origin = np.broadcast_to((-R.T @ t).astype(np.float32), dirs.shape)
    rays = np.ascontiguousarray(np.concatenate([origin, dirs_m], axis=-1))
    ans = mesh_scene(*meshes[0]).cast_rays(o3d.core.Tensor(rays))
    return _hits(ans, [0], dirs, dirs_m)
