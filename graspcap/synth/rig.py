"""The capture rig's geometry: cameras, turntable, object placement and hand-object motion."""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation, Slerp

from graspcap.synth.config import LensConfig, SynthConfig
from graspcap.synth.objects import ObjectMesh
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import from_rotvec, inv_T, make_T, rot_z

TABLE_HALF_M = 0.6
TABLE_THICKNESS_M = 0.03


def color_K(cfg: SynthConfig) -> np.ndarray:
    """(3, 3) colour-camera intrinsics, principal point at the image centre."""
    return np.array([[cfg.f_px, 0, cfg.width / 2], [0, cfg.f_px, cfg.height / 2], [0, 0, 1.0]])


def project_distorted(K: np.ndarray, dist: np.ndarray, points_c: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) of camera-frame ``points_c`` (n, 3) through OpenCV's radial-tangential
    model ``dist`` (k1, k2, p1, p2, k3), as ``cv2.projectPoints`` computes them."""
    k1, k2, p1, p2, k3 = np.asarray(dist, float)[:5]
    p = np.asarray(points_c, float)
    x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def sample_lens(lens: LensConfig, K: np.ndarray, width: int, height: int,
                rng: np.random.Generator) -> np.ndarray:
    """Distortion coefficients (5,) drawn from ``lens``'s ranges, redrawn until the
    distorted radius grows monotonically out to the image corners (a lens that folds the
    image onto itself is no lens)."""
    corner = np.hypot(width / 2, height / 2) / min(K[0, 0], K[1, 1]) * 1.05
    r = np.linspace(0.0, 3.0, 3001)
    for _ in range(100):
        k1, k2, k3 = (rng.uniform(*lens.k1), rng.uniform(*lens.k2), rng.uniform(*lens.k3))
        p1, p2 = rng.uniform(-lens.p, lens.p, 2)
        rd = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
        rising = np.flatnonzero(np.diff(rd) <= 0)
        top = rd[: rising[0] + 1].max() if len(rising) else rd.max()
        if top > corner * 1.1:
            return np.array([k1, k2, p1, p2, k3])
    raise StageError("synth", f"no lens in {lens} keeps a {width}x{height} image monotonic")


def distorted_pixel_rays(K: np.ndarray, dist: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit rays (h, w, 3) through every pixel centre of a camera with distortion ``dist``
    (each pixel undistorted iteratively, to 1e-10 in normalised coordinates)."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)[:, None]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    xy = cv2.undistortPoints(uv, K, np.asarray(dist, float), criteria=criteria)[:, 0]
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(height, width, 3)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def thermal_K(cfg: SynthConfig) -> np.ndarray:
    """(3, 3) thermal-camera intrinsics, principal point at the image centre."""
    return np.array([[cfg.thermal_f_px, 0, cfg.thermal_width / 2],
                     [0, cfg.thermal_f_px, cfg.thermal_height / 2], [0, 0, 1.0]])


def thermal_extrinsics(cfg: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """``T_color_thermal``: a few centimetres beside the colour camera, nearly parallel."""
    direction = rng.uniform(0, 2 * np.pi)
    offset = rng.uniform(*cfg.thermal_offset_m)
    t = [offset * np.cos(direction), offset * np.sin(direction), rng.uniform(-0.005, 0.005)]
    return from_rotvec(rng.normal(0, np.radians(1.0), 3), t)


def turntable_pose(cfg: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """``T_color_turntable``: camera 0.6-0.8 m from the platter centre, looking down 30-45 deg."""
    dist = rng.uniform(*cfg.camera_distance_m)
    elev = np.radians(rng.uniform(*cfg.camera_elevation_deg))
    yaw = rng.uniform(0, 2 * np.pi)
    forward = np.array([0.0, np.cos(elev), -np.sin(elev)])
    centre = -dist * forward
    x = np.cross(forward, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R_turntable_color = np.stack([x, np.cross(forward, x), forward], axis=1)
    # Aim a little off the platter centre so the object is not always dead centre.
    T_turntable_color = (rot_z(yaw) @ make_T(R_turntable_color, centre)
                         @ from_rotvec(rng.normal(0, 0.02, 3), [0, 0, 0]))
    return inv_T(T_turntable_color)


def platter_mesh(cfg: SynthConfig) -> tuple[np.ndarray, np.ndarray]:
    """Platter disk in the turntable frame, top face at z = 0."""
    disk = trimesh.creation.cylinder(cfg.platter_radius_m, cfg.platter_thickness_m, sections=96)
    return np.asarray(disk.vertices) - [0, 0, cfg.platter_thickness_m / 2], np.asarray(disk.faces)


def table_mesh(cfg: SynthConfig) -> tuple[np.ndarray, np.ndarray]:
    """Table slab in the turntable frame, top face under the platter."""
    box = trimesh.creation.box([2 * TABLE_HALF_M, 2 * TABLE_HALF_M, TABLE_THICKNESS_M])
    shift = [0, 0, -cfg.platter_thickness_m - TABLE_THICKNESS_M / 2]
    return np.asarray(box.vertices) + shift, np.asarray(box.faces)


_MAX_HULL_FACES = 3000
"""Convex hulls with more faces (a ball, a bulb) are thinned before finding the stable poses
(their cost grows with the faces; the pose is settled onto the full mesh afterwards)."""


@lru_cache(maxsize=16)
def _stable_poses(key: str, vertices: bytes, faces: bytes) -> tuple[np.ndarray, np.ndarray]:
    v = np.frombuffer(vertices).reshape(-1, 3)
    f = np.frombuffer(faces, dtype=np.int64).reshape(-1, 3)
    mesh = trimesh.Trimesh(v, f, process=False)
    hull = mesh.convex_hull
    if len(hull.faces) > _MAX_HULL_FACES:  # round objects: rest them on a coarser hull
        step = int(np.ceil(len(hull.faces) / _MAX_HULL_FACES))
        mesh = trimesh.Trimesh(np.asarray(hull.vertices)[::step], process=False).convex_hull
    poses, prob = trimesh.poses.compute_stable_poses(mesh)
    keep = prob >= min(0.03, prob.max())  # a ball rests every way: keep its likeliest pose
    return poses[keep], prob[keep] / prob[keep].sum()


def rest_on_platter(
    obj: ObjectMesh, cfg: SynthConfig, rng: np.random.Generator, avoid: np.ndarray | None = None
) -> np.ndarray:
    """``T_turntable_o``: a stable resting pose, random yaw, small offset from the centre.

    ``avoid`` (n,) per-vertex weights (the contact map, for the scan): like an operator who
    knows the protocol, put the object down on a face that hides as little of them as the
    stable poses allow (no view from above sees the face on the platter).
    """
    poses, prob = _stable_poses(obj.name, obj.vertices.tobytes(), obj.faces.tobytes())
    if avoid is not None and avoid.sum() > 0:
        hidden = np.array([_hidden_share(obj, T, avoid) for T in poses])
        keep = hidden <= hidden.min() + 0.02
        prob = np.where(keep, prob, 0.0) / prob[keep].sum()
    T_stable = poses[rng.choice(len(poses), p=prob)]
    r, a = cfg.object_offset_m * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
    T = make_T(np.eye(3), [r * np.cos(a), r * np.sin(a), 0.0]) @ rot_z(rng.uniform(0, 2 * np.pi))
    T = T @ T_stable
    # compute_stable_poses rests the hull on z = 0; settle exactly onto the mesh's lowest point
    T[2, 3] -= (obj.vertices @ T[:3, :3].T + T[:3, 3])[:, 2].min()
    return T


def _hidden_share(obj: ObjectMesh, T: np.ndarray, weights: np.ndarray) -> float:
    """Share of ``weights`` on vertices facing the platter or within 3 mm of it in pose ``T``."""
    mesh = trimesh.Trimesh(obj.vertices, obj.faces, process=False)
    normal_z = mesh.vertex_normals @ T[2, :3]
    z = obj.vertices @ T[2, :3]
    hidden = (normal_z < -0.5) | (z < z.min() + 0.003)
    return float(weights[hidden].sum() / weights.sum())


def smoothstep(x: np.ndarray | float) -> np.ndarray:
    """0 -> 1 with zero slope at both ends; clipped outside [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def interpolate_pose(T_a: np.ndarray, T_b: np.ndarray, s: float) -> np.ndarray:
    """Pose between ``T_a`` (s = 0) and ``T_b`` (s = 1): slerp rotation, linear translation."""
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T_a[:3, :3], T_b[:3, :3]])))
    return make_T(slerp([s]).as_matrix()[0], (1 - s) * T_a[:3, 3] + s * T_b[:3, 3])
