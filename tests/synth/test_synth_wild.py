"""The wild profile: sessions the validator accepts, deterministic per seed, every
randomisation factor checked in its range from what the rig wrote (truth, manifest, images),
and a rig hand that is not the pipeline's model."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy.optimize import least_squares

from graspcap.cli import build_parser
from graspcap.synth import PRESETS, config_for, generate_session
from graspcap.synth.config import (
    CaptureConfig,
    KinectDepthConfig,
    RealDetectorConfig,
    WildHandConfig,
)
from graspcap.synth.objects import ALL_OBJECT_NAMES, EXTENT_RANGE_M, procedural_object
from graspcap.synth.rig import distorted_pixel_rays, project_distorted
from graspcap.synth.sensors import kinect_depth_mm, real_detections
from graspcap.synth.wild_hand import WildHand, WildHandShape
from graspcap.tasks.core.geometry import from_rotvec, inv_T, transform_points
from graspcap.tasks.core.render import cast_rays
from graspcap.tasks.hand.model import SKELETON, HandModel
from graspcap.tasks.session.load_session import validate_session

WILD = PRESETS["wild"].model_copy(update={"frames": 12, "scan_views": (6, 6)})
REALISTIC_DIGEST = "0df45757341c6f2ed7d2da7e91c253ec908ef7af045873b5016a6035f2320803"
PHALANGES = [k for k, (a, _) in enumerate(SKELETON) if a != 0]  # bones not from the wrist


@pytest.fixture(scope="module")
def sessions(tmp_path_factory) -> list[Path]:
    out = tmp_path_factory.mktemp("wild")
    return [generate_session(out, [18, i], WILD) for i in range(2)]


def _load(session: Path):
    manifest = json.loads((session / "session.json").read_text())
    truth = json.loads((session / "ground_truth/truth.json").read_text())
    return manifest, truth


def _hand_size_px(uv: np.ndarray) -> float:
    return float(np.linalg.norm(uv.max(axis=0) - uv.min(axis=0)))


def _p90_depth_error_mm(written: np.ndarray, expected, dx: int, dy: int) -> float:
    """p90 |written - expected| (mm) on the rendered hand and object, ``written`` shifted back
    by (dx, dy) pixels first."""
    h, w = written.shape
    moved = np.zeros_like(written)
    moved[max(-dy, 0): h + min(-dy, 0), max(-dx, 0): w + min(-dx, 0)] = \
        written[max(dy, 0): h + min(dy, 0), max(dx, 0): w + min(dx, 0)]
    fg = expected.mesh_index >= 0
    both = fg & (moved > 0)
    assert both.sum() > 0.6 * fg.sum()
    return float(np.percentile(np.abs(moved - expected.depth_m)[both], 90) * 1000)


def _max_pairwise_turn_deg(T_w_c: list) -> float:
    R = np.array(T_w_c)[:, :3, :3]
    rel = np.einsum("iba,jbc->ijac", R, R)  # R_i^T R_j
    cos = (np.trace(rel, axis1=2, axis2=3) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())


# --- the profile and the CLI --------------------------------------------------------------


def test_existing_presets_keep_their_digest_and_wild_turns_everything_on():
    assert PRESETS["realistic"].digest() == REALISTIC_DIGEST  # synth/2 truth stays byte-identical
    wild = PRESETS["wild"]
    for name in ("wild_hand", "capture", "lens", "object_set", "detector", "kinect_depth"):
        assert getattr(wild, name) is not None, name
        assert getattr(PRESETS["realistic"], name) is None, name
    assert PRESETS["real-detector"].detector is not None
    assert PRESETS["real-detector"].wild_hand is None
    assert config_for("wild", 12).frames == 12 and config_for("wild", 12).lens is not None


def test_cli_profile_with_difficulty_alias_and_checked_choices(capsys):
    parser = build_parser()
    assert parser.parse_args(["synth", "out", "--profile", "wild"]).profile == "wild"
    assert parser.parse_args(["synth", "out", "--difficulty", "hard"]).profile == "hard"
    assert parser.parse_args(["synth", "out"]).profile == "realistic"
    with pytest.raises(SystemExit) as exc:
        parser.parse_args(["synth", "out", "--profile", "feral"])
    assert exc.value.code == 2
    assert "invalid choice: 'feral'" in capsys.readouterr().err


# --- sessions: contract, determinism, ranges from the written truth ------------------------


def test_wild_sessions_validate_and_write_the_randomisation(sessions):
    for session in sessions:
        assert validate_session(session) == [], session
        manifest, truth = _load(session)
        assert truth["difficulty"] == "wild"
        rnd = truth["randomisation"]
        assert rnd["hand_model"] == "wild_hand/1"
        assert manifest["color_camera"]["dist"] == rnd["dist"] and any(rnd["dist"])
        assert (manifest["color_camera"]["width"], manifest["color_camera"]["height"]) == (
            rnd["camera"]["width"], rnd["camera"]["height"])
        assert len(truth["joint_angles_rad"]) == 20 and len(truth["joints_w"]) == 21


def test_same_seed_same_bytes(sessions, tmp_path):
    again = generate_session(tmp_path, [18, 1], WILD)
    files = sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(sessions[1]) for p in sessions[1].rglob("*")
                           if p.is_file())
    for rel in files:
        assert (again / rel).read_bytes() == (sessions[1] / rel).read_bytes(), rel


def test_real_detector_profile_alone_keeps_the_realistic_rig(tmp_path):
    cfg = PRESETS["real-detector"].model_copy(update={"frames": 8, "scan_views": (6, 6)})
    session = generate_session(tmp_path, [18, 0], cfg)
    assert validate_session(session) == []
    manifest, truth = _load(session)
    assert (manifest["color_camera"]["width"], manifest["color_camera"]["height"]) == (640, 480)
    assert manifest["color_camera"]["dist"] == [0.0] * 5
    rnd = truth["randomisation"]
    assert rnd["hand_model"] == "hand_model/1" and rnd["hand_shape"] is None
    assert len(rnd["detector"]["events"]) == 8 and truth["difficulty"] == "real-detector"


def test_clean_keypoints_are_the_truth_joints_through_the_distorted_lens(sessions):
    for session in sessions:
        manifest, truth = _load(session)
        camera = manifest["color_camera"]
        K, dist = np.array(camera["K"]), np.array(camera["dist"])
        clean = np.load(session / "ground_truth/keypoints_clean.npy")
        joints_w = np.array(truth["joints_w"])
        for k, T_w_c in enumerate(truth["T_w_c"]):
            P = transform_points(inv_T(np.array(T_w_c)), joints_w)
            uv = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)[0][:, 0]
            assert np.abs(uv - clean[truth["steady_from"] + k]).max() < 1e-6
            # the pinhole would be off by pixels: the distortion is really in the images
        pinhole = (P @ K.T)[:, :2] / P[:, 2:]
        assert np.abs(pinhole - uv).max() > 0.05


def test_hand_and_object_at_truth_poses_explain_the_video_depth(sessions):
    """The written truth (rig hand shape and pose, object pose, cameras, lens, depth shift)
    reproduces the written depth images."""
    for session in sessions:
        manifest, truth = _load(session)
        cam, rnd = manifest["color_camera"], truth["randomisation"]
        K, dist, w, h = np.array(cam["K"]), np.array(cam["dist"]), cam["width"], cam["height"]
        hand = WildHand(WildHandShape.from_json(rnd["hand_shape"])).mesh(
            np.array(truth["joint_angles_rad"]), np.array(truth["T_w_p"]), truth["hand_scale"])
        mesh = trimesh.load(session / "object.ply", process=False)
        T_w_o = np.array(truth["T_adj"]) @ np.array(truth["T_w_o_stage1"])
        rays = distorted_pixel_rays(K, dist, w, h).astype(np.float32)
        dx, dy = rnd["depth_shift_px"]
        k = len(truth["T_w_c"]) - 1
        T_c_w = inv_T(np.array(truth["T_w_c"][k]))
        expected = cast_rays([(np.asarray(mesh.vertices), np.asarray(mesh.faces)),
                              (hand.vertices, hand.faces)], [T_c_w @ T_w_o, T_c_w], rays)
        path = session / manifest["grasp"]["depth"].format(index=truth["steady_from"] + k)
        written = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(float) / 1000
        assert _p90_depth_error_mm(written, expected, dx, dy) < 3.0, session
        # the depth really is misaligned: unshifted, it fits worse
        assert _p90_depth_error_mm(written, expected, dx, dy) < _p90_depth_error_mm(
            written, expected, 0, 0), session


def test_contact_truth_lies_on_the_rig_hand(sessions):
    """Contacted vertices are where the rig's own hand touches the object, and only there."""
    for session in sessions:
        _, truth = _load(session)
        hand = WildHand(WildHandShape.from_json(truth["randomisation"]["hand_shape"])).mesh(
            np.array(truth["joint_angles_rad"]), np.array(truth["T_o_p"]), truth["hand_scale"])
        mesh = trimesh.load(session / "object.ply", process=False)
        contact = np.load(session / "ground_truth/contact.npy")
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(hand.vertices.astype(np.float32), hand.faces.astype(np.uint32))
        d = scene.compute_distance(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)))
        d = d.numpy()
        assert (contact > 0.5).sum() >= 10, session
        assert d[contact > 0.5].max() < 0.003 and contact[d > 0.006].max() < 0.01, session


