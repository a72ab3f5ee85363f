"""The registration engine on Kinect v2-like depth: flying pixels, the hand as free space and
the feature-free grid starts (issue 19, item 4)."""

from __future__ import annotations

import numpy as np
import trimesh

from graspcap.tasks.core.geometry import inv_T, make_T, pose_error
from graspcap.tasks.core.render import render
from graspcap.tasks.object_pose.registration.depth_agreement import views_agreement
from graspcap.tasks.object_pose.registration.engine import (
    RegistrationConfig,
    prepare_model,
    prepare_scene,
)
from graspcap.tasks.object_pose.registration.grid_search import grid_candidates, rotation_grid
from graspcap.tasks.object_pose.registration.point_clouds import drop_flying_pixels

K = np.array([[540.0, 0.0, 80.0], [0.0, 540.0, 60.0], [0.0, 0.0, 1.0]])


def test_flying_pixels_are_dropped_and_surfaces_kept():
    # a square at 0.8 m before a wall at 1.2 m; every pixel of the square's rim on the right
    # reads a depth between the two (the veil), as a time-of-flight camera gives it
    d = np.full((120, 160), 1.2)
    d[40:80, 40:100] = 0.8
    rng = np.random.default_rng(0)
    d[40:80, 100] = 0.8 + rng.uniform(0.05, 0.35, 40)  # veil, one pixel wide
    d[40:80, 101] = 1.2 - rng.uniform(0.05, 0.35, 40)  # and on the wall's side
    d[10, 10] = 0.0  # a dropout stays a dropout
    out = drop_flying_pixels(d, K)
    assert not out[40:80, 100:102].any()  # the whole veil
    assert (out[40:80, 40:100] == 0.8).all()  # the square with its rim
    wall = np.ones_like(d, bool)
    wall[40:80, 40:102] = False
    wall[10, 10] = False
    assert (out[wall] == 1.2).all()  # the wall, its rim at the square included
    assert out[10, 10] == 0.0


def test_a_clean_silhouette_is_never_touched():
    # a noise-free camera: a square before a wall, a one-pixel stick out of it (2 neighbours
    # at its depth, the wall beside it) and a dropout hole; nothing lies between a nearer and
    # a farther surface, so nothing is dropped, even with no share gate
    d = np.full((120, 160), 1.2)
    d[40:80, 40:100] = 0.8
    d[30:40, 60] = 0.8
    d[90:100, 10:20] = 0.0
    out = drop_flying_pixels(d, K, min_share=0.0)
    np.testing.assert_array_equal(out, d)


def _box_depth(T_c_o, box, w=160, h=120, wall_m=1.2):
    hits = render([box], [T_c_o], K, w, h)
    return np.where(hits.mesh_index == 0, hits.depth_m, wall_m), hits.mesh_index == 0


def test_the_hand_is_free_space():
    # a box at 0.8 m; the "hand" mask covers its left half and shows depth 5 cm beyond it:
    # a pose there would hide what the hand pixels show, so they count against it
    box = trimesh.creation.box([0.06, 0.06, 0.06])
    mesh = (np.asarray(box.vertices), np.asarray(box.faces))
    T = make_T(np.eye(3), [0.0, 0.0, 0.8])
    depth, seen = _box_depth(T, mesh)
    hand = np.zeros_like(seen)
    hand[:, :80] = True
    depth_hand_behind = np.where(hand & seen, depth + 0.05, depth)
    views = [(depth_hand_behind, ~hand, np.eye(4))]
    masked_only = views_agreement(views, K, mesh, T, 0.006)
    free = views_agreement(views, K, mesh, T, 0.006, free_outside=True)
    assert masked_only[0] == 1.0  # blind to the hand pixels
    n_right, n_left = int((seen & ~hand).sum()), int((seen & hand).sum())
    assert free[2] == n_right + n_left and free[0] == n_right / (n_right + n_left)
    # the hand in front of the object hides it: no evidence against the pose
    depth_hand_front = np.where(hand & seen, depth - 0.03, depth)
    front = views_agreement([(depth_hand_front, ~hand, np.eye(4))], K, mesh, T, 0.006,
                            free_outside=True)
    assert front[0] == 1.0 and front[2] == n_right


def test_grid_starts_find_a_box_that_features_cannot():
    # a 16 x 8 x 5.6 cm carton 1 m away turned 100 deg: three flat faces seen, no feature
    box = trimesh.creation.box([0.08, 0.056, 0.16])
    mesh = (np.asarray(box.vertices), np.asarray(box.faces))
    R = trimesh.transformations.rotation_matrix(np.radians(100), [1.0, 0.4, 0.2])[:3, :3]
    T_c_o = make_T(R, [0.02, -0.01, 1.0])
    hits = render([mesh], [T_c_o], K * [[2], [2], [1]], 320, 240)
    v, u = np.nonzero(hits.mesh_index == 0)
    z = hits.depth_m[v, u]
    Kb = K * [[2], [2], [1]]
    pts = np.stack([(u - Kb[0, 2]) / Kb[0, 0] * z, (v - Kb[1, 2]) / Kb[1, 1] * z, z], 1)
    cfg = RegistrationConfig(coarse_model_points=5000)
    model = prepare_model(*mesh, cfg)
    scene, _, _ = prepare_scene(pts, None, np.zeros(3), cfg)
    found = grid_candidates(scene, model, cfg, rotation_grid("I"), np.zeros(3), 4, cfg.voxel_m)
    best = found[0]
    assert best.fitness > 0.95
    # a box is its own twin under the half turns about its axes: any of them is right
    twins = [make_T(np.diag(s), [0, 0, 0]) for s in ([1, 1, 1], [1, -1, -1], [-1, 1, -1],
                                                       [-1, -1, 1])]
    errs = [pose_error(inv_T(best.T_o_s) @ Tw, T_c_o) for Tw in twins]
    rot, trans = min(errs)
    assert rot < 1.0 and trans < 0.002, errs
