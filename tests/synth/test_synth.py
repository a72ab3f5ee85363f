"""The synthetic rig: contract, truth self-consistency, grasp physics, noise, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh

from graspcap.synth import OBJECT_NAMES, PRESETS, generate, generate_session, procedural_object
from graspcap.synth.objects import load_object
from graspcap.synth.sensors import detect_keypoints
from graspcap.synth.session import participant_scale
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, project, rot_z, transform_points
from graspcap.tasks.core.render import render
from graspcap.tasks.core.render import render as cast
from graspcap.tasks.hand.model import FINGERTIPS, SURFACE_OFFSET_M, HandModel
from graspcap.tasks.session.load_session import validate_session

SMALL = PRESETS["realistic"].model_copy(
    update={"frames": 14, "scan_views": (6, 6), "adjust_fraction": (0.2, 0.25)}
)
TRUTH_KEYS = {"T_w_o_stage1", "T_adj", "steady_from", "T_w_c", "joints_w", "T_turntable_o_scan",
              "T_w_p", "T_o_p", "hand_scale", "joint_angles_rad", "difficulty", "seed"}


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    return generate_session(tmp_path_factory.mktemp("synth"), [11, 0], SMALL)


def _load(session: Path):
    manifest = json.loads((session / "session.json").read_text())
    truth = json.loads((session / "ground_truth/truth.json").read_text())
    mesh = trimesh.load(session / "object.ply", process=False)
    return manifest, truth, mesh


def _depth_m(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(float) * 0.001


def _median_depth_error_mm(observed_m: np.ndarray, expected_m: np.ndarray) -> tuple[float, float]:
    """Median |diff| (mm) on pixels the model covers and the sensor measured; their share."""
    model = expected_m > 0
    both = model & (observed_m > 0)
    return float(np.median(np.abs(observed_m - expected_m)[both]) * 1000), both.sum() / model.sum()


def test_session_validates_and_has_documented_keys(session):
    assert validate_session(session) == []
    manifest, truth, mesh = _load(session)
    assert manifest["format"] == "grasp-capture-session/1"
    assert manifest["session_id"].startswith("synth-s11-000-")
    assert manifest["grasp"]["steady_from"] is None  # default: the builder detects it
    assert manifest["grasp"]["count"] == 14
    assert len(manifest["scan"]["views"]) == 6
    assert TRUTH_KEYS <= set(truth)
    steady = truth["steady_from"]
    assert 2 <= steady < 14 and len(truth["T_w_c"]) == 14 - steady
    np.testing.assert_allclose(truth["T_w_c"][0], np.eye(4), atol=1e-12)
    contact = np.load(session / "ground_truth/contact.npy")
    assert contact.shape == (len(mesh.vertices),)
    assert 0.0 <= contact.min() and contact.max() <= 1.0 and (contact > 0.5).sum() >= 20
    assert np.load(session / "ground_truth/keypoints_clean.npy").shape == (14, 21, 2)
    kp = json.loads((session / "grasp/keypoints/000000_keypoints.json").read_text())
    assert kp["version"] == 1.3 and isinstance(kp["people"], list)


def test_truth_joints_through_truth_cameras_match_clean_keypoints(session):
    manifest, truth, _ = _load(session)
    K = np.array(manifest["color_camera"]["K"])
    clean = np.load(session / "ground_truth/keypoints_clean.npy")
    joints_w = np.array(truth["joints_w"])
    for k, T_w_c in enumerate(truth["T_w_c"]):
        uv = project(K, transform_points(inv_T(np.array(T_w_c)), joints_w))
        assert np.abs(uv - clean[truth["steady_from"] + k]).max() < 0.01


def test_object_at_truth_pose_matches_stage1_and_scan_depth(session):
    manifest, truth, mesh = _load(session)
    K, w, h = np.array(manifest["color_camera"]["K"]), 640, 480
    obj = (np.asarray(mesh.vertices), np.asarray(mesh.faces))
    expected = render([obj], [np.array(truth["T_w_o_stage1"])], K, w, h).depth_m
    err, share = _median_depth_error_mm(_depth_m(session / "stage1/depth.png"), expected)
    assert err < 3.0 and share > 0.7, (err, share)

    T_color_turntable = np.array(manifest["turntable"]["T_color_turntable"])
    view = manifest["scan"]["views"][2]
    T_c_o = T_color_turntable @ rot_z(np.radians(view["angle_deg"])) @ np.array(
        truth["T_turntable_o_scan"])
    expected = render([obj], [T_c_o], K, w, h).depth_m
    err, share = _median_depth_error_mm(_depth_m(session / view["depth"]), expected)
    assert err < 3.0 and share > 0.7, (err, share)


def test_hand_and_object_at_truth_poses_match_video_depth(session):
    """T_adj, T_w_p, the angles and T_w_c[i] together explain steady frames' depth."""
    manifest, truth, mesh = _load(session)
    K = np.array(manifest["color_camera"]["K"])
    hm = HandModel("right")
    hand = hm.mesh(np.array(truth["joint_angles_rad"]), np.array(truth["T_w_p"]),
                   truth["hand_scale"])
    T_w_o = np.array(truth["T_adj"]) @ np.array(truth["T_w_o_stage1"])
    meshes = [(np.asarray(mesh.vertices), np.asarray(mesh.faces)), (hand.vertices, hand.faces)]
    for k in (0, len(truth["T_w_c"]) - 1):
        T_c_w = inv_T(np.array(truth["T_w_c"][k]))
        expected = render(meshes, [T_c_w @ T_w_o, T_c_w], K, 640, 480).depth_m
        path = session / manifest["grasp"]["depth"].format(index=truth["steady_from"] + k)
        err, share = _median_depth_error_mm(_depth_m(path), expected)
        assert err < 3.0 and share > 0.7, (k, err, share)


