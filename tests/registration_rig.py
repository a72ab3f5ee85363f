"""A small synthetic turntable rig for the registration tests (real meshes, rendered depth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from graspcap.tasks.core.geometry import inv_T, make_T, rot_z
from graspcap.tasks.core.render import render

WIDTH, HEIGHT = 640, 480
K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
PLATTER_RADIUS_M = 0.15
MESHES = {
    "mustard": "ycb_meshes/YcbMustardBottle/textured_simple_reoriented.obj",
    "soup": "ycb_meshes/YcbTomatoSoupCan/textured_simple_reoriented.obj",
    "fuze": "meshes_trimesh/fuze.obj",
    # The bunny PLY is already in metres (0.155 x 0.153 x 0.121 m): used unscaled.
    "bunny": "meshes_trimesh/bunny.ply",
}


def look_at_turntable(distance_m: float = 0.7, elevation_deg: float = 40.0) -> np.ndarray:
    """``T_color_turntable`` of a camera ``distance_m`` from the platter centre, looking at it
    from ``elevation_deg`` above the horizontal."""
    e = np.radians(elevation_deg)
    c = np.array([0.0, -distance_m * np.cos(e), distance_m * np.sin(e)])
    z = -c / np.linalg.norm(c)
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    T_turntable_color = make_T(np.stack([x, y, z], axis=1), c)
    return inv_T(T_turntable_color)


def load_mesh(shared_data: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3), faces (m, 3)) of one of :data:`MESHES`."""
    m = trimesh.load(shared_data / MESHES[name], force="mesh")
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


def stable_pose(vertices: np.ndarray, faces: np.ndarray, index: int = 0) -> np.ndarray:
    """``T_turntable_o`` resting the mesh on z = 0 in its ``index``-th most likely stable pose,
    centred over the origin."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    poses, _ = trimesh.poses.compute_stable_poses(mesh, n_samples=1)
    T = poses[index]
    v = trimesh.transform_points(vertices, T)
    centre = (v.min(0) + v.max(0)) / 2
    return make_T(np.eye(3), [-centre[0], -centre[1], -v[:, 2].min()]) @ T


def background() -> list[tuple[tuple[np.ndarray, np.ndarray], np.ndarray]]:
    """Platter disk (top at z = 0) and table (top at z = -0.03), turntable frame."""
    platter = trimesh.creation.cylinder(radius=PLATTER_RADIUS_M, height=0.03, sections=96)
    table = trimesh.creation.box([1.6, 1.6, 0.02])
    return [
        ((platter.vertices, platter.faces), make_T(np.eye(3), [0, 0, -0.015])),
        ((table.vertices, table.faces), make_T(np.eye(3), [0, 0.2, -0.04])),
    ]


def noisy_depth(hits_depth_m, cos_incidence, rng, noise_m=0.001, min_cos=0.2) -> np.ndarray:
    """Rendered depth with Gaussian noise, grazing pixels dropped and quantised to mm."""
    d = hits_depth_m + rng.normal(0.0, noise_m, hits_depth_m.shape)
    d = np.where((hits_depth_m > 0) & (cos_incidence >= min_cos), d, 0.0)
    return np.round(d * 1000.0) / 1000.0


def render_turntable(
    obj: tuple[np.ndarray, np.ndarray],
    T_turntable_o: np.ndarray,
    T_color_turntable: np.ndarray,
    rng: np.random.Generator,
    angle_rad: float = 0.0,
    with_object: bool = True,
) -> np.ndarray:
    """Noisy depth (h, w) of the platter turned by ``angle_rad``, with the object on it."""
    meshes, poses = [], []
    T_color_platter = T_color_turntable @ rot_z(angle_rad)  # the platter, turned
    for mesh, T_turntable_m in background():  # the disk looks the same at any angle
        meshes.append(mesh)
        poses.append(T_color_turntable @ T_turntable_m)
    if with_object:
        meshes.append(obj)
        poses.append(T_color_platter @ T_turntable_o)
    hits = render(meshes, poses, K, WIDTH, HEIGHT)
    return noisy_depth(hits.depth_m, hits.cos_incidence, rng)


def random_pose_on_platter(
    vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator, index: int = 0
) -> np.ndarray:
    """A stable pose, turned by a random angle about z and shifted up to 3 cm."""
    shift = make_T(np.eye(3), [*rng.uniform(-0.03, 0.03, 2), 0.0])
    return shift @ rot_z(rng.uniform(0, 2 * np.pi)) @ stable_pose(vertices, faces, index)


def lifted_in_hand(
    obj: tuple[np.ndarray, np.ndarray],
    T_w_o1: np.ndarray,
    T_color_turntable: np.ndarray,
    rng: np.random.Generator,
    lift_m: float = 0.2,
    angle_deg: float = 30.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The object moved ``lift_m`` towards the camera and turned ``angle_deg`` about a random
    axis through its centre, with three capsule "fingers" in front of part of it.

    Returns (noisy depth (h, w), hand mask (h, w) bool, true ``T_w_o``).
    """
    V, _ = obj
    c_o = (V.min(0) + V.max(0)) / 2
    c_w = T_w_o1[:3, :3] @ c_o + T_w_o1[:3, 3]
    axis = rng.normal(size=3)
    R = trimesh.transformations.rotation_matrix(np.radians(angle_deg), axis)[:3, :3]
    c_new = c_w - lift_m * c_w / np.linalg.norm(c_w)
    T_w_o = make_T(R @ T_w_o1[:3, :3], c_new - R @ T_w_o1[:3, :3] @ c_o)
    meshes, poses = [m for m, _ in background()], [T_color_turntable @ T for _, T in background()]
    meshes.append(obj)
    poses.append(T_w_o)
    alone = render([obj], [T_w_o], K, WIDTH, HEIGHT).depth_m
    v, u = np.nonzero(alone > 0)
    u0 = np.percentile(u, 70)  # fingers across the right part of the object, touching it
    for dv in (-14, 0, 14):
        r = int(np.median(v)) + dv
        col = u[v == r][np.argmin(np.abs(u[v == r] - u0))]
        z = alone[r, col]
        p = np.array([(col - K[0, 2]) / K[0, 0] * z, (r - K[1, 2]) / K[1, 1] * z, z])
        finger = trimesh.creation.capsule(height=0.05, radius=0.008)
        centre = p - 0.0085 * p / np.linalg.norm(p)
        Rf = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])[:3, :3]
        meshes.append((finger.vertices, finger.faces))
        poses.append(make_T(Rf, centre))
    hits = render(meshes, poses, K, WIDTH, HEIGHT)
    depth = noisy_depth(hits.depth_m, hits.cos_incidence, rng)
    mask = hits.mesh_index >= len(background()) + 1
    return depth, mask, T_w_o