def test_hand_ranges_from_the_written_truth(sessions):
    template = WildHandShape.template().bone_lengths_m()
    ratios = []
    for session in sessions:
        _, truth = _load(session)
        scale = truth["hand_scale"]
        assert 0.8 <= scale <= 1.2
        joints = np.array(truth["joints_w"])
        lengths = np.array([np.linalg.norm(joints[b] - joints[a]) for a, b in SKELETON])
        r = lengths[PHALANGES] / (scale * template[PHALANGES])
        assert np.all((r > 0.85 - 1e-9) & (r < 1.15 + 1e-9)), r
        assert r.max() - r.min() > 0.1  # bones vary independently within a hand
        ratios.append(r)
        shape = truth["randomisation"]["hand_shape"]
        cfg = WildHandConfig()
        assert cfg.thumb_opposition_deg[0] <= np.degrees(shape["opposition_rad"]) <= \
            cfg.thumb_opposition_deg[1]
        assert cfg.abduction_deg[0] <= np.degrees(shape["abduction_rad"]) <= cfg.abduction_deg[1]
    assert np.std(np.concatenate(ratios)) > 0.05


def test_geometry_object_and_detector_ranges_from_the_written_files(sessions):
    cap = CaptureConfig()
    for session in sessions:
        manifest, truth = _load(session)
        cam = manifest["color_camera"]
        sizes = {(w, h): f for w, h, f in cap.cameras}
        assert (cam["width"], cam["height"]) in sizes
        f = sizes[(cam["width"], cam["height"])]
        assert abs(cam["K"][0][0] / f - 1) <= cap.focal_jitter + 1e-9
        T = np.array(manifest["turntable"]["T_color_turntable"])
        assert 0.6 - 1e-6 <= np.linalg.norm(T[:3, 3]) <= 1.0 + 1e-6
        palm_z = np.array(truth["joints_w"])[[0, 1, 5, 9, 13, 17]].mean(axis=0)[2]
        assert 0.4 - 0.02 <= palm_z <= 1.2 + 0.02
        turn = _max_pairwise_turn_deg(truth["T_w_c"])
        assert 18.0 <= turn <= 190.0
        assert abs(turn / truth["randomisation"]["motion_turn_deg"] - 1) < 0.1
        shift = np.max(np.abs(np.array(truth["T_w_c"])[:, :3, 3] - 0), axis=0)
        assert np.all(shift < 0.1 + 0.3 + 0.25)  # translation + lift + the turn's lever
        mesh = trimesh.load(session / "object.ply", process=False)
        assert 0.05 - 1e-3 <= mesh.extents.max() <= 0.30 + 1e-3
        assert abs(mesh.extents.max() - truth["randomisation"]["object_extent_m"]) < 1e-6
        assert 1 <= np.hypot(*truth["randomisation"]["depth_shift_px"]) <= 3 * np.sqrt(2)
        # keypoint error of the frames the detector got right: 5-10 % of the hand (occluded
        # joints heavier), measured on the written detections against the clean projections
        clean = np.load(session / "ground_truth/keypoints_clean.npy")
        events = truth["randomisation"]["detector"]["events"]
        shares = []
        for i, event in enumerate(events):
            doc = json.loads((session / manifest["grasp"]["keypoints"].format(index=i))
                             .read_text())
            assert (event == "missing") == (doc["people"] == [])
            if event != "ok" or truth["randomisation"]["detector"]["swapped"][i]:
                continue
            kp = np.array(doc["people"][0]["hand_right_keypoints_2d"]).reshape(21, 3)
            seen = kp[:, 2] > 0
            err = np.linalg.norm(kp[seen, :2] - clean[i, seen], axis=1)
            shares.append(np.median(err) / _hand_size_px(clean[i]))
        assert 0.02 < np.median(shares) < 0.2, shares


