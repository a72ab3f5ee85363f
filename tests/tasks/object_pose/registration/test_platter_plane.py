"""The platter top measured in the depth (``PlatterCrop.fit_platter``): a wild rig's depth,
shifted against the colour camera, reads the platter millimetres off its calibrated height
(wild [80625, 4]: 3.7 mm up, tilted 1 deg; half the points kept as the object were the
platter's)."""

from __future__ import annotations

import numpy as np

from graspcap.tasks.core.geometry import make_T, transform_points
from graspcap.tasks.object_pose.registration.point_clouds import (
    PlatterCrop,
    crop_platter,
    platter_plane,
)

F_PX, W, H = 500.0, 320, 240
K = np.array([[F_PX, 0.0, W / 2], [0.0, F_PX, H / 2], [0.0, 0.0, 1.0]])


def _scene(offset_m: float, tilt_deg: float, noise_m: float, seed: int = 0):
    """Turntable-frame points: the platter top (r <= 0.15 m) at ``offset_m`` tilted by
    ``tilt_deg`` about x with depth-like noise, and a 4 cm cube of points standing on it."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.15, 0.15, (20000, 2))
    xy = xy[np.linalg.norm(xy, axis=1) <= 0.15]
    z = offset_m + np.tan(np.radians(tilt_deg)) * xy[:, 1] + rng.normal(0, noise_m, len(xy))
    platter = np.c_[xy, z]
    cube = rng.uniform([-0.02, -0.02, 0.0], [0.02, 0.02, 0.04], (3000, 3))
    cube[:, 2] += offset_m
    return platter, cube


def test_the_plane_is_found_under_an_object():
    platter, cube = _scene(0.0037, 1.0, 0.0014)
    coef, sigma = platter_plane(np.r_[platter, cube], PlatterCrop(fit_platter=True))
    assert abs(coef[2] - 0.0037) < 0.0005
    assert abs(np.degrees(np.arctan(coef[1])) - 1.0) < 0.2
    assert 0.001 < sigma < 0.002


def test_no_plane_without_a_platter_or_beyond_the_tilt():
    crop = PlatterCrop(fit_platter=True)
    _, cube = _scene(0.0, 0.0, 0.001)
    assert platter_plane(cube[cube[:, 2] > 0.02], crop) is None  # nothing near the top
    platter, _ = _scene(0.0, 8.0, 0.0005)
    assert platter_plane(platter[np.abs(platter[:, 2]) < 0.012], crop) is None


def _depth_of(points_t: np.ndarray, T_c_t: np.ndarray) -> np.ndarray:
    """A depth image (H, W) of turntable-frame points seen by a camera at ``T_c_t``."""
    p = transform_points(T_c_t, points_t)
    u = np.round(p[:, 0] / p[:, 2] * F_PX + W / 2).astype(int)
    v = np.round(p[:, 1] / p[:, 2] * F_PX + H / 2).astype(int)
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    d = np.zeros((H, W))
    order = np.argsort(-p[inside, 2])  # the nearest point of a pixel written last
    d[v[inside][order], u[inside][order]] = p[inside, 2][order]
    return d


def _crops(platter: np.ndarray, cube: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(calibrated crop, crop on the measured platter, T_t_c) of the scene's depth seen by a
    camera 0.8 m away looking down at the platter by 45 deg."""
    R = np.array([[1.0, 0.0, 0.0], [0.0, -np.sqrt(0.5), -np.sqrt(0.5)],
                  [0.0, np.sqrt(0.5), -np.sqrt(0.5)]])
    T_c_t = make_T(R, np.array([0.0, 0.0, 0.8]))
    depth = _depth_of(np.r_[platter, cube], T_c_t)
    calibrated = crop_platter(depth, K, T_c_t, PlatterCrop(drop_flying=False), prepared=True)
    measured = crop_platter(depth, K, T_c_t, PlatterCrop(drop_flying=False, fit_platter=True),
                            prepared=True)
    return calibrated, measured, np.linalg.inv(T_c_t)


def test_a_raised_platter_is_not_kept_as_the_object():
    calibrated, measured, T_t_c = _crops(*_scene(0.0045, 0.5, 0.0012, seed=1))

    def height(p: np.ndarray) -> np.ndarray:  # over the true (raised, tilted) platter top
        q = transform_points(T_t_c, p)
        return q[:, 2] - 0.0045 - np.tan(np.radians(0.5)) * q[:, 1]

    assert np.mean(height(calibrated) < 0.002) > 0.5  # the raised top outnumbers the cube
    assert np.mean(height(measured) < 0.002) < 0.02
    cube_kept = (height(measured) > 0.008).sum()
    assert cube_kept >= 0.98 * (height(calibrated) > 0.008).sum()


def test_a_platter_where_calibrated_keeps_the_calibrated_crop():
    # the depth confirms the calibration (within its noise): the crop is the calibrated one
    calibrated, measured, _ = _crops(*_scene(0.0, 0.0, 0.0012, seed=2))
    np.testing.assert_array_equal(measured, calibrated)
