"""A ball's rotation is unobservable: ICP refines its pose by translation alone
(``RegistrationConfig.round_spread``). Point-to-plane ICP's near-singular rotation steps threw
a wild 62 mm ball from its true pose (scene fitness 0.70) 100 mm off, fitness 0 (wild
[22921, 10])."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from graspcap.tasks.core.geometry import inv_T, make_T
from graspcap.tasks.object_pose.registration.engine import (
    RegistrationConfig,
    is_round,
    prepare_model,
    refine,
)
from graspcap.tasks.object_pose.registration.point_clouds import to_pcd

RADIUS_M = 0.031


def _ball() -> trimesh.Trimesh:
    """A 62 mm ball with its origin at its bottom, as the wild balls."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS_M)
    mesh.apply_translation([0.0, 0.0, RADIUS_M])
    return mesh


def _cap(centre: np.ndarray, n: int = 600, seed: int = 0) -> np.ndarray:
    """Points (n, 3) on the camera-facing third of a ball at ``centre`` (camera at the
    origin, looking along +z), 0.5 mm noise."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(4 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d[:, 2] < -0.5][:n]
    return centre + RADIUS_M * d + rng.normal(scale=0.0005, size=(len(d), 3))


def test_a_ball_is_round_a_box_and_a_can_are_not():
    cfg = RegistrationConfig()
    assert is_round(prepare_model(_ball().vertices, _ball().faces, cfg), 0.03)
    for mesh in (trimesh.creation.box((0.06, 0.06, 0.06)),
                 trimesh.creation.cylinder(0.033, 0.12)):  # fmt: skip
        assert not is_round(prepare_model(mesh.vertices, mesh.faces, cfg), 0.03)


def test_a_ball_is_refined_by_translation_from_any_rotation():
    ball = _ball()
    cfg = RegistrationConfig(round_spread=0.03)
    model = prepare_model(ball.vertices, ball.faces, cfg)
    centre = np.array([0.05, -0.02, 0.75])
    scene = to_pcd(_cap(centre))
    for seed in range(4):
        R = Rotation.random(random_state=seed).as_matrix()
        # the start: any rotation, its centre 12 mm off the truth's
        start_centre = centre + np.array([0.008, -0.006, 0.006])
        T_w_o = make_T(R, start_centre - R @ model.centroid)
        c = refine(scene, model, inv_T(T_w_o), cfg, "start")
        T = inv_T(c.T_o_s)
        assert np.linalg.norm(T[:3, :3] @ model.centroid + T[:3, 3] - centre) < 0.0015
        assert np.allclose(T[:3, :3], R)  # the rotation is kept
        assert c.fitness > 0.9
