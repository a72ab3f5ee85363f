"""The object's points near the hand in several steady frames: found per view, then joined.

Fused first, the views sit a camera error apart and the object of one view merges with the
background of another into one cluster wider than any object (wild [78643, 9]: 34 points of 7
views were left, the stage refused and the first frame's flipped pose was kept)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from graspcap.tasks.object_pose.adjustment_region import near_hand, region_per_view
from graspcap.tasks.object_pose.estimate_adjustment import PRESETS


def _grid(lo, hi, step=0.002):
    axes = [np.arange(a, b + 1e-9, step) if b > a else np.array([a])
            for a, b in zip(lo, hi, strict=True)]  # fmt: skip
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _scene(shift_m: float):
    """A palm-sized slab of hand, a 4 cm ball touching it, a wall 2 cm behind the ball; the
    whole view moved by ``shift_m`` along x (its camera's error)."""
    hand = _grid((-0.04, -0.04, 0.50), (0.04, 0.04, 0.52))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ball = np.array([0.085, 0.0, 0.51]) + 0.04 * d[d[:, 2] < 0.3]  # the side a camera sees
    wall = _grid((0.145, -0.25, 0.40), (0.145, 0.25, 0.70), 0.003)
    move = np.array([shift_m, 0.0, 0.0])
    return hand + move, ball + move, wall + move


def test_each_view_keeps_its_object_and_leaves_the_background_out():
    config = PRESETS["default"]
    radius_m = 0.04
    views = [_scene(0.0), _scene(-0.012)]  # the second camera 12 mm off
    points = [np.concatenate([ball, wall]) for _, ball, wall in views]
    hands = [hand for hand, _, _ in views]
    balls = np.concatenate([ball for _, ball, _ in views])
    walls = np.concatenate([wall for _, _, wall in views])

    region = region_per_view(points, hands, radius_m, config)
    near_ball = cKDTree(balls).query(region)[0] < 1e-9
    assert near_ball.all()  # no wall point
    assert len(region) >= 0.95 * len(balls)  # and (nearly) every ball point

    # fused, the first view's ball touches the second view's wall: one wide cluster, wall kept
    fused = near_hand(np.concatenate(points), np.concatenate(hands), radius_m, config)
    assert (cKDTree(walls).query(fused)[0] < 1e-9).sum() > 100

    # a view without a hand of its own adds nothing while another has one
    lone = region_per_view([points[0], points[1]], [hands[0], hands[1][:5]], radius_m, config)
    assert len(lone) == len(near_hand(points[0], hands[0], radius_m, config))
