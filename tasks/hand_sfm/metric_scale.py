"""Metric scale of an up-to-scale reconstruction from the aligned depth at the keypoints.

For an inlier observation of joint j in frame i the camera sees the skin above the joint
centre, so ``depth(uv) + surface_offset_m[j]`` should equal ``s * z_ij`` where ``z_ij`` is
the reconstructed depth of the joint in that camera (reconstruction units). The scale ``s``
is the robust median of those ratios; ratios far from it (the object in front of a finger,
background at a silhouette edge) are rejected.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

DepthLookup = Callable[[int, np.ndarray], np.ndarray]
"""``depth_at(frame, uv_px (k, 2)) -> depth_m (k,)``: aligned depth in metres at the pixels of
video frame ``frame``; 0 (or NaN) where the sensor has no valid depth."""


def window_median(depth_m: np.ndarray, uv_px: np.ndarray, window_px: int = 2) -> np.ndarray:
    """Median of the valid (finite, > 0) depths in the (2 * window_px + 1)^2 square around
    each rounded pixel, clipped at the image border; 0 where the square holds none or the
    pixel lies outside the image.

    depth_m : (h, w) metres; uv_px : (k, 2) pixels. Returns (k,) metres.
    """
    h, w = depth_m.shape
    u, v = np.rint(np.asarray(uv_px, dtype=float).reshape(-1, 2)).astype(int).T
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    offsets = np.arange(-window_px, window_px + 1)
    rows, cols = v[:, None] + offsets, u[:, None] + offsets  # (k, 2 * window_px + 1)
    in_rows, in_cols = (rows >= 0) & (rows < h), (cols >= 0) & (cols < w)
    win = depth_m[np.clip(rows, 0, h - 1)[:, :, None], np.clip(cols, 0, w - 1)[:, None, :]]
    # NaN > 0 is False: invalid readings drop out too, as do pixels beyond the border
    valid = ((win > 0) & in_rows[:, :, None] & in_cols[:, None, :]).reshape(len(u), -1)
    n = valid.sum(axis=1)
    # each row's median of the valid readings (as np.nanmedian): sorted with the invalid ones
    # last, the middle one or the mean of the middle two, in the depth's own float type
    ranked = np.sort(np.where(valid, win.reshape(len(u), -1), np.inf), axis=1)
    has = np.flatnonzero(inside & (n > 0))
    lo, hi = ranked[has, (n[has] - 1) // 2], ranked[has, n[has] // 2]
    out = np.zeros(len(u))
    out[has] = (lo + hi) / ranked.dtype.type(2)
    return out


def depth_lookup(read: Callable[[int], np.ndarray], window_px: int = 2) -> DepthLookup:
    """A :data:`DepthLookup` over the frames ``read(frame) -> (h, w)`` metres, by
    :func:`window_median` (frames read lazily, as the lookup asks for them)."""

    def depth_at(frame: int, uv_px: np.ndarray) -> np.ndarray:
        return window_median(read(int(frame)), uv_px, window_px)

    return depth_at


def depth_lookup_from_frames(depth_m: np.ndarray, window_px: int = 2) -> DepthLookup:
    """A :data:`DepthLookup` over depth images (n, h, w) in metres, by :func:`window_median`."""
    depth_m = np.asarray(depth_m, dtype=float)
    return depth_lookup(lambda frame: depth_m[frame], window_px)


@dataclass(frozen=True)
class ScaleEstimate:
    """Result of :func:`estimate_scale`.

    scale_m_per_unit : metres per reconstruction unit.
    n_samples : observations with valid depth; n_inliers : those kept.
    spread : median absolute relative deviation of the kept ratios.
    inlier : (k,) bool, the input samples kept.
    """

    scale_m_per_unit: float
    n_samples: int
    n_inliers: int
    spread: float
    inlier: np.ndarray


def ratio_mode(ratio: np.ndarray, rel_tol: float) -> float:
    """Centre of the densest window of relative half-width ``rel_tol`` among ratios (k,) > 0.

    Readings of a hand are often mostly wrong (the object or the hand's own palm and fingers
    in front of a joint, all nearer than the joint's skin), so a median can sit among the
    wrong ones; the correct readings form the one tight cluster.
    """
    lr = np.sort(np.log(ratio))
    hi = np.searchsorted(lr, lr + 2 * rel_tol, side="right")
    k = int(np.argmax(hi - np.arange(len(lr))))
    return float(np.exp(np.median(lr[k : hi[k]])))


def estimate_scale(
    z_units: np.ndarray,
    depth_m: np.ndarray,
    offset_m: np.ndarray,
    *,
    rel_tol: float,
    min_samples: int,
) -> ScaleEstimate | None:
    """Robust ratio ``(depth_m + offset_m) / z_units`` over k samples, all arrays (k,): the
    densest cluster (:func:`ratio_mode`), refined by the median of the ratios within
    ``rel_tol`` of it.

    Returns None when fewer than ``min_samples`` samples survive.
    """
    z = np.asarray(z_units, dtype=float)
    d = np.asarray(depth_m, dtype=float)
    valid = np.isfinite(z) & np.isfinite(d) & (z > 0) & (d > 0)
    ratio = (d[valid] + np.asarray(offset_m, dtype=float)[valid]) / z[valid]
    if len(ratio) < min_samples:
        return None
    s = ratio_mode(ratio, rel_tol)
    for _ in range(3):
        keep = np.abs(ratio / s - 1.0) < rel_tol
        if keep.sum() < min_samples:
            return None
        s = float(np.median(ratio[keep]))
    spread = float(np.median(np.abs(ratio[keep] / s - 1.0)))
    inlier = np.zeros(len(z), bool)
    inlier[np.flatnonzero(valid)[keep]] = True
    return ScaleEstimate(s, int(len(ratio)), int(keep.sum()), spread, inlier)
