"""Change-point statistics of select_steady: windowed residual energies, robust
standardisation, CUSUM, and the matched filter on the direction of the last motion.

``res`` everywhere is (n, 21, 2) float residual vectors (px) of each frame's keypoints against
one fixed hand posed per frame, NaN where unknown or gross.
"""

from __future__ import annotations

import numpy as np


def window_scores(res: np.ndarray, half: int, min_points: int) -> np.ndarray:
    """(n,) RMS px of the residual vectors averaged over frames i-half .. i+half.

    Each joint's mean vector is weighted by its count, so pure noise gives the same expected
    score whatever the window holds.
    """
    n = len(res)
    valid = np.isfinite(res[..., 0])
    filled = np.where(valid[..., None], res, 0.0)
    c_sum = np.concatenate([np.zeros((1, 21, 2)), np.cumsum(filled, axis=0)])
    c_cnt = np.concatenate([np.zeros((1, 21)), np.cumsum(valid, axis=0)])
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) + half + 1, 0, n)
    total = c_sum[hi] - c_sum[lo]
    count = c_cnt[hi] - c_cnt[lo]
    energy = np.sum(total**2, axis=2) / np.maximum(count, 1)  # count * |mean|^2
    seen = count > 0
    scores = np.sqrt(np.sum(energy, axis=1) / np.maximum(seen.sum(1), 1))
    scores[(seen.sum(1) < min_points) | ~valid.any(1)] = np.nan
    return scores


def standardise(values, ref):
    """(values - median) / (1.4826 MAD) over the finite values of the reference frames, and
    (median, spread); None when fewer than 3 reference values are finite."""
    ref_values = values[ref][np.isfinite(values[ref])]
    if len(ref_values) < 3:
        return None
    med = float(np.median(ref_values))
    spread = 1.4826 * float(np.median(np.abs(ref_values - med)))
    spread = max(spread, 1e-3 * max(abs(med), 1e-9), 1e-12)
    return (values - med) / spread, med, spread


def cusum(z, drift, start=0):
    """(n + 1,) ``sum_{start <= i < t} (z_i - drift)``, NaN frames counting 0; -inf before
    ``start``."""
    steps = np.where(np.isfinite(z[start:]), z[start:] - drift, 0.0)
    return np.concatenate([np.full(start, -np.inf), [0.0], np.cumsum(steps)])


def matched_filter(res, onset, pattern_frames, drift, min_points, smooth_frames, latest,
                   earliest=0):
    """(pattern (21, 2), z (n,), cusum (n + 1,), onset) of the projection of every frame's
    residual on the direction of the frames ``onset - pattern_frames .. onset - 1``,
    standardised by the frames from ``onset + smooth_frames``, its CUSUM with ``drift`` from
    the window's start, the onset between ``earliest`` and ``latest``; None when that window
    holds no residual or too few steady frames follow."""
    n = len(res)
    hi = onset
    lo = max(hi - pattern_frames, 0)
    valid = np.isfinite(res[..., 0])
    r = np.where(valid[..., None], res, 0.0)
    total = r[lo:hi].sum(0)
    if hi <= 0 or not np.any(total):
        return None
    D = np.broadcast_to(total, r.shape).copy()
    D[lo:hi] -= r[lo:hi]  # leave each window frame out of its own direction
    norm = np.sqrt(np.sum(D**2 * valid[..., None], axis=(1, 2)))
    a = np.sum(r * D, axis=(1, 2)) / np.maximum(norm, 1e-12)
    a[(valid.sum(1) < min_points) | (norm <= 0)] = np.nan
    found = standardise(a, np.arange(min(onset + smooth_frames, n - 1), n))
    if found is None:
        return None
    z = found[0]
    sums = cusum(z, drift, lo)
    sums[latest + 1 :] = -np.inf  # the last motion's frames lie just before the coarse onset
    sums[: min(earliest, latest)] = -np.inf
    return total / np.linalg.norm(total), z, sums, int(np.argmax(sums))
