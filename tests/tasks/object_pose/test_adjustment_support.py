"""What estimate_adjustment needs before it believes a pose (issue 19, item 4): the judged
pixels it asks for scale with the pixels the object covers (a small object far away shows
few), and the hand it looks beside is the masked pixels' cluster that holds the most pixels."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from graspcap.tasks.core.geometry import inv_T, make_T, pose_error
from graspcap.tasks.core.render import render
from graspcap.tasks.object_pose.adjustment_region import (
    hand_cluster,
    needed_pixels,
    surface_area_m2,
)
from graspcap.tasks.object_pose.estimate_adjustment import PRESETS
from graspcap.tasks.object_pose.registration.engine import prepare_model
from tests.registration_rig import HEIGHT, WIDTH, K


def _model(mesh: trimesh.Trimesh):
    return prepare_model(mesh.vertices, mesh.faces, PRESETS["default"].registration)


def test_the_mean_silhouette_is_a_quarter_of_the_surface_area():
    box = trimesh.creation.box([0.06, 0.04, 0.1])
    area = surface_area_m2(box.vertices, box.faces)
    assert np.isclose(area, box.area)
    rng = np.random.default_rng(3)
    counts = []
    for _ in range(40):  # random turns at 0.8 m: the mean silhouette (Cauchy) is area / 4
        R = trimesh.transformations.random_rotation_matrix(rng.random(3))[:3, :3]
        hits = render([(box.vertices, box.faces)], [make_T(R, [0.0, 0.0, 0.8])], K, WIDTH, HEIGHT)
        counts.append(int((hits.mesh_index == 0).sum()))
    expected = area / 4 * K[0, 0] * K[1, 1] / 0.8**2
    assert abs(np.mean(counts) / expected - 1) < 0.1, (np.mean(counts), expected)


def test_a_small_far_object_needs_fewer_judged_pixels_a_large_one_min_points():
    cfg = PRESETS["default"]
    views = [(None, None, np.eye(4))]
    ball = trimesh.creation.icosphere(3, radius=0.035)
    model, area = _model(ball), surface_area_m2(ball.vertices, ball.faces)
    at = [make_T(np.eye(3), [0.0, 0.0, z]) for z in (0.5, 0.85, 3.0)]
    near, far, very_far = (needed_pixels(views, K, model, area, T, cfg) for T in at)
    # a 7 cm ball at 0.85 m covers ~1900 pixels, ~480 judged at stride 2: 15 % of them
    assert cfg.min_points_floor < far < near <= cfg.min_points
    assert 60 <= far <= 80, far
    assert very_far == cfg.min_points_floor
    mug = trimesh.creation.cylinder(radius=0.045, height=0.15)
    assert needed_pixels(views, K, _model(mug), mug.area, at[1], cfg) == cfg.min_points
    # every view adds the pixels the object covers in it
    two = needed_pixels(views * 2, K, model, area, at[1], cfg)
    assert two == min(cfg.min_points, 2 * far) or abs(two - 2 * far) <= 1


def test_the_hand_is_the_cluster_holding_the_most_pixels_not_voxels():
    """A hand 0.35 m away (0.5 mm between pixels: ~60 pixels per 4 mm voxel) and background
    at 1.07 m seen through the mask's rim (2.5 mm between pixels): more voxels, fewer pixels."""
    g = np.arange(0.0, 0.06, 0.0005)
    hand = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    hand = np.column_stack([hand, np.full(len(hand), 0.35)])
    b = np.arange(0.0, 0.2, 0.0025)
    back = np.stack(np.meshgrid(b, b[:40]), -1).reshape(-1, 2) + [0.3, 0.0]
    back = np.column_stack([back, np.full(len(back), 1.07)])
    assert len(hand) > len(back)
    cfg = PRESETS["default"]
    found = hand_cluster(np.concatenate([back, hand]), cfg.cluster_voxel_m, cfg.cluster_eps_m)
    assert np.allclose(found[:, 2], 0.35, atol=0.003)


@pytest.mark.slow
def test_real_detector_spray_bottle_is_found_beside_the_hand(tmp_path):
    """real-detector [56705, 3] (tuning seed, 60 frames; a spray bottle 0.35 m away): the
    hand cluster by voxels was background at 1.07 m and the stage refused (fitness 0.25);
    measured since: built from 7 fused frames, the tracked object 0.47 deg / 0.7 mm per frame
    (median of ``tracking.T_c_o``; 0.43 deg / 4.9 mm through propagate_poses), 203 s."""
    from graspcap.synth import config_for, generate_session
    from graspcap.synth.evaluate import load_truth
    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

    d = generate_session(tmp_path, [56705, 3], config_for("real-detector", 60))
    configs, res = configs_for(), {}
    for name in ("load_session", "register_object", "detect_keypoints", "select_steady",
                 "joint_solve", "reconstruct_hand", "crosscheck_sfm", "fit_hand",
                 "estimate_adjustment"):  # fmt: skip
        res[name] = run_stage(STAGES[name], d, configs[name], res)
    adj, truth = res["estimate_adjustment"], load_truth(d)
    off = res["select_steady"].steady_from - int(truth["steady_from"])
    T_obj = truth["T_adj"] @ truth["T_w_o_stage1"]
    n = len(truth["T_w_c"])
    errs = [pose_error(T, inv_T(truth["T_w_c"][off + i]) @ T_obj)
            for i, T in enumerate(adj.tracking.T_c_o) if 0 <= off + i < n]  # fmt: skip
    rot, trans = np.median(np.asarray(errs), axis=0)
    assert rot < 2.0 and trans < 0.008, (rot, trans)
