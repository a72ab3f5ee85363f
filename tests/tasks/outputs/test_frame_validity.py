"""frame_validity: the per-frame depth support of the object pose on synthetic depth (visible
and agreeing, covered by the hand, shifted by 2 cm, holes, out of view), the hand and camera
verdicts, and the whole per-frame table."""

from __future__ import annotations

import re

import numpy as np
import pytest
import trimesh

from graspcap.tasks.core.geometry import from_rotvec, make_T
from graspcap.tasks.core.render import render
from graspcap.tasks.outputs.frame_validity import (
    OUTSIDE_WINDOW,
    FrameValidityConfig,
    SupportScene,
    camera_solved,
    frame_validity,
    hand_used,
    object_support,
)

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
T_C_O = from_rotvec([0.3, -0.4, 0.2], [0.01, -0.02, 0.5])
"""A 10 cm box half a metre in front of the camera, turned."""


def _mesh(extents, at=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=extents)
    return np.asarray(box.vertices) + at, np.asarray(box.faces)


OBJECT = _mesh((0.1, 0.1, 0.1))
WALL = _mesh((2.0, 2.0, 0.01))
"""A wall a metre behind the object (camera frame), so the depth around it is far."""


def _hand_in_front(T_c_o: np.ndarray, width: float) -> tuple[np.ndarray, np.ndarray]:
    """A slab ``width`` wide 4 cm in front of the object (towards the camera), in the object
    frame (as the final hand is)."""
    towards = np.linalg.inv(T_c_o)[:3, :3] @ (-T_c_o[:3, 3] / np.linalg.norm(T_c_o[:3, 3]))
    slab = trimesh.creation.box(extents=(width, width, 0.01))
    # the slab's normal along the ray to the camera: rotate z onto ``towards``
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, towards)
    angle = np.arccos(np.clip(z @ towards, -1, 1))
    R = from_rotvec(axis / np.linalg.norm(axis) * angle, np.zeros(3))[:3, :3]
    vertices = np.asarray(slab.vertices) @ R.T + towards * 0.09
    return vertices, np.asarray(slab.faces)


def _depth(meshes, poses, noise_m=0.0, seed=0) -> np.ndarray:
    """What a depth camera sees of ``meshes`` at ``poses`` (camera frame) and the wall."""
    hits = render([*meshes, WALL], [*poses, make_T(np.eye(3), [0, 0, 1.5])], K, W, H)
    depth = hits.depth_m.astype(float)
    depth += np.random.default_rng(seed).normal(0.0, noise_m, depth.shape) * (depth > 0)
    return depth


def test_an_object_the_depth_shows_where_the_pose_puts_it_is_supported():
    depth = _depth([OBJECT], [T_C_O], noise_m=0.002)
    out = object_support(depth, K, SupportScene(OBJECT), T_C_O)
    assert out.supported is True and out.reason is None
    assert out.agreement > 0.99 and out.pixels > 1000  # a 10 cm box at 0.5 m, every 2nd pixel
    assert out.median_diff_m < 0.003


def test_depth_two_centimetres_further_than_the_pose_is_a_disagreement():
    shifted = make_T(np.eye(3), [0.0, 0.0, 0.02]) @ T_C_O  # the object 2 cm further away
    depth = _depth([OBJECT], [shifted], noise_m=0.002)
    out = object_support(depth, K, SupportScene(OBJECT), T_C_O)
    assert out.supported is False
    assert out.agreement < 0.1
    assert 0.015 < out.median_diff_m < 0.025
    assert out.reason.startswith(f"depth disagrees: median {out.median_diff_m * 1e3:.0f} mm, ")
    assert out.reason.endswith(f"of {out.pixels} pixels within 10 mm")
    loose = FrameValidityConfig(depth_tol_m=0.03)  # the tolerance is the config's
    assert object_support(depth, K, SupportScene(OBJECT), T_C_O, loose).supported is True


def test_an_object_the_hand_covers_cannot_be_judged_and_a_half_covered_one_can():
    hand = _hand_in_front(T_C_O, 0.3)
    depth = _depth([OBJECT, hand], [T_C_O, T_C_O], noise_m=0.002)
    out = object_support(depth, K, SupportScene(OBJECT, hand), T_C_O)
    assert out.supported is None and np.isnan(out.agreement)
    assert out.reason.startswith("too few object pixels visible: 0 of ")
    assert out.reason.endswith("outside the hand (need 50; the hand covers it)")
    # without the hand in the scene, the slab in front is depth that disagrees
    assert object_support(depth, K, SupportScene(OBJECT), T_C_O).supported is False

    small = _hand_in_front(T_C_O, 0.06)  # covers the middle of the box only
    depth = _depth([OBJECT, small], [T_C_O, T_C_O], noise_m=0.002)
    out = object_support(depth, K, SupportScene(OBJECT, small), T_C_O)
    assert out.supported is True and out.agreement > 0.95
    whole = object_support(_depth([OBJECT], [T_C_O]), K, SupportScene(OBJECT), T_C_O)
    assert 50 <= out.pixels < whole.pixels * 0.8


