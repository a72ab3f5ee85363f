"""Depth rendering (``core.render``): one mesh is cast in its own frame against a scene built
once, and must see what the scene rebuilt in the camera's frame sees."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from graspcap.tasks.core import render as R
from graspcap.tasks.core.geometry import make_T


def _reference_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit rays through the pixel centres, written out as the textbook formula."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_pixel_rays_are_the_normalised_pixel_directions_to_the_bit():
    # the synthetic rig renders with these rays: its sessions must not move by a bit
    for K, w, h in [(np.array([[519.2, 0, 480.1], [0, 519.9, 270.4], [0, 0, 1]]), 960, 540),
                    (np.array([[600.0, 0, 110.3], [0, 601.0, 95.7], [0, 0, 1]]), 220, 190)]:
        assert np.array_equal(R.pixel_rays(K, w, h), _reference_rays(K, w, h))


def test_one_mesh_in_its_own_frame_sees_what_the_camera_frame_scene_sees():
    mesh = trimesh.creation.annulus(0.02, 0.04, 0.08)  # holes and grazing walls
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    K = np.array([[600.0, 0, 110.0], [0, 600.0, 95.0], [0, 0, 1]])
    R._SCENES.clear()
    rng = np.random.default_rng(0)
    for k in range(6):
        T = make_T(Rotation.random(random_state=k).as_matrix(),
                   [rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), 0.4])
        cached = R.render([(V, F)], [T], K, 220, 190)
        rebuilt = R.cast_rays([(V, F)], [T], R.pixel_rays(K, 220, 190).astype(np.float32))
        hit = rebuilt.mesh_index >= 0
        assert hit.sum() > 2000
        assert np.array_equal(cached.mesh_index, rebuilt.mesh_index)
        # float32 vertices moved vs float32 rays moved: micrometres apart
        assert np.abs(cached.depth_m[hit] - rebuilt.depth_m[hit]).max() < 1e-5
        assert np.abs(cached.cos_incidence[hit] - rebuilt.cos_incidence[hit]).max() < 1e-3
        assert np.mean(cached.triangle[hit] == rebuilt.triangle[hit]) > 0.999
    assert len(R._SCENES) == 1  # built once for the six poses