def test_rig_hand_is_not_the_pipeline_model(sessions):
    """The 20-DoF model (pose, angles, scale free) cannot reproduce the rig's hand; it fits
    its own keypoints exactly."""
    hm = HandModel("right")

    def fit(target: np.ndarray, x0: np.ndarray) -> float:
        def resid(x):
            T = from_rotvec(x[:3], x[3:6])
            return (hm.keypoints(hm.clip(x[7:]), T, x[6]) - target).ravel()
        sol = least_squares(resid, x0, x_scale="jac", max_nfev=400)
        return float(np.sqrt((sol.fun.reshape(21, 3) ** 2).sum(1).mean()))

    _, truth = _load(sessions[0])
    T = np.array(truth["T_w_p"])
    rotvec = cv2.Rodrigues(T[:3, :3])[0].ravel()
    x0 = np.concatenate([rotvec, T[:3, 3], [truth["hand_scale"]], truth["joint_angles_rad"]])
    rig_joints = np.array(truth["joints_w"])
    own = hm.keypoints(np.array(truth["joint_angles_rad"]), T, truth["hand_scale"])
    x_off = x0 + np.concatenate([[0.02, -0.02, 0.01, 0.003, -0.002, 0.002, 0.03],
                                 np.full(20, 0.05)])
    assert fit(own, x_off) < 1e-4
    assert fit(rig_joints, x0) > 0.002  # metres: a misfit no pose or scale removes

    # structure: the knuckles of the rig hand move in the palm as the fingers close
    wild = WildHand(WildHandShape.sample(WildHandConfig(), np.random.default_rng(4)))
    closed = np.array([0.5, 0.3, 0.3, 0.3] + [0.0, 1.2, 1.3, 0.9] * 4)
    moved = np.linalg.norm(wild.keypoints(closed)[17] - wild.keypoints(np.zeros(20))[17])
    assert moved > 0.002
    fixed = np.linalg.norm(hm.keypoints(closed)[17] - hm.keypoints(np.zeros(20))[17])
    assert fixed < 1e-12
    assert len(np.unique(wild.mesh(closed).part)) == 17


