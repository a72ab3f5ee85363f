"""hand_depth: a hand displaced along the one camera's axis (where the detections cannot tell
depth from size) is pulled back onto a noisy cloud sampled from the posed model's surface."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from graspcap.tasks.core.geometry import make_T
from graspcap.tasks.hand.model import HandModel, HandSide
from graspcap.tasks.hand_sfm.hand_depth import (
    HandDepthConfig,
    capsule_distance,
    refine_with_depth,
)

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])


def _surface_points(model, angles, T_w_p, scale, rng, n=4000, noise_m=0.001):
    """Points on the posed capsules' union (not inside another capsule), with noise."""
    caps = model.capsules(angles, T_w_p, scale)
    k = rng.integers(0, len(caps.radius), n)
    t = rng.uniform(0, 1, n)[:, None]
    axis = caps.start[k] + t * (caps.end[k] - caps.start[k])
    u = caps.end[k] - caps.start[k]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3))
    d -= np.sum(d * u, axis=1, keepdims=True) * u  # across the axis: on the capsule's side
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = axis + d * caps.radius[k, None]
    pts = pts[np.abs(capsule_distance(pts, caps)) < 1e-6]
    return pts + rng.normal(0, noise_m, pts.shape)


def test_cloud_recovers_depth_and_scale():
    rng = np.random.default_rng(3)
    model = HandModel(HandSide.RIGHT)
    angles = np.clip(np.tile([0.0, 0.5, 0.4, 0.3], 5) + rng.normal(0, 0.1, 20),
                     model.lower_rad, model.upper_rad)
    scale = 1.0
    T_w_p = make_T(Rotation.from_rotvec([np.pi, 0.2, 0.1]).as_matrix(), [0.0, -0.03, 0.45])
    truth = model.keypoints(angles, T_w_p, scale)
    cloud = _surface_points(model, angles, T_w_p, scale, rng)
    # the detections of one camera (the world's), exact: depth and size stay ambiguous
    uv = truth[:, :2] / truth[:, 2:] * 600.0 + [320.0, 240.0]
    # the start: the hand 15 mm further along the ray and 3 % larger (the same image nearly)
    k = 1.0 + 0.015 / 0.45
    T_start = T_w_p.copy()
    T_start[:3, 3] *= k
    start = model.keypoints(angles, T_start, scale * k)
    assert np.mean(np.linalg.norm(start - truth, axis=1)) > 0.01
    ref = refine_with_depth(
        cloud, uv[None], np.ones((1, 21), bool), np.full((1, 21), 2.0), K, np.eye(4)[None],
        np.ones(1, bool), HandSide.RIGHT, T_start, angles, np.ones(20), scale * k,
        HandDepthConfig(),
    )  # fmt: skip
    assert ref is not None
    got = model.keypoints(ref.angles_rad, ref.T_w_p, ref.scale)
    assert np.mean(np.linalg.norm(got - truth, axis=1)) < 0.003
    assert abs(ref.scale - scale) < 0.02
    assert abs(ref.offset_m) < 0.002


def test_too_few_points():
    model = HandModel(HandSide.LEFT)
    T = make_T(np.eye(3), [0.0, 0.0, 0.5])
    angles = model.rest_angles()
    assert refine_with_depth(
        np.zeros((0, 3)), np.zeros((1, 21, 2)), np.zeros((1, 21), bool), np.ones((1, 21)), K,
        np.eye(4)[None], np.ones(1, bool), HandSide.LEFT, T, angles, np.ones(20), 1.0,
        HandDepthConfig(),
    ) is None  # fmt: skip