def test_hot_thermal_pixels_fall_on_contacted_vertices(session):
    manifest, truth, mesh = _load(session)
    contact = np.load(session / "ground_truth/contact.npy").astype(float)
    th = manifest["thermal_camera"]
    K_th = np.array(th["K"])
    T_thermal_turntable = inv_T(np.array(th["T_color_thermal"])) @ np.array(
        manifest["turntable"]["T_color_turntable"])
    faces = np.asarray(mesh.faces)
    hot_total, on_contact = 0, 0
    for view in manifest["scan"]["views"]:
        kelvin = cv2.imread(str(session / view["thermal"]), cv2.IMREAD_UNCHANGED) * 0.01
        T = (T_thermal_turntable @ rot_z(np.radians(view["angle_deg"]))
             @ np.array(truth["T_turntable_o_scan"]))
        hits = cast([(np.asarray(mesh.vertices), faces)], [T], K_th, th["width"], th["height"])
        projected = hits.interpolate(0, faces, contact)
        near = cv2.dilate(projected.astype(np.float32), np.ones((3, 3), np.uint8))  # optics blur
        hot = kelvin > 295.0 + 1.0
        hot_total += hot.sum()
        on_contact += (near[hot] > 0.5).sum()
    assert hot_total >= 10
    assert on_contact / hot_total >= 0.9, (on_contact, hot_total)


def test_grasp_touches_without_deep_penetration(session):
    _, truth, mesh = _load(session)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32))

    def sdf(points):
        return scene.compute_signed_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()

    hm = HandModel("right")
    angles, T_o_p, scale = (np.array(truth["joint_angles_rad"]), np.array(truth["T_o_p"]),
                            truth["hand_scale"])
    hand = hm.mesh(angles, T_o_p, scale)
    tri = hand.vertices[hand.faces]
    samples = np.concatenate([hand.vertices, tri.mean(axis=1)])
    assert sdf(samples).min() >= -0.002
    tips = hm.keypoints(angles, T_o_p, scale)[list(FINGERTIPS)]
    gaps = sdf(tips) - SURFACE_OFFSET_M[list(FINGERTIPS)] * scale
    assert (gaps <= 0.003).sum() >= 3, gaps
    # contacted vertices are where the hand is, and only there
    contact = np.load(session / "ground_truth/contact.npy")
    hand_scene = o3d.t.geometry.RaycastingScene()
    hand_scene.add_triangles(hand.vertices.astype(np.float32), hand.faces.astype(np.uint32))
    d = hand_scene.compute_distance(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)))
    d = d.numpy()
    assert d[contact > 0.5].max() < 0.003
    assert contact[d > 0.006].max() < 0.01


def test_same_seed_same_bytes_other_seed_differs(session, tmp_path):
    again = generate_session(tmp_path / "a", [11, 0], SMALL)
    other = generate_session(tmp_path / "b", [11, 1], SMALL)
    for rel in ("session.json", "ground_truth/truth.json", "grasp/depth/000005.png",
                "grasp/keypoints/000007_keypoints.json", "scan/thermal/001.png"):
        assert (again / rel).read_bytes() == (session / rel).read_bytes(), rel
    assert (other / "ground_truth/truth.json").read_bytes() != (
        session / "ground_truth/truth.json").read_bytes()
    assert (other / "grasp/depth/000005.png").read_bytes() != (
        session / "grasp/depth/000005.png").read_bytes()


@pytest.mark.parametrize("name", ["easy", "realistic", "hard"])
def test_keypoint_noise_matches_preset(name):
    cfg = PRESETS[name]
    rng = np.random.default_rng(5)
    clean = np.stack([np.linspace(60, 580, 21), np.full(21, 240.0)], axis=1)  # 26 px apart
    frames = [detect_keypoints(clean, np.zeros(21, bool), 640, 480, cfg, rng)
              for _ in range(3000)]
    empty = sum(f is None for f in frames) / len(frames)
    kp = np.stack([f for f in frames if f is not None])
    detected = kp[..., 2] > 0
    resid = np.linalg.norm(kp[..., :2] - clean, axis=-1)[detected]
    outlier = resid > 15.0
    inlier_sigma = np.sqrt((resid[~outlier] ** 2).mean() / 2)  # per coordinate
    assert abs(empty - cfg.kp_no_person_rate) < 0.012
    assert abs((~detected).mean() - cfg.kp_missing_rate) < 0.008
    assert abs(inlier_sigma - cfg.kp_sigma_px) < 0.05 * cfg.kp_sigma_px + 0.02
    swapped = cfg.kp_swap_rate * 8 / 21  # a swap moves 8 of 21 points by >= 26 px
    expected = cfg.kp_outlier_rate + (1 - cfg.kp_outlier_rate) * swapped
    assert abs(outlier.mean() - expected) < 0.01, (outlier.mean(), expected)
    if cfg.kp_outlier_rate > 0:
        assert (kp[..., 2][detected][outlier] >= 0.5).mean() > 0.6  # outliers come confident


