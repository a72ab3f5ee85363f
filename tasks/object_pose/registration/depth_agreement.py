"""Does a depth image show a mesh at a pose? Rendered depth against measured depth.

Unlike a nearest-neighbour fitness, the comparison penalises model surface where the depth
shows empty space (a mug's handle turned into the air).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.core.render import render


def image_box(
    K: np.ndarray, points_c: np.ndarray, width: int, height: int
) -> tuple[int, int, int, int]:
    """Pixel box (u0, v0, u1, v1), end exclusive, within the image, holding every pixel whose
    centre ray can hit the convex hull of ``points_c`` (n, 3) (camera frame); the whole image
    when a point is not in front of the camera."""
    if not np.all(points_c[:, 2] > 1e-9):
        return 0, 0, width, height
    uv = points_c[:, :2] / points_c[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    lo = np.floor(uv.min(axis=0)).astype(int) - 1
    hi = np.ceil(uv.max(axis=0)).astype(int) + 2
    return (
        int(np.clip(lo[0], 0, width)), int(np.clip(lo[1], 0, height)),
        int(np.clip(hi[0], 0, width)), int(np.clip(hi[1], 0, height)),
    )  # fmt: skip


def depth_agreement(
    depth_m: np.ndarray,
    K: np.ndarray,
    mesh: tuple[np.ndarray, np.ndarray],
    T_c_o: np.ndarray,
    tol_m: float,
    keep: np.ndarray | None = None,
    stride_px: int = 1,
) -> tuple[float, float, int]:
    """Does the depth (h, w) show the mesh (vertices (n, 3), faces (m, 3)) at ``T_c_o``?

    The mesh is rendered; over the pixels where it is visible, the depth valid and ``keep``
    (h, w) bool True (all when None), a pixel agrees when ``|depth - rendered| <= tol_m``.
    Depth further away means the camera sees through where the model would be (a handle
    placed where there is none); nearer depth means something covers it: both count against
    the pose. Unlike a nearest-neighbour fitness, this penalises model surface that the depth
    does not show. Only every ``stride_px``-th pixel of every ``stride_px``-th row is judged
    (a grid anchored at the mesh's pixel box: a score from a fraction of the rays). Returns
    (agreeing share, RMS depth difference of the agreeing pixels, pixels judged).
    """
    n, n_agree, sq = _compare(depth_m, K, mesh, T_c_o, tol_m, keep, stride_px)
    if n == 0 or n_agree == 0:
        return 0.0, 0.0, n
    return n_agree / n, float(np.sqrt(sq / n_agree)), n


def _compare(
    depth_m: np.ndarray,
    K: np.ndarray,
    mesh: tuple[np.ndarray, np.ndarray],
    T_c_o: np.ndarray,
    tol_m: float,
    keep: np.ndarray | None,
    stride_px: int = 1,
    free_outside: bool = False,
) -> tuple[int, int, float]:
    """(pixels judged, pixels agreeing, sum of their squared depth differences): the mesh is
    rendered only over the pixel box its vertices project into (identical rays, fewer), at
    every ``stride_px``-th pixel and row of it. With ``free_outside`` the pixels outside
    ``keep`` whose depth lies more than ``tol_m`` beyond the rendered mesh are judged too, as
    disagreeing: what is seen there (a hand) is seen through where the mesh would be."""
    h, w = depth_m.shape
    T_c_o = np.asarray(T_c_o, float)
    K = np.asarray(K, float)
    u0, v0, u1, v1 = image_box(K, transform_points(T_c_o, mesh[0]), w, h)
    if u1 <= u0 or v1 <= v0:
        return 0, 0, 0.0
    s = max(int(stride_px), 1)
    K_box = K.copy()
    K_box[:2, 2] -= (u0, v0)
    K_box[:2] /= s  # pixel (u0 + s i, v0 + s j) of the image is pixel (i, j) of the grid
    K_box[2] = (0.0, 0.0, 1.0)
    depth_m = depth_m[v0:v1:s, u0:u1:s]
    hits = render([mesh], [T_c_o], K_box, depth_m.shape[1], depth_m.shape[0])
    seen = (hits.mesh_index == 0) & (depth_m > 0)
    through = 0
    if keep is not None:
        kept = keep[v0:v1:s, u0:u1:s]
        if free_outside:
            out = seen & ~kept
            through = int(np.count_nonzero(depth_m[out] > hits.depth_m[out] + tol_m))
        seen &= kept
    diff = depth_m[seen] - hits.depth_m[seen]
    agree = np.abs(diff) <= tol_m
    return int(seen.sum()) + through, int(agree.sum()), float(np.sum(diff[agree] ** 2))


def views_agreement(
    views: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    K: np.ndarray,
    mesh: tuple[np.ndarray, np.ndarray],
    T_w_o: np.ndarray,
    tol_m: float,
    stride_px: int = 1,
    free_outside: bool = False,
) -> tuple[float, float, int]:
    """Does the depth show the object at ``T_w_o``? In every view ``(depth (h, w), keep
    (h, w), T_ref_c (4, 4))`` renders the mesh at ``inv(T_ref_c) @ T_w_o``; over the pixels
    where it is visible, ``keep`` is True (the hand is masked out) and the depth valid, a
    pixel agrees when ``|depth - rendered| <= tol_m``. Depth further away means the camera
    sees through where the object would be; nearer depth means something unmasked covers it
    (or the pose is inside another surface): both count against the pose. Returns (agreeing
    share, RMS depth difference of the agreeing pixels, pixels judged), over all views, on
    every ``stride_px``-th pixel and row (:func:`depth_agreement`). With ``free_outside``
    the masked pixels (the hand) count against the pose where their depth lies beyond the
    rendered object: the object can be behind the hand, never in front of what is seen."""
    n = n_agree = 0
    sq = 0.0
    for depth, keep, T_ref_c in views:
        dn, da, dsq = _compare(
            depth, K, mesh, inv_T(T_ref_c) @ T_w_o, tol_m, keep, stride_px, free_outside
        )
        n, n_agree, sq = n + dn, n_agree + da, sq + dsq
    if n == 0 or n_agree == 0:
        return 0.0, 0.0, n
    return n_agree / n, float(np.sqrt(sq / n_agree)), n