def lifted_procedural(kind: str, seed: int, angle_deg: float):
    """A procedural ``kind`` on the platter (pose from ``seed``), then lifted and turned
    ``angle_deg`` in the hand (``lifted_in_hand``, rng ``100 + seed``): (mesh (V, F),
    T_w_o_stage1, depth, hand mask, true T_w_o)."""
    from graspcap.synth.objects import procedural_object

    obj = procedural_object(kind)
    mesh = (obj.vertices, obj.faces)
    T_color_turntable = look_at_turntable()
    T_w_o1 = T_color_turntable @ random_pose_on_platter(*mesh, np.random.default_rng(seed),
                                                        index=0)
    depth, mask, T_true = lifted_in_hand(
        mesh, T_w_o1, T_color_turntable, np.random.default_rng(100 + seed), angle_deg=angle_deg
    )
    return mesh, T_w_o1, depth, mask, T_true


def rig_session_stage1(out: Path, seed: list[int], kind: str):
    """Stage-1 inputs of the synthetic rig session ``seed`` (realistic preset) whose object
    is a ``kind``, and its true pose: (depth_m, K, T_color_turntable, V, F, T_w_o_stage1).
    The stage-1 scene is drawn before the video, so 8 frames give the same stage 1 as 60."""
    from graspcap.synth import config_for, generate_session
    from graspcap.synth.evaluate import load_truth
    from graspcap.tasks import pipeline

    d = generate_session(out, seed, config_for("realistic", 8))
    assert d.name.endswith(kind)
    s = pipeline.run_stage(
        pipeline.STAGES["load_session"], d, pipeline.configs_for()["load_session"], {}
    )
    V, F = s.read_mesh()
    return (
        s.read_depth_m(s.manifest.stage1.depth),
        np.asarray(s.manifest.color_camera.K, float),
        np.asarray(s.manifest.turntable.T_color_turntable, float),
        V,
        F,
        np.asarray(load_truth(d)["T_w_o_stage1"], float),
    )
