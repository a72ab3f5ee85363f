"""The depth surfaces' lattice in metres (``surface_cloud``'s ``spacing_m``): a far hand is
sampled finely enough for the normals to come from its own fingers.

The scene: five curved fingers (cylinders 16 mm across, 4 mm apart, axes vertical) before a
wall that slopes away behind them, seen by a 960 x 540 camera with f = 520 px. At 1 m a
finger is ~8 px wide; on the 3 px lattice the normals' reach (2 nodes each side, 12 px)
lands beyond a finger's edges, on the wall or the next finger, and its normal is theirs.
"""

from __future__ import annotations

import numpy as np

from graspcap.tasks.hand_sfm.surface_clouds import surface_cloud

W, H = 960, 540
R = 0.008
CENTRES = np.arange(-2, 3) * 0.02


def _fingers(K: np.ndarray, z_m: float) -> np.ndarray:
    """Depth image (H, W) of the fingers, their front at depth ``z_m``, 80 mm tall, before a
    wall 0.3-0.6 m behind them (its depth grows downwards in the image)."""
    fx, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    x = (np.arange(W) - cx) * z_m / fx  # lateral position at the fingers' depth
    depth = np.repeat((z_m + 0.3 + 0.3 * np.arange(H) / H)[:, None], W, axis=1)
    rows = np.abs(np.arange(H) - cy) * z_m / K[1, 1] < 0.04
    for centre in CENTRES:
        off = np.abs(x - centre)
        inside = off < R
        front = z_m + R - np.sqrt(np.maximum(R**2 - off**2, 0.0))
        depth[np.ix_(rows, inside)] = front[inside]
    return depth


def _right_normals(cloud, z_m: float) -> float:
    """Share of the cloud's finger points whose normal is within 30 deg of the cylinder's."""
    p, n = cloud.points, cloud.normals
    on = p[:, 2] < z_m + 0.1
    axis_x = CENTRES[np.argmin(np.abs(p[on, :1] - CENTRES[None]), axis=1)]
    true = np.stack([p[on, 0] - axis_x, np.zeros(on.sum()), p[on, 2] - (z_m + R)], axis=1)
    true /= np.linalg.norm(true, axis=1, keepdims=True)
    return float(np.mean(np.abs(np.sum(true * n[on], axis=1)) > np.cos(np.radians(30))))


def _cloud(depth, K, centre_z, **kw):
    return surface_cloud(depth, K, np.array([0.0, 0.0, centre_z]), radius_m=0.15,
                         stride_px=3, min_points=1, **kw)  # fmt: skip


def test_a_far_hand_gets_its_own_normals_on_a_metric_lattice():
    K = np.array([[520.0, 0, W / 2], [0, 520.0, H / 2], [0, 0, 1]])
    depth = _fingers(K, 1.0)
    fixed = _cloud(depth, K, 1.0)
    metric = _cloud(depth, K, 1.0, spacing_m=0.0025)
    assert fixed.stride_px == 3 and metric.stride_px == 1
    shares = _right_normals(fixed, 1.0), _right_normals(metric, 1.0)
    # measured: 12 % of 80 finger points on the 3 px lattice, 100 % of 777 on the 1 px one
    assert shares[1] >= 0.9 and shares[0] <= 0.6, shares


def test_a_near_hand_keeps_the_coarse_lattice():
    """At 0.45 m before f = 615 px the metric lattice is the 3 px one: the same cloud."""
    K = np.array([[615.0, 0, W / 2], [0, 615.0, H / 2], [0, 0, 1]])
    depth = _fingers(K, 0.45)
    fixed = _cloud(depth, K, 0.45)
    metric = _cloud(depth, K, 0.45, spacing_m=0.0025)
    assert metric.stride_px == fixed.stride_px == 3
    np.testing.assert_array_equal(metric.points, fixed.points)
