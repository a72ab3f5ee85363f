"""One synthetic session end to end: place, grasp, move, render, write to the contract."""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from graspcap.schemas.session import SessionManifest
from graspcap.synth.config import (
    RANDOMISATION_FIELDS,
    STAGE_VERSION,
    ObjectSetConfig,
    SynthConfig,
)
from graspcap.synth.grasp import APPROACH_M, Grasp, hand_contact, plan_grasp
from graspcap.synth.motion import steady_motion, wild_motion
from graspcap.synth.objects import (
    EXTENT_RANGE_M,
    OBJECT_NAMES,
    ObjectMesh,
    load_object,
    procedural_object,
    scaled_object,
    write_object,
)
from graspcap.synth.raycast import StaticCamera
from graspcap.synth.rig import (
    color_K,
    interpolate_pose,
    platter_mesh,
    project_distorted,
    rest_on_platter,
    sample_lens,
    smoothstep,
    table_mesh,
    thermal_extrinsics,
    thermal_K,
    turntable_pose,
)
from graspcap.synth.sensors import (
    ALBEDO,
    depth_shift_px,
    detect_keypoints,
    kinect_depth_mm,
    noisy_depth_mm,
    openpose_json,
    real_detections,
    shaded_rgb,
    thermal_centikelvin,
)
from graspcap.synth.wild_hand import MODEL_VERSION as WILD_HAND_VERSION
from graspcap.synth.wild_hand import WildHand, WildHandShape
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import backproject, inv_T, make_T, project, transform_points
from graspcap.tasks.core.render import RayHits
from graspcap.tasks.hand.model import RIGID_PALM_POINTS, HandModel, HandSide

COLOR_PATTERN = "grasp/color/{index:06d}.jpg"
DEPTH_PATTERN = "grasp/depth/{index:06d}.png"
KEYPOINTS_PATTERN = "grasp/keypoints/{index:06d}_keypoints.json"
_APPROACH_M = APPROACH_M  # the open hand starts this far back along its palmar normal
_LIFT_M = 0.05  # extra height of the object's path while it is picked up


def participant_scale(participant: int, spread: float) -> float:
    """A participant's stable hand scale in ``1 +- spread``."""
    return float(1.0 + spread * (2.0 * np.random.default_rng([7919, participant]).uniform() - 1))


def _seed_label(seed: Sequence[int]) -> str:
    head, *rest = seed
    return f"s{head}" + "".join(f"-{r:03d}" for r in rest)