# --- the sensor models on their own ------------------------------------------------------


def test_real_detector_errors_failures_swaps_and_missing_runs():
    n = 600
    rng = np.random.default_rng(3)
    t = np.linspace(0, 1, n)[:, None, None]
    base = np.stack([np.linspace(0, 100, 21), np.r_[0, np.linspace(0, 60, 20)]], axis=1)
    clean = 300 + base[None] + 40 * np.sin(2 * np.pi * t)  # a 117 px hand drifting about
    occluded = np.zeros((n, 21), bool)
    occluded[:, 15:] = True
    cfg = RealDetectorConfig()
    kps, events, swapped, share = real_detections(clean, occluded, 1280, 720, cfg, rng)
    assert cfg.error_share[0] <= share <= cfg.error_share[1]
    events = np.array(events)
    size = _hand_size_px(clean[0])
    good = [i for i in range(n) if events[i] == "ok" and not swapped[i]]
    err = np.stack([np.linalg.norm(kps[i][:, :2] - clean[i], axis=1) for i in good])
    seen = np.stack([kps[i][:, 2] > 0 for i in good])
    visible = err[:, :15][seen[:, :15]].mean() / size
    assert abs(visible / share - 1) < 0.25  # the per-joint error is the drawn share
    assert err[:, 15:][seen[:, 15:]].mean() > 1.5 * err[:, :15][seen[:, :15]].mean()
    # temporally correlated: an error repeats much of itself in the next frame
    e = np.stack([kps[i][:, :2] - clean[i] for i in good])
    consecutive = [k for k in range(len(good) - 1) if good[k + 1] == good[k] + 1]
    both = seen[consecutive] & seen[[k + 1 for k in consecutive]]
    a, b = e[consecutive][both].ravel(), e[[k + 1 for k in consecutive]][both].ravel()
    assert np.corrcoef(a, b)[0, 1] > 0.5
    # whole-frame failures of every kind, far from the hand, and confident
    for kind in ("wrong_place", "mirrored", "other_hand"):
        assert (events == kind).sum() >= 5, kind
    failed = [i for i in range(n) if events[i] in ("wrong_place", "other_hand")]
    far = [np.median(np.linalg.norm(kps[i][:, :2] - clean[i], axis=1)) > 0.3 * size
           for i in failed]
    assert np.mean(far) > 0.8
    conf_bad = np.mean([kps[i][kps[i][:, 2] > 0, 2].mean() for i in failed])
    conf_good = np.mean([kps[i][kps[i][:, 2] > 0, 2].mean() for i in good])
    assert abs(conf_bad - conf_good) < 0.15  # confidences say little about the error
    # swaps and runs of missing frames
    assert 0.03 < swapped.mean() < 0.15
    missing = (events == "missing").astype(int)
    start, end = np.flatnonzero(np.diff(np.r_[0, missing, 0])).reshape(-1, 2).T
    inner = end < n  # a run cut off by the end of the video may be shorter
    assert len(start) >= 5 and (end - start)[inner].min() >= 2
    assert all(kps[i] is None for i in np.flatnonzero(missing))


