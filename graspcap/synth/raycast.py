"""A fixed camera over a static background, ray cast once (the synthetic rig's renderer).

Casting itself is :func:`graspcap.tasks.core.render.cast_rays`, whose hits keep the triangle and
its barycentric coordinates (to interpolate per-vertex values such as contact).
"""

from __future__ import annotations

import numpy as np

from graspcap.synth.rig import distorted_pixel_rays, project_distorted
from graspcap.tasks.core.geometry import transform_points
from graspcap.tasks.core.render import RayHits, cast_rays, pixel_rays


class StaticCamera:
    """A fixed pinhole camera over a static background (platter, table).

    The background is cast once; each :meth:`render` casts only the moving
    meshes, only inside their projected bounding box, and composites by depth.
    Mesh indices: the moving meshes first (0 .. n-1), then the background's.
    """

    def __init__(self, K: np.ndarray, width: int, height: int,
                 background: list[tuple[np.ndarray, np.ndarray]], T_c_b: list[np.ndarray],
                 dist: np.ndarray | None = None):
        self.K, self.width, self.height = np.asarray(K, float), width, height
        self.dist = None if dist is None or not np.any(dist) else np.asarray(dist, float)
        if self.dist is None:
            self.dirs = pixel_rays(self.K, width, height).astype(np.float32)
        else:  # each pixel's ray through the distorted lens
            self.dirs = distorted_pixel_rays(self.K, self.dist, width, height).astype(np.float32)
        self.background = cast_rays(background, T_c_b, self.dirs)

    def render(
        self, meshes: list[tuple[np.ndarray, np.ndarray]], T_c_m: list[np.ndarray]
    ) -> RayHits:
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
            if self.dist is None:
                uv = pts[:, :2] / pts[:, 2:3] * [self.K[0, 0], self.K[1, 1]] + self.K[:2, 2]
                pad = 0
            else:  # the distorted image of a vertex; a few pixels more for the faces between
                uv, pad = project_distorted(self.K, self.dist, pts), 4
            u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 2 - pad, 0,
                             [self.width, self.height])
            u1, v1 = np.clip(np.ceil(uv.max(0)).astype(int) + 3 + pad, 0,
                             [self.width, self.height])
        else:
            u0, v0, u1, v1 = 0, 0, self.width, self.height
        if u1 <= u0 or v1 <= v0:
            return RayHits(**out)
        fg = cast_rays(meshes, T_c_m, np.ascontiguousarray(self.dirs[v0:v1, u0:u1]))
        win = (slice(v0, v1), slice(u0, u1))
        bg_d = out["depth_m"][win]
        take = (fg.mesh_index >= 0) & ((bg_d <= 0) | (fg.depth_m < bg_d))
        for key in out:
            out[key][win][take] = getattr(fg, key)[take]
        return RayHits(**out)