def _write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def _png(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    assert ok, path
    _write(path, buf.tobytes())


def _jpg(path: Path, rgb: np.ndarray, quality: int) -> None:
    ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok, path
    _write(path, buf.tobytes())


def _matrix(T: np.ndarray) -> list[list[float]]:
    return [[float(x) for x in row] for row in np.asarray(T)]


class _Scene:
    """The colour and thermal cameras over the static platter and table."""

    def __init__(self, cfg: SynthConfig, T_color_turntable: np.ndarray,
                 T_color_thermal: np.ndarray, dist: np.ndarray | None = None):
        static = [platter_mesh(cfg), table_mesh(cfg)]
        self.color = StaticCamera(color_K(cfg), cfg.width, cfg.height, static,
                                  [T_color_turntable] * 2, dist)
        self.T_thermal_color = inv_T(T_color_thermal)
        self.thermal = StaticCamera(thermal_K(cfg), cfg.thermal_width, cfg.thermal_height, static,
                                    [self.T_thermal_color @ T_color_turntable] * 2)

    def render(self, parts: list[tuple[tuple[np.ndarray, np.ndarray], np.ndarray]]) -> RayHits:
        """Colour-camera hits of ``parts`` (mesh, T_color_mesh), then platter, then table."""
        return self.color.render([m for m, _ in parts], [T for _, T in parts])

    def render_thermal(
        self, parts: list[tuple[tuple[np.ndarray, np.ndarray], np.ndarray]]
    ) -> RayHits:
        """Thermal-camera hits of ``parts`` given in the colour frame."""
        return self.thermal.render([m for m, _ in parts],
                                   [self.T_thermal_color @ T for _, T in parts])


def _above_table(points_w: np.ndarray, T_color_turntable: np.ndarray,
                 margin_m: float = 0.008) -> bool:
    return bool(transform_points(inv_T(T_color_turntable), points_w)[:, 2].min() > margin_m)


def _in_image(uv: np.ndarray, cfg: SynthConfig, margin_px: float) -> bool:
    return bool(np.all((uv >= margin_px) & (uv <= [cfg.width - margin_px, cfg.height - margin_px])))


def _steady_pose(obj: ObjectMesh, hand_o: np.ndarray, joints_o: np.ndarray, T_w_o1: np.ndarray,
                 T_color_turntable: np.ndarray, cfg: SynthConfig, rng: np.random.Generator,
                 proj: Projection):
    """Object pose at the first steady frame: lifted towards the camera, a bounded turn."""
    K = color_K(cfg)
    centre_o = joints_o[list(RIGID_PALM_POINTS)].mean(axis=0)
    sample = np.concatenate([obj.vertices[::7], hand_o[::5]])
    # with cfg.capture one depth is drawn and kept (coming 5 cm nearer every 10 tries), else
    # the accepted depths would crowd at the near end of a wide range
    target = None if cfg.capture is None else rng.uniform(*cfg.hand_distance_m)
    for k in range(60):
        axis = rng.normal(size=3)
        angle = np.radians(rng.uniform(0.3, 1.0) * cfg.adjust_rotation_deg)
        R = make_T(cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0], [0, 0, 0])[:3, :3]
        R_w_o = R @ T_w_o1[:3, :3]
        if target is None:
            uv = rng.uniform([0.35 * cfg.width, 0.3 * cfg.height],
                             [0.65 * cfg.width, 0.6 * cfg.height])
            z = rng.uniform(*cfg.hand_distance_m)
        else:
            uv = rng.uniform([0.3 * cfg.width, 0.15 * cfg.height],
                             [0.7 * cfg.width, 0.6 * cfg.height])
            z = max(cfg.hand_distance_m[0], target - 0.05 * (k // 10))
        c_w = backproject(K, uv[None], np.array([z]))[0]
        T = make_T(R_w_o, c_w - R_w_o @ centre_o)
        if _in_image(proj(transform_points(T, joints_o)), cfg, 25) and _above_table(
                transform_points(T, sample), T_color_turntable, 0.02):
            return T
    raise StageError("synth", f"object {obj.name}: no steady pose keeps the hand in view")


WILD_ATTEMPTS = 4
"""Draws of object, hand and scene a session of ``object_set`` gets before it fails: a
hand that cannot grasp the object drawn (a remote lying flat) draws both again."""


def generate_session(out: Path, session_seed: int | Sequence[int], config: SynthConfig,
                     object_mesh: Path | None = None) -> Path:
    """Write one synthetic session (and its ground truth) under ``out``; returns its directory.

    Deterministic: the same ``session_seed`` and ``config`` give byte-identical files. With
    ``config.object_set`` (and no ``object_mesh``) a draw whose grasp or motion cannot be
    made is replaced by the next (``WILD_ATTEMPTS`` in all, each its own seeded stream).
    """
    seed = [int(session_seed)] if np.isscalar(session_seed) else [int(s) for s in session_seed]
    attempts = WILD_ATTEMPTS if config.object_set is not None and object_mesh is None else 1
    for attempt in range(attempts):
        rng = np.random.default_rng(seed if attempt == 0 else [*seed, 7700 + attempt])
        try:
            return _generate_session(Path(out), seed, rng, config, object_mesh)
        except StageError:
            if attempt == attempts - 1:
                raise
    raise AssertionError("unreachable")


def _generate_session(out: Path, seed: list[int], rng: np.random.Generator, config: SynthConfig,
                      object_mesh: Path | None) -> Path:
    """One draw of a session from ``rng``: the object, participant and intent, then the rest;
    a draw that fails leaves nothing behind."""
    cfg = config
    if object_mesh is not None:
        obj = load_object(object_mesh)
    elif cfg.object_set is None:
        obj = procedural_object(str(rng.choice(OBJECT_NAMES)), cfg.object_faces)
    else:
        obj = _wild_object(cfg.object_set, cfg.object_faces, rng)
    pid = int(rng.integers(1, cfg.participants + 1))
    participant, scale = f"p{pid:02d}", participant_scale(pid, cfg.hand_scale_spread)
    intent = str(rng.choice(["use", "handoff"]))
    session_id = f"synth-{_seed_label(seed)}-{obj.name}"
    root = Path(out) / session_id
    try:
        return _write_session(root, session_id, seed, rng, config, obj, participant, scale,
                              intent)
    except StageError:
        shutil.rmtree(root, ignore_errors=True)  # no half-written session left behind
        raise


def _write_session(root: Path, session_id: str, seed: list[int], rng: np.random.Generator,
                   config: SynthConfig, obj: ObjectMesh, participant: str,
                   scale: float, intent: str) -> Path:
    """Hand, cameras, stage 1, grasp, video, scan, manifest and truth of one session."""
    cfg = config
    hm: HandModel | WildHand = HandModel(HandSide.RIGHT)
    shape = None
    if cfg.wild_hand is not None:
        scale = float(rng.uniform(*cfg.wild_hand.size))
        shape = WildHandShape.sample(cfg.wild_hand, rng)
        hm = WildHand(shape)
    cfg = _session_camera(cfg, rng)  # the drawn camera replaces the fixed fields

    K, K_th = color_K(cfg), thermal_K(cfg)
    dist = None if cfg.lens is None else sample_lens(cfg.lens, K, cfg.width, cfg.height, rng)
    proj: Projection = ((lambda P: project(K, P)) if dist is None
                        else (lambda P: project_distorted(K, dist, P)))
    T_color_thermal = thermal_extrinsics(cfg, rng)
    T_color_turntable = turntable_pose(cfg, rng)
    if cfg.capture is not None:  # the hand is held in front of the turntable, not behind it
        lo, hi = cfg.capture.hand_distance_m
        far = min(hi, float(np.linalg.norm(T_color_turntable[:3, 3])) + 0.1)
        cfg = cfg.model_copy(update={"hand_distance_m": (lo, max(lo + 0.05, far))})
    depth_mm = _DepthSensor(cfg, rng)
    scene = _Scene(cfg, T_color_turntable, T_color_thermal, dist)
    obj_mesh = (obj.vertices, obj.faces)

    # stage1 (register_object's input): the object alone on the platter.
    T_turntable_o1 = rest_on_platter(obj, cfg, rng)
    T_w_o1 = T_color_turntable @ T_turntable_o1
    hits = scene.render([(obj_mesh, T_w_o1)])
    _png(root / "stage1/depth.png", depth_mm(hits))
    albedo = [ALBEDO["object"], ALBEDO["platter"], ALBEDO["table"]]
    _png(root / "stage1/color.png", shaded_rgb(hits, albedo, rng)[..., ::-1])

    # The grasp, planned on the object as it rests on the platter.
    grasp = plan_grasp(obj, hm, scale, T_turntable_o1[:3, :3].T @ [0.0, 0.0, 1.0], cfg, rng)
    hand_p = hm.mesh(grasp.angles_rad, np.eye(4), scale)
    hand_o = transform_points(grasp.T_o_p, hand_p.vertices)
    joints_o = hm.keypoints(grasp.angles_rad, grasp.T_o_p, scale)
    T_w_o_steady = _steady_pose(obj, hand_o, joints_o, T_w_o1, T_color_turntable, cfg, rng,
                                proj)
    T_adj = T_w_o_steady @ inv_T(T_w_o1)
    T_w_p = T_w_o_steady @ grasp.T_o_p
    joints_w = hm.keypoints(grasp.angles_rad, T_w_p, scale)

    count = cfg.frames
    steady = int(np.clip(round(count * rng.uniform(*cfg.adjust_fraction)), 2, count - 2))
    motions, total_turn_deg = _video_motion(obj, hand_o, joints_o, T_w_o_steady,
                                            T_color_turntable, steady, cfg, rng, proj)

    # The grasp video.
    clean = np.zeros((count, 21, 2))
    occluded = np.zeros((count, 21), bool)
    albedo = [ALBEDO["object"], ALBEDO["hand"], ALBEDO["platter"], ALBEDO["table"]]
    for i in range(count):
        if i >= steady:
            M = motions[i - steady]
            T_w_o, T_w_p_i, angles = M @ T_w_o_steady, M @ T_w_p, grasp.angles_rad
            hand_v = transform_points(T_w_p_i, hand_p.vertices)
        else:
            T_w_o, T_w_p_i, angles = _adjustment(grasp, T_w_o1, T_w_o_steady, T_color_turntable,
                                                 i / steady)
            hand_v = hm.mesh(angles, T_w_p_i, scale).vertices
        joints = hm.keypoints(angles, T_w_p_i, scale)
        clean[i] = proj(joints)
        hits = scene.render([(obj_mesh, T_w_o), ((hand_v, hand_p.faces), np.eye(4))])
        _png(root / DEPTH_PATTERN.format(index=i), depth_mm(hits))
        _jpg(root / COLOR_PATTERN.format(index=i), shaded_rgb(hits, albedo, rng), cfg.jpeg_quality)
        occluded[i] = _occluded(hits, clean[i], joints[:, 2])
        if cfg.detector is not None:  # a real detector also suffers from the hand's own cover
            occluded[i] |= _self_occluded(hits, clean[i], joints[:, 2])
        if cfg.detector is None:
            kp = detect_keypoints(clean[i], occluded[i], cfg.width, cfg.height, cfg, rng)
            _write(root / KEYPOINTS_PATTERN.format(index=i),
                   json.dumps(openpose_json(kp)).encode())
    detector = None
    if cfg.detector is not None:  # errors correlated over frames: the whole video at once
        kps, events, swapped, share = real_detections(clean, occluded, cfg.width, cfg.height,
                                                      cfg.detector, rng)
        for i, kp in enumerate(kps):
            _write(root / KEYPOINTS_PATTERN.format(index=i),
                   json.dumps(openpose_json(kp)).encode())
        detector = {"error_share": share, "events": events,
                    "swapped": [bool(x) for x in swapped],
                    "hidden_joint_share": float(occluded.mean())}

    # The scan: the object back on the platter in a new pose, rotated through 360 deg.
    contact = hand_contact(obj, hand_o, hand_p.faces, hand_p.part)
    T_turntable_o_scan = rest_on_platter(obj, cfg, rng, avoid=contact)
    n_views = int(rng.integers(cfg.scan_views[0], cfg.scan_views[1] + 1))
    views = []
    for k in range(n_views):
        angle_deg = 360.0 * k / n_views
        T_c_o = T_color_turntable @ _rot_z_deg(angle_deg) @ T_turntable_o_scan
        hits = scene.render([(obj_mesh, T_c_o)])
        depth_rel, thermal_rel = f"scan/depth/{k:03d}.png", f"scan/thermal/{k:03d}.png"
        _png(root / depth_rel, depth_mm(hits))
        th = scene.render_thermal([(obj_mesh, T_c_o)])
        _png(root / thermal_rel, thermal_centikelvin(th, obj.faces, contact, cfg, rng))
        views.append({"thermal": thermal_rel, "depth": depth_rel, "angle_deg": angle_deg})

    write_object(obj, root / "object.ply")
    manifest = {
        "format": "grasp-capture-session/1",
        "session_id": session_id,
        "participant": participant,
        "object_id": obj.name,
        "intent": intent,
        "hand": "right",
        "object_mesh": "object.ply",
        "color_camera": {"K": _matrix(K),
                         "dist": [0.0] * 5 if dist is None else [float(d) for d in dist],
                         "width": cfg.width,
                         "height": cfg.height},
        "depth_scale_m": 0.001,
        "thermal_camera": {"K": _matrix(K_th), "dist": [0.0] * 5, "width": cfg.thermal_width,
                           "height": cfg.thermal_height,
                           "T_color_thermal": _matrix(T_color_thermal)},
        "turntable": {"T_color_turntable": _matrix(T_color_turntable)},
        "stage1": {"depth": "stage1/depth.png", "color": "stage1/color.png"},
        "grasp": {"fps": cfg.fps, "count": count, "color": COLOR_PATTERN, "depth": DEPTH_PATTERN,
                  "keypoints": KEYPOINTS_PATTERN,
                  "steady_from": steady if cfg.write_steady_from else None},
        "scan": {"views": views},
    }
    SessionManifest.model_validate(manifest)  # the writer honours the contract
    _write(root / "session.json", (json.dumps(manifest, indent=2) + "\n").encode())

    truth = {
        "generator": STAGE_VERSION,
        "config_digest": cfg.digest(),
        "difficulty": cfg.difficulty.value,
        "seed": seed,
        "object_id": obj.name,
        "T_w_o_stage1": _matrix(T_w_o1),
        "T_adj": _matrix(T_adj),
        "steady_from": steady,
        "T_w_c": [_matrix(inv_T(M)) for M in motions],
        "joints_w": _matrix(joints_w),
        "T_turntable_o_scan": _matrix(T_turntable_o_scan),
        "T_w_p": _matrix(T_w_p),
        "T_o_p": _matrix(grasp.T_o_p),
        "hand_scale": scale,
        "joint_angles_rad": [float(a) for a in grasp.angles_rad],
        "touching_fingers": [bool(t) for t in grasp.touching],
        "penetration_mm": grasp.penetration_m * 1000.0,
    }
    if _randomised(config):
        truth["randomisation"] = {
            "hand_model": WILD_HAND_VERSION if shape is not None else "hand_model/1",
            "hand_shape": None if shape is None else shape.to_json(),
            "camera": {"width": cfg.width, "height": cfg.height, "f_px": cfg.f_px},
            "dist": [0.0] * 5 if dist is None else [float(d) for d in dist],
            "depth_shift_px": list(depth_mm.shift_px),
            "object_extent_m": float((obj.vertices.max(0) - obj.vertices.min(0)).max()),
            "motion_turn_deg": total_turn_deg,
            "detector": detector,
        }
    _write(root / "ground_truth/truth.json", (json.dumps(truth, indent=1) + "\n").encode())
    np.save(root / "ground_truth/contact.npy", contact.astype(np.float32))
    np.save(root / "ground_truth/keypoints_clean.npy", clean)
    return root


Projection = Callable[[np.ndarray], np.ndarray]
"""Camera-frame points (n, 3) -> colour pixels (n, 2), through the lens when it has one."""


def _randomised(cfg: SynthConfig) -> bool:
    return any(getattr(cfg, name) is not None for name in RANDOMISATION_FIELDS)


def _wild_object(objects: ObjectSetConfig, faces: int, rng: np.random.Generator) -> ObjectMesh:
    """A procedural object of ``objects.names``, scaled into its plausible size range."""
    name = str(rng.choice(list(objects.names)))
    lo, hi = EXTENT_RANGE_M.get(name, objects.extent_m)
    lo, hi = max(lo, objects.extent_m[0]), min(hi, objects.extent_m[1])
    if lo > hi:
        raise StageError("synth", f"object {name}: its sizes {EXTENT_RANGE_M.get(name)} m lie "
                         f"outside object_set.extent_m {objects.extent_m}")
    return scaled_object(procedural_object(name, faces), float(rng.uniform(lo, hi)))


def _session_camera(cfg: SynthConfig, rng: np.random.Generator) -> SynthConfig:
    """``cfg`` with the session's drawn camera, distances in place of the fixed fields
    (``cfg`` itself when ``cfg.capture`` is None)."""
    cap = cfg.capture
    if cap is None:
        return cfg
    width, height, f_px = cap.cameras[int(rng.integers(len(cap.cameras)))]
    f_px *= 1.0 + rng.uniform(-cap.focal_jitter, cap.focal_jitter)
    return cfg.model_copy(update={"width": int(width), "height": int(height),
                                  "f_px": float(f_px),
                                  "camera_distance_m": cap.turntable_distance_m,
                                  "camera_elevation_deg": cap.camera_elevation_deg,
                                  "hand_distance_m": cap.hand_distance_m})


class _DepthSensor:
    """Depth images of ray hits: the fixed model of ``synth/2`` or Kinect v2-like."""

    def __init__(self, cfg: SynthConfig, rng: np.random.Generator):
        self.cfg, self.rng = cfg, rng
        self.shift_px = (0, 0)
        if cfg.kinect_depth is not None:
            self.dropout_rate = float(rng.uniform(*cfg.kinect_depth.dropout_rate))
            self.shift_px = depth_shift_px(cfg.kinect_depth, rng)

    def __call__(self, hits: RayHits) -> np.ndarray:
        if self.cfg.kinect_depth is None:
            return noisy_depth_mm(hits.depth_m, hits.cos_incidence, self.cfg, self.rng)
        return kinect_depth_mm(hits.depth_m, hits.cos_incidence, self.cfg.kinect_depth,
                               self.dropout_rate, self.shift_px, self.rng)



def _rot_z_deg(angle_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _adjustment(grasp: Grasp, T_w_o1: np.ndarray, T_w_o_steady: np.ndarray,
                T_color_turntable: np.ndarray, x: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Object pose, palm pose and angles at fraction ``x`` in [0, 1) of grasp adjustment.

    The open hand approaches and closes while the object still rests on the
    platter, then the object is lifted (with a small arc) to its steady pose
    while the fingers settle.
    """
    s_hand = float(smoothstep(x))
    s_obj = float(smoothstep((x - 0.35) / 0.65))
    T_w_o = interpolate_pose(T_w_o1, T_w_o_steady, s_obj)
    T_w_o[:3, 3] += T_color_turntable[:3, 2] * _LIFT_M * np.sin(np.pi * s_obj)
    back = make_T(np.eye(3), [0.0, 0.0, -_APPROACH_M * (1.0 - min(1.0, s_hand / 0.6))])
    angles = grasp.open_angles_rad + s_hand * (grasp.angles_rad - grasp.open_angles_rad)
    return T_w_o, T_w_o @ grasp.T_o_p @ back, angles


def _occluded(
    hits: RayHits, uv: np.ndarray, z_m: np.ndarray, margin_m: float = 0.003
) -> np.ndarray:
    """(21,) joints whose pixel shows the object (mesh 0) in front of them."""
    h, w = hits.depth_m.shape
    px = np.round(uv).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    out = np.zeros(len(uv), bool)
    u, v = px[inside, 0], px[inside, 1]
    out[inside] = (hits.mesh_index[v, u] == 0) & (hits.depth_m[v, u] < z_m[inside] - margin_m)
    return out


SELF_OCCLUSION_M = 0.03
"""A joint counts as hidden by the hand itself when the hand's surface at its pixel lies
this much in front of it (well over a finger's radius and capsule offset, up to 2 cm, so that
the joint's own skin never counts)."""


def _self_occluded(hits: RayHits, uv: np.ndarray, z_m: np.ndarray) -> np.ndarray:
    """(21,) joints whose pixel shows the hand (mesh 1) well in front of them."""
    h, w = hits.depth_m.shape
    px = np.round(uv).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    out = np.zeros(len(uv), bool)
    u, v = px[inside, 0], px[inside, 1]
    out[inside] = (hits.mesh_index[v, u] == 1) & (
        hits.depth_m[v, u] < z_m[inside] - SELF_OCCLUSION_M)
    return out


def _video_motion(obj: ObjectMesh, hand_o: np.ndarray, joints_o: np.ndarray,
                  T_w_o_steady: np.ndarray, T_color_turntable: np.ndarray, steady: int,
                  cfg: SynthConfig, rng: np.random.Generator, proj: Projection
                  ) -> tuple[np.ndarray, float | None]:
    """Rigid motions M_i (camera frame) of hand and object for frames ``steady`` .. count-1:
    turned by at least ``MIN_STEADY_TURN_DEG`` (``cfg.capture``: within its rotation range),
    in view and above the table; and the total turn aimed at (None without ``cfg.capture``)."""
    joints_w = transform_points(T_w_o_steady, joints_o)
    sample = transform_points(T_w_o_steady, np.concatenate([obj.vertices[::11], hand_o[::7]]))
    centre = transform_points(T_w_o_steady, joints_o[list(RIGID_PALM_POINTS)]).mean(axis=0)
    T_turntable_color = inv_T(T_color_turntable)
    def in_view(M: np.ndarray) -> bool:
        return _in_image(proj(transform_points(M, joints_w)), cfg, 5)

    def heights_m(M: np.ndarray) -> float:
        return float(transform_points(T_turntable_color @ M, sample)[:, 2].min())

    try:
        if cfg.capture is not None:
            return wild_motion(centre, cfg.frames - steady, cfg.capture, rng, in_view=in_view,
                               heights_m=heights_m, up=T_color_turntable[:3, 2])
        return steady_motion(centre, cfg.frames - steady, cfg, rng, in_view=in_view,
                             heights_m=heights_m, up=T_color_turntable[:3, 2]), None
    except StageError as e:
        raise StageError("synth", f"object {obj.name}: {e.reason}") from e