def test_the_detected_keypoints_mask_the_hand_the_model_misses():
    hand = _hand_in_front(T_C_O, 0.3)
    depth = _depth([OBJECT, hand], [T_C_O, T_C_O])
    centre = K @ T_C_O[:3, 3]
    kp = np.zeros((21, 3))
    kp[:, :2] = centre[:2] / centre[2] + np.linspace(-60, 60, 21)[:, None] * [1, 0.3]
    kp[:, 2] = 1.0
    cfg = FrameValidityConfig(bone_radius_px=120.0)  # bones thick enough to hide the box
    out = object_support(depth, K, SupportScene(OBJECT), T_C_O, cfg, keypoints=kp)
    assert out.supported is None and out.reason.startswith("too few object pixels visible")
    kp[:, 2] = 0.1  # below detect_confidence: not the hand
    assert object_support(depth, K, SupportScene(OBJECT), T_C_O, cfg,
                          keypoints=kp).supported is False


def test_depth_holes_and_an_object_out_of_view_cannot_be_judged():
    out = object_support(np.zeros((H, W)), K, SupportScene(OBJECT), T_C_O)
    assert out.supported is None
    assert out.reason.startswith("too few object pixels with depth: 0 of ")
    behind = make_T(np.eye(3), [0.0, 0.0, -1.0]) @ T_C_O
    far_left = make_T(np.eye(3), [-2.0, 0.0, 0.0]) @ T_C_O
    for T in (behind, far_left):
        out = object_support(_depth([OBJECT], [T_C_O]), K, SupportScene(OBJECT), T)
        assert out.supported is None and out.pixels == 0
        assert out.reason in ("object out of view", "object barely in view: 0 pixels (need 50)")


def _keypoints(n_detected: int) -> np.ndarray:
    kp = np.zeros((21, 3))
    kp[:, :2] = 100.0
    kp[:n_detected, 2] = 0.9
    return kp


def test_hand_used_and_camera_solved_say_why_not():
    inl = np.zeros(21, bool)
    inl[:8] = True
    assert hand_used(_keypoints(12), inl) == (True, None)
    assert hand_used(_keypoints(0), np.zeros(21, bool)) == (False, "no detection")
    inl[3:] = False
    assert hand_used(_keypoints(12), inl) == (False, "3 of 12 detected keypoints inliers "
                                                     "(need 6)")
    assert hand_used(_keypoints(12), inl, FrameValidityConfig(min_hand_inliers=3)) == (True,
                                                                                      None)
    assert hand_used(_keypoints(12), None) == (None, OUTSIDE_WINDOW)
    assert camera_solved(_keypoints(12), True) == (True, None)
    assert camera_solved(_keypoints(4), False) == (
        False, "interpolated from its neighbours: 4 keypoints detected")
    assert camera_solved(_keypoints(0), False) == (
        False, "interpolated from its neighbours: no detection")
    assert camera_solved(_keypoints(0), None) == (False, f"no camera: {OUTSIDE_WINDOW}")


def test_frame_validity_per_frame():
    frames = np.array([10, 11, 12, 13])
    kp = np.stack([_keypoints(21), _keypoints(0), _keypoints(21), _keypoints(21)])
    inlier = np.ones((3, 21), bool)
    inlier[1] = False  # frame 11: nothing detected, camera interpolated
    pose_valid = np.array([True, False, True])
    shifted = make_T(np.eye(3), [0.0, 0.0, 0.02]) @ T_C_O
    depth = {10: _depth([OBJECT], [T_C_O]), 11: _depth([OBJECT], [T_C_O]),
             12: _depth([OBJECT], [shifted])}
    read = []

    def read_depth(f: int) -> np.ndarray:
        read.append(f)
        return depth[f]

    out = frame_validity(frames, kp, np.array([10, 11, 12]), pose_valid, inlier,
                         np.stack([T_C_O] * 4), read_depth, K, OBJECT, None)
    assert read == [10, 11, 12]  # frame 13 has no camera: no depth read
    assert out.frames == (10, 11, 12, 13)
    assert out.hand_used == (True, False, True, None)
    assert out.hand_reason == (None, "no detection", None, OUTSIDE_WINDOW)
    assert out.camera_solved == (True, False, True, False)
    assert out.camera_reason[:2] == (None, "interpolated from its neighbours: no detection")
    assert out.object_supported == (True, True, False, None)
    assert re.match(r"depth disagrees: median 2[01] mm, 0% of \d+ pixels within 10 mm$",
                    out.object_reason[2])
    assert out.object_reason[3] == f"no camera: {OUTSIDE_WINDOW}"
    assert out.object_depth_agreement[0] == pytest.approx(1.0)
    assert out.object_depth_agreement[2] < 0.1 and out.object_depth_agreement[3] is None


def test_frame_rejected_whole_carries_its_reason():
    """A frame reconstruct_hand rejected whole (its detection another hand) is not used, with
    the stage's reason, even where some of its keypoints happen to lie near the hand."""
    frames = np.array([10, 11])
    kp = np.stack([_keypoints(21), _keypoints(21)])
    inlier = np.ones((2, 21), bool)
    why = "frame 11: the detected hand is 150 px (80% of its size) from where ..."
    depth = {10: _depth([OBJECT], [T_C_O]), 11: _depth([OBJECT], [T_C_O])}
    out = frame_validity(frames, kp, np.array([10, 11]), np.array([True, False]), inlier,
                         np.stack([T_C_O] * 2), depth.__getitem__, K, OBJECT, None,
                         rejected=("", why))  # fmt: skip
    assert out.hand_used == (True, False)
    assert out.hand_reason == (None, f"rejected whole: {why}")
