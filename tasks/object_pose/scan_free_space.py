"""Free-space check of a posed mesh against the turntable scan's own depth views.

A pose that puts model surface where a view's depth sees *past* it (the camera looks
through where the surface would be) is contradicted by that view, however well the fused
cloud's points sit on the model. A mug turned so that its handle hangs in the air, or put
upside down on its rim, explains nearly every scan point (the nearest-neighbour fitness is
blind to model surface without data) but its handle or base is in space the views saw empty.

Model points behind the measured depth are not judged against it (self-occluded or hidden
by something nearer), so the check needs no rendering: it projects surface samples into
every view and compares each with the nearest valid depth in a small window around its
pixel (silhouette pixels do not count against a pose that is off by a pixel).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.object_pose.registration.depth_agreement import image_box


@dataclass(frozen=True)
class FreeSpaceViews:
    """Scan views prepared for :func:`free_space_violation`.

    Attributes
    ----------
    depth_m : (n_views, h + 2 r, w + 2 r) float32
        Depth of each view padded by ``r = window_px // 2`` on every side; +inf where invalid,
        in the padding and outside the region judged.
    T_c_ref : (n_views, 4, 4) float
        Reference frame (the turntable at angle 0) into each view's camera frame.
    K : (3, 3) float
        Depth intrinsics.
    window_px : int
        A point is compared with the nearest valid depth in this window around its pixel.
    """

    depth_m: np.ndarray
    T_c_ref: np.ndarray
    K: np.ndarray
    window_px: int


def prepare_views(
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    window_px: int = 3,
    region_ref: np.ndarray | None = None,
) -> FreeSpaceViews:
    """``views`` [(depth_m (h, w), T_ref_c (4, 4))] -> :class:`FreeSpaceViews`; depth 0 (or
    non-finite) is invalid and never judges a point. With ``region_ref`` (k, 3) (reference
    frame, e.g. the corners of the space over the platter) only the pixel box of their
    convex hull is judged in each view."""
    K = np.asarray(K, float)
    window_px = max(int(window_px), 1)
    r = window_px // 2
    depths, T = [], []
    for depth_m, T_ref_c in views:
        T_c_ref = inv_T(np.asarray(T_ref_c, float))
        d = np.asarray(depth_m, np.float32)
        h, w = d.shape
        u0, v0, u1, v1 = (0, 0, w, h) if region_ref is None else image_box(
            K, transform_points(T_c_ref, np.asarray(region_ref, float)), w, h
        )  # fmt: skip
        out = np.full((h + 2 * r, w + 2 * r), np.inf, np.float32)
        box = d[v0:v1, u0:u1]
        out[r + v0 : r + v1, r + u0 : r + u1] = np.where(np.isfinite(box) & (box > 0), box, np.inf)
        depths.append(out)
        T.append(T_c_ref)
    return FreeSpaceViews(np.stack(depths), np.stack(T), K, window_px)


def free_space_violation(fs: FreeSpaceViews, points_ref: np.ndarray, tol_m: float) -> float:
    """Share of (point, view) pairs, over the ``points_ref`` (n, 3) (reference frame) that
    project in front of a view's camera onto a window with valid depth, in which the nearest
    depth of the window sees more than ``tol_m`` past the point (0 when no pair is judged)."""
    n_views, hp, wp = fs.depth_m.shape
    r = fs.window_px // 2
    h, w = hp - 2 * r, wp - 2 * r
    offsets = [dv * wp + du for dv in range(-r, r + 1) for du in range(-r, r + 1)]
    judged = violated = 0
    for i in range(n_views):
        p = transform_points(fs.T_c_ref[i], points_ref)
        p = p[p[:, 2] > 1e-6]
        uv = np.floor((p @ fs.K.T)[:, :2] / p[:, 2:3] + 0.5).astype(np.int64)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        z = p[inside, 2]
        centre = (uv[inside, 1] + r) * wp + uv[inside, 0] + r
        flat = fs.depth_m[i].ravel()
        near = np.full(len(z), np.inf, np.float32)
        for off in offsets:
            np.minimum(near, flat[centre + off], out=near)
        valid = np.isfinite(near)
        judged += int(valid.sum())
        violated += int(np.count_nonzero(near[valid] > z[valid] + tol_m))
    return violated / judged if judged else 0.0