def test_session_keypoints_follow_the_noise_model(session):
    clean = np.load(session / "ground_truth/keypoints_clean.npy")
    resid = []
    for i in range(len(clean)):
        people = json.loads((session / f"grasp/keypoints/{i:06d}_keypoints.json").read_text())
        for person in people["people"]:
            kp = np.array(person["hand_right_keypoints_2d"]).reshape(21, 3)
            ok = kp[:, 2] > 0
            resid.extend(np.linalg.norm(kp[ok, :2] - clean[i, ok], axis=1))
    resid = np.array(resid)
    inl = resid[resid < 15]
    assert len(inl) > 150
    assert 1.8 < np.sqrt((inl**2).mean() / 2) < 3.2  # realistic: 2.5 px per coordinate


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_procedural_object_is_watertight_metric_and_not_symmetric(name):
    obj = procedural_object(name)
    mesh = trimesh.Trimesh(obj.vertices, obj.faces, process=False)
    assert mesh.is_watertight and mesh.volume > 0
    assert 5000 <= len(mesh.faces) <= 30000
    assert 0.05 < mesh.extents.max() < 0.3
    moments, axes = trimesh.inertia.principal_axis(mesh.moment_inertia)
    # the main axis is the one whose moment stands apart (the axis of a body of revolution)
    main = axes[np.argmax([min(abs(m - o) for o in np.delete(moments, i))
                           for i, m in enumerate(moments)])]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(obj.vertices.astype(np.float32), obj.faces.astype(np.uint32))
    centre = mesh.center_mass
    for angle_deg in (60, 90, 120, 180):
        R = trimesh.transformations.rotation_matrix(np.radians(angle_deg), main, centre)
        moved = transform_points(R, obj.vertices).astype(np.float32)
        d = scene.compute_distance(o3d.core.Tensor(moved)).numpy()
        assert d.max() > 0.004, (angle_deg, d.max())


def test_object_file_is_checked_for_metres(tmp_path, shared_data):
    ycb = load_object(shared_data / "ycb_meshes/YcbMustardBottle/textured_simple_reoriented.obj")
    assert trimesh.Trimesh(ycb.vertices, ycb.faces).is_watertight
    big = tmp_path / "box_mm.stl"
    trimesh.creation.box([80.0, 60.0, 120.0]).export(big)
    with pytest.raises(StageError, match="metres"):
        load_object(big)


def test_barycentric_hits_interpolate_vertex_values():
    box = trimesh.creation.box([0.2, 0.2, 0.2])
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.5]
    K = np.array([[300.0, 0, 80], [0, 300.0, 60], [0, 0, 1]])
    hits = cast([(box.vertices, box.faces)], [T], K, 160, 120)
    cam_pts = transform_points(T, box.vertices)
    z = hits.interpolate(0, box.faces, cam_pts[:, 2])
    hit = hits.mesh_index == 0
    assert hit.sum() > 1000
    np.testing.assert_allclose(z[hit], hits.depth_m[hit], atol=1e-5)


def test_participant_scale_is_stable_and_bounded():
    scales = [participant_scale(p, 0.1) for p in range(1, 40)]
    assert scales == [participant_scale(p, 0.1) for p in range(1, 40)]
    assert 0.9 <= min(scales) and max(scales) <= 1.1 and np.std(scales) > 0.02


@pytest.mark.slow
def test_workers_give_the_same_sessions(tmp_path):
    one = generate(tmp_path / "one", sessions=2, seed=3, frames=10, workers=1)
    two = generate(tmp_path / "two", sessions=2, seed=3, frames=10, workers=2)
    for a, b in zip(one, two, strict=True):
        assert a.name == b.name
        for rel in ("session.json", "ground_truth/truth.json", "grasp/depth/000009.png"):
            assert (a / rel).read_bytes() == (b / rel).read_bytes()


def test_config_for_overrides_frames_and_validates():
    from pydantic import ValidationError

    from graspcap.synth import config_for

    cfg = config_for("hard", 30)
    assert cfg.frames == 30 and cfg.kp_sigma_px == PRESETS["hard"].kp_sigma_px
    with pytest.raises(ValidationError):
        config_for("easy", 2)
    with pytest.raises(ValidationError):
        PRESETS["easy"].model_validate({"no_such_field": 1})
    sigmas = [PRESETS[d].depth_sigma_m for d in ("easy", "realistic", "hard")]
    assert sigmas == sorted(sigmas) and len(set(sigmas)) == 3
