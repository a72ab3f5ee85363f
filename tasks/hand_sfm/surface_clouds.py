"""The surface of a frame the depth links register: the hand and the object it holds.

A frame's surface is its depth inside a sphere around the hand's current centre, minus the
static scene: with the turntable pose known, everything less than ``min_height_m`` above the
platter's top plane (the platter and the table) is dropped. Sampled on a pixel lattice, with
normals from the lattice neighbours, for ``hand_sfm.depth_links``'s point-to-plane ICP.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.geometry import backproject, inv_T

DepthFrame = Callable[[int], np.ndarray]
"""``depth_frame(frame) -> depth_m (h, w)``: aligned depth of a video frame in metres, 0 where
the sensor has no reading."""


@dataclass(frozen=True)
class SurfaceCloud:
    """Sampled surface of one frame, camera coordinates, on a pixel lattice.

    index : (gh, gw) int32, row of ``points`` at each lattice node, -1 where none.
    first_px : (u, v) pixel of lattice node (0, 0); stride_px : pixels between nodes.
    points, normals : (n, 3) float; normals unit length and facing the camera.
    """

    index: np.ndarray
    first_px: tuple[int, int]
    stride_px: int
    points: np.ndarray
    normals: np.ndarray


def hand_centre(
    K: np.ndarray, uv_px: np.ndarray, depth_m: np.ndarray, below_skin_m: float
) -> np.ndarray | None:
    """Rough hand centre (3,) in the camera from keypoints (k, 2) and their depth readings
    (k,): the median pixel at the median valid reading plus ``below_skin_m``; None without
    a reading."""
    valid = np.isfinite(depth_m) & (depth_m > 0)
    if not valid.any():
        return None
    uv = np.median(uv_px[valid], axis=0)[None]
    return backproject(K, uv, np.array([np.median(depth_m[valid]) + below_skin_m]))[0]


def surface_cloud(
    depth_m: np.ndarray,
    K: np.ndarray,
    centre_c: np.ndarray,
    *,
    radius_m: float,
    stride_px: int,
    T_color_turntable: np.ndarray | None = None,
    min_height_m: float = 0.015,
    normal_step: int = 2,
    max_jump_m: float = 0.01,
    min_points: int = 50,
    spacing_m: float | None = None,
) -> SurfaceCloud | None:
    """Depth pixels on a lattice of ``stride_px`` within ``radius_m`` of ``centre_c`` (3,) and,
    when the turntable pose ``T_color_turntable`` (4, 4) is given, at least ``min_height_m``
    above its top plane. Normals from the lattice neighbours ``normal_step`` nodes away (central
    differences), none across a depth jump over ``max_jump_m``. None with fewer than
    ``min_points``.

    With ``spacing_m`` the lattice is as fine as needed for its nodes to lie about that far
    apart at the centre's depth, ``stride_px`` at most: a hand twice as far is sampled on a
    lattice twice as fine, so that the normals' reach (``normal_step`` nodes) stays inside a
    finger instead of spanning its edges (where the jump test drops the point, or, with both
    ends beyond the finger, the point takes the normal of what lies there)."""
    h, w = depth_m.shape
    c = np.asarray(centre_c, dtype=float)
    if not np.all(np.isfinite(c)) or c[2] <= radius_m * 0.5:
        return None
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if spacing_m is not None:
        stride_px = int(np.clip(round(spacing_m * fx / c[2]), 1, stride_px))
    z_near = max(c[2] - radius_m, 0.05)
    u0 = int(np.clip(fx * (c[0] - radius_m) / z_near + cx, 0, w))
    u1 = int(np.clip(fx * (c[0] + radius_m) / z_near + cx + 1, 0, w))
    v0 = int(np.clip(fy * (c[1] - radius_m) / z_near + cy, 0, h))
    v1 = int(np.clip(fy * (c[1] + radius_m) / z_near + cy + 1, 0, h))
    k = normal_step
    # the box above bounds the sphere's image loosely (about twice its area for a hand at
    # 0.45 m); cut it to the sphere's exact image plus the normals' reach, on the same
    # lattice, which keeps the same points
    margin = (k + 1) * stride_px + 1
    u0, u1 = _tight(u0, u1, c[0], c[2], radius_m, fx, cx, margin, stride_px)
    v0, v1 = _tight(v0, v1, c[1], c[2], radius_m, fy, cy, margin, stride_px)
    z = depth_m[v0:v1:stride_px, u0:u1:stride_px].astype(float)
    if z.shape[0] <= 2 * k or z.shape[1] <= 2 * k:
        return None
    u = (np.arange(z.shape[1]) * stride_px + u0 - cx) / fx
    v = (np.arange(z.shape[0]) * stride_px + v0 - cy) / fy
    P = np.stack([u[None, :] * z, v[:, None] * z, z], axis=2)
    keep = (z > 0) & (np.sum((P - c) ** 2, axis=2) < radius_m**2)
    if T_color_turntable is not None:
        T_turntable_color = inv_T(T_color_turntable)
        keep &= P @ T_turntable_color[2, :3] + T_turntable_color[2, 3] > min_height_m
    du = P[k:-k, 2 * k :] - P[k:-k, : -2 * k]
    dv = P[2 * k :, k:-k] - P[: -2 * k, k:-k]
    keep = (
        keep[k:-k, k:-k]
        & (np.abs(du[..., 2]) < max_jump_m) & (np.abs(dv[..., 2]) < max_jump_m)
        & (z[k:-k, 2 * k :] > 0) & (z[k:-k, : -2 * k] > 0)
        & (z[2 * k :, k:-k] > 0) & (z[: -2 * k, k:-k] > 0)
    )  # fmt: skip
    if keep.sum() < min_points:
        return None
    n = np.cross(du[keep], dv[keep])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    pts = P[k:-k, k:-k][keep]
    n *= -np.sign(np.sum(n * pts, axis=1))[:, None]
    index = np.full(keep.shape, -1, dtype=np.int32)
    index[keep] = np.arange(len(pts), dtype=np.int32)
    return SurfaceCloud(index, (u0 + k * stride_px, v0 + k * stride_px), stride_px, pts, n)


def _tight(
    lo: int, hi: int, c_a: float, c_z: float, r: float, f: float, c0: float, margin: int,
    stride: int,
) -> tuple[int, int]:
    """Pixel range [lo, hi) along one image axis cut to the image of the ball of radius ``r``
    around (c_a, c_z) (that axis and depth) widened by ``margin`` pixels; ``lo`` moves by
    whole ``stride`` steps so that the lattice stays the same."""
    rho = np.hypot(c_a, c_z)
    if r >= rho:
        return lo, hi
    theta, half = np.arctan2(c_a, c_z), np.arcsin(r / rho)
    if theta + half >= np.pi / 2 or theta - half <= -np.pi / 2:
        return lo, hi
    first = f * np.tan(theta - half) + c0 - margin
    last = f * np.tan(theta + half) + c0 + margin
    new_lo = lo + stride * max(int(np.floor((first - lo) / stride)), 0)
    return new_lo, max(min(hi, int(np.ceil(last)) + 1), new_lo)


def surface_reader(
    depth_frame: Callable[[int], np.ndarray],
    K: np.ndarray,
    first_frame: int,
    T_color_turntable: np.ndarray,
    *,
    centre_below_skin_m: float,
    radius_m: float,
    stride_px: int,
    min_height_m: float,
    spacing_m: float | None = None,
) -> Callable[[int, np.ndarray, np.ndarray], SurfaceCloud | None]:
    """``(i, uv_i, depth_i) -> `` the surface of row ``i`` (video frame ``first_frame + i``)
    around the hand its keypoints ``uv_i`` and their depth readings ``depth_i`` place, or None
    without a reading: the depth links' surfaces (``DepthLinkConfig``'s fields)."""

    def surface_at(i: int, uv_i: np.ndarray, depth_i: np.ndarray) -> SurfaceCloud | None:
        centre = hand_centre(K, uv_i, depth_i, centre_below_skin_m)
        if centre is None:
            return None
        return surface_cloud(
            depth_frame(first_frame + i), K, centre, radius_m=radius_m, stride_px=stride_px,
            T_color_turntable=T_color_turntable, min_height_m=min_height_m,
            spacing_m=spacing_m,
        )  # fmt: skip

    return surface_at
