"""Free-space check of a posed mesh against the turntable scan's own depth views.

A pose that puts model surface where a view's depth sees *past* it (the camera looks
through where the surface would be) is contradicted by that view, however well the fused
cloud's points sit on the model. A mug turned so that its handle hangs in the air, or put
upside down on its rim, explains nearly every scan point (the nearest-neighbour fitness is
blind to model surface without data) but its handle or base is in space the views saw empty.

Model points behind the measured depth are not judged against it (self-occluded or hidden
by something nearer), so the check needs no rendering: it projects surface samples into
every view and compares with a depth image eroded to the nearest valid depth in a small
window (silhouette pixels do not count against a pose that is off by a pixel).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter

from graspcap.tasks.depth_agreement import image_box
from graspcap.tasks.geometry import inv_T, transform_points


@dataclass(frozen=True)
class FreeSpaceViews:
    """Scan views prepared for :func:`free_space_violation`.

    Attributes
    ----------
    near_depth_m : (n_views, h, w) float
        Nearest valid depth within the window around each pixel; 0 where there is none or
        outside the region judged.
    T_c_ref : (n_views, 4, 4) float
        Reference frame (the turntable at angle 0) into each view's camera frame.
    K : (3, 3) float
        Depth intrinsics.
    """

    near_depth_m: np.ndarray
    T_c_ref: np.ndarray
    K: np.ndarray


def prepare_views(
    views: Sequence[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    window_px: int = 3,
    region_ref: np.ndarray | None = None,
) -> FreeSpaceViews:
    """``views`` [(depth_m (h, w), T_ref_c (4, 4))] -> :class:`FreeSpaceViews`; depth 0 (or
    non-finite) is invalid and never judges a point. With ``region_ref`` (k, 3) (reference
    frame, e.g. the corners of the space over the platter) only the pixel box of their
    convex hull is judged in each view (and eroded: the rest of the image costs nothing)."""
    K = np.asarray(K, float)
    near, T = [], []
    for depth_m, T_ref_c in views:
        T_c_ref = inv_T(np.asarray(T_ref_c, float))
        d = np.asarray(depth_m, float)
        h, w = d.shape
        u0, v0, u1, v1 = (0, 0, w, h) if region_ref is None else image_box(
            K, transform_points(T_c_ref, np.asarray(region_ref, float)), w, h
        )  # fmt: skip
        out = np.zeros((h, w))
        if u1 > u0 and v1 > v0:
            box = d[v0:v1, u0:u1]
            box = np.where(np.isfinite(box) & (box > 0), box, np.inf)
            box = minimum_filter(box, size=max(int(window_px), 1), mode="nearest")
            out[v0:v1, u0:u1] = np.where(np.isfinite(box), box, 0.0)
        near.append(out)
        T.append(T_c_ref)
    return FreeSpaceViews(np.stack(near), np.stack(T), K)


def free_space_violation(fs: FreeSpaceViews, points_ref: np.ndarray, tol_m: float) -> float:
    """Share of (point, view) pairs, over the ``points_ref`` (n, 3) (reference frame) that
    project into a view with valid depth in front of that view's camera, in which the depth
    sees more than ``tol_m`` past the point (0 when no pair is judged)."""
    n_views, h, w = fs.near_depth_m.shape
    judged = violated = 0
    for i in range(n_views):
        p = transform_points(fs.T_c_ref[i], points_ref)
        z = p[:, 2]
        front = z > 1e-6
        p, z = p[front], z[front]
        uv = np.floor((p @ fs.K.T)[:, :2] / z[:, None] + 0.5).astype(np.int64)
        u, v = uv[:, 0], uv[:, 1]
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d = fs.near_depth_m[i][v[inside], u[inside]]
        valid = d > 0
        judged += int(valid.sum())
        violated += int(np.count_nonzero(d[valid] > z[inside][valid] + tol_m))
    return violated / judged if judged else 0.0