def test_kinect_depth_noise_flying_pixels_and_shift():
    h, w = 120, 160
    depth = np.full((h, w), 1.0, np.float32)
    depth[:, 80:] = 0.7  # a step: near right half, far left half
    cos = np.ones((h, w), np.float32)
    kc = KinectDepthConfig(dropout_blobs=0)
    rng = np.random.default_rng(0)
    out = kinect_depth_mm(depth, cos, kc, 0.0, (2, 1), rng).astype(float) / 1000
    assert np.all(out[0, :] == 0) and np.all(out[:, :2] == 0)  # shifted by (dx, dy) = (2, 1)
    far = out[1:, 2:80]
    assert abs(np.std(far[:, :70]) - kc.sigma_1m_m) < 0.0006  # ~1.5 mm at 1 m (mm rounding)
    near = out[1:, 90:]
    assert np.std(near) < np.std(far[:, :70])  # noise grows with distance
    edge = out[1:, 80:84]  # the step's columns, shifted by 2
    between = (edge > 0.72) & (edge < 0.98)
    assert between.mean() > 0.1  # flying pixels between the two sides
    drop = kinect_depth_mm(depth, cos, KinectDepthConfig(), 0.02, (1, 0), rng)
    assert 0.02 < (drop[:, 1:] == 0).mean() < 0.1


def test_new_objects_are_watertight_and_their_sizes_fit_the_range():
    for name in ALL_OBJECT_NAMES:
        lo, hi = EXTENT_RANGE_M[name]
        assert 0.05 <= lo < hi <= 0.30, name
    for name in ALL_OBJECT_NAMES[5:]:
        obj = procedural_object(name)
        mesh = trimesh.Trimesh(obj.vertices, obj.faces, process=False)
        assert mesh.is_watertight and mesh.volume > 0, name


def test_distorted_projection_matches_opencv():
    K = np.array([[540.0, 0, 480], [0, 540, 270], [0, 0, 1]])
    dist = np.array([-0.18, 0.07, 0.001, -0.0012, 0.01])
    P = np.random.default_rng(1).uniform([-0.4, -0.3, 0.5], [0.4, 0.3, 1.2], (40, 3))
    ref = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)[0][:, 0]
    np.testing.assert_allclose(project_distorted(K, dist, P), ref, atol=1e-9)


# --- many sessions (slow) -----------------------------------------------------------------


@pytest.mark.slow
def test_ranges_over_many_wild_sessions(tmp_path):
    """Ten 40-frame sessions (a 20-frame one has a run of missing frames with chance ~0.4):
    the three cameras, both rotation directions, small and large objects,
    detector failures, swaps and missing runs all occur in what the rig wrote."""
    found = {"cameras": set(), "turns": [], "extents": [], "events": set(), "swaps": 0,
             "both_ways": 0}
    for i in range(10):
        session = generate_session(tmp_path, [7, i], WILD.model_copy(update={"frames": 40}))
        assert validate_session(session) == [], session
        manifest, truth = _load(session)
        rnd = truth["randomisation"]
        found["cameras"].add((manifest["color_camera"]["width"],
                              manifest["color_camera"]["height"]))
        turn = _max_pairwise_turn_deg(truth["T_w_c"])
        found["turns"].append(turn)
        from_start = float(np.max(np.degrees(np.arccos(np.clip(
            (np.trace(np.array(truth["T_w_c"])[:, :3, :3], axis1=1, axis2=2) - 1) / 2,
            -1, 1)))))
        found["both_ways"] += turn > from_start + 5
        found["extents"].append(rnd["object_extent_m"])
        found["events"] |= set(rnd["detector"]["events"])
        found["swaps"] += sum(rnd["detector"]["swapped"])
    assert found["cameras"] == {(640, 480), (960, 540), (1280, 720)}
    assert min(found["turns"]) >= 18 and max(found["turns"]) <= 190
    assert max(found["turns"]) - min(found["turns"]) > 60
    assert found["both_ways"] >= 2
    assert min(found["extents"]) < 0.12 and max(found["extents"]) > 0.15
    assert {"missing", "wrong_place", "mirrored", "other_hand"} & found["events"]
    assert "missing" in found["events"] and found["swaps"] > 0
