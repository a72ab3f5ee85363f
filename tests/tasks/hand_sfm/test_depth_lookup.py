"""metric_scale.depth_lookup: the median of the non-zero depth in a window around each pixel,
checked against a plain per-pixel loop (windows clipped at the border, no depth -> 0)."""

from __future__ import annotations

import numpy as np

from graspcap.tasks.hand_sfm.metric_scale import depth_lookup


def _reference(depth: np.ndarray, uv: np.ndarray, window_px: int) -> np.ndarray:
    h, w = depth.shape
    out = np.zeros(len(uv))
    for k, (u, v) in enumerate(np.rint(uv).astype(int)):
        r, c = max(v - window_px, 0), max(u - window_px, 0)
        win = depth[r : v + window_px + 1, c : u + window_px + 1]
        vals = win[win > 0]
        if 0 <= u < w and 0 <= v < h and vals.size:
            out[k] = np.median(vals)
    return out


def test_matches_a_per_pixel_loop():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 1.0, (48, 64))
    depth[rng.random(depth.shape) < 0.4] = 0.0  # dropouts
    depth[10:20, 10:20] = 0.0  # a hole larger than the window
    uv = np.vstack([
        np.column_stack([rng.uniform(-5, 70, 2000), rng.uniform(-5, 55, 2000)]),
        [[15, 15], [0, 0], [63, 47], [64, 47], [-0.4, 3], [63.6, 10]],
    ])  # fmt: skip
    for window_px in (0, 2, 3):
        got = depth_lookup(lambda _: depth, window_px)(0, uv)
        np.testing.assert_array_equal(got, _reference(depth, uv, window_px))
    got = depth_lookup(lambda _: depth, 2)(0, uv)
    assert got[-6] == 0.0 and got[-3] == 0.0  # inside the hole; outside the image
    assert (got > 0).sum() > 1000
