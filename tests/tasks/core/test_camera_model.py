"""The lens model (``tasks/core/camera.py``): OpenCV semantics, round trips, and the exact
pinhole identity when ``dist`` is zero."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from graspcap.tasks.core.camera import Camera
from graspcap.tasks.core.geometry import project

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
LENSES = {
    "kinect": [0.1, -0.25, 0.001, -0.002, 0.08],
    "wide webcam": [-0.32, 0.14, 0.0008, -0.0012, -0.03],
    "four": [-0.1, 0.02, 0.0, 0.001],
    "rational 8": [0.2, -0.1, 0.001, 0.0, 0.01, 0.15, -0.05, 0.02],
}


def _points(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.3, 1.2, n)
    xy = rng.uniform(-0.45, 0.45, (n, 2)) * z[:, None]  # within the 640x480 field
    return np.concatenate([xy, z[:, None]], axis=1)


@pytest.mark.parametrize("dist", LENSES.values(), ids=LENSES.keys())
def test_project_is_cv2_projectpoints_and_undistort_inverts_it(dist):
    cam = Camera(K, dist, 640, 480)
    P = _points()
    px = cam.project(P)
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, np.asarray(dist))
    np.testing.assert_allclose(px, ref.reshape(-1, 2), atol=1e-9)
    assert np.abs(px - project(K, P)).max() > 1.0  # the lens moves pixels
    np.testing.assert_allclose(cam.undistort_px(px), project(K, P), atol=1e-6)
    np.testing.assert_allclose(cam.distort_px(cam.undistort_px(px)), px, atol=1e-6)


def test_zero_dist_is_the_pinhole_camera_bit_for_bit():
    cam = Camera(K, [0.0] * 5, 640, 480)
    assert not cam.distorted
    P = _points()
    assert np.array_equal(cam.project(P), project(K, P))
    px = project(K, P)
    assert np.array_equal(cam.undistort_px(px), px) and np.array_equal(cam.distort_px(px), px)
    keypoints = np.random.default_rng(1).uniform(0, 400, (7, 21, 3))
    assert cam.undistort_keypoints(keypoints) is keypoints
    depth = np.random.default_rng(2).integers(0, 3000, (480, 640)).astype(np.uint16)
    assert cam.undistort_image(depth) is depth


def test_keypoints_keep_confidence_and_nan():
    cam = Camera(K, LENSES["kinect"], 640, 480)
    kp = np.zeros((2, 21, 3))
    kp[..., :2] = project(K, _points(42))[:, :].reshape(2, 21, 2)
    kp[..., 2] = 0.7
    kp[1, 3, :2] = np.nan
    out = cam.undistort_keypoints(kp)
    assert np.array_equal(out[..., 2], kp[..., 2])
    assert np.isnan(out[1, 3, :2]).all() and np.isfinite(np.delete(out.reshape(-1, 3), 24, 0)).all()
    np.testing.assert_allclose(out[0, :, :2], cam.undistort_px(kp[0, :, :2]))


def test_points_outside_the_lens_field_never_fold_back_into_the_image():
    """Far outside the field a barrel polynomial turns back: cv2.projectPoints puts such a
    point inside the image; the camera says it is nowhere (NaN), as for z <= 0."""
    dist = np.array(LENSES["wide webcam"])
    cam = Camera(K, dist, 640, 480)
    P = np.array([[1.95, 0.05, 1.0], [0.05, 0.02, -0.5], [0.1, 0.05, 0.8]])
    ref, _ = cv2.projectPoints(P[:1], np.zeros(3), np.zeros(3), K, dist)
    assert 0 <= ref[0, 0, 0] < 640  # folded back in
    px = cam.project(P)
    assert np.isnan(px[:2]).all() and np.isfinite(px[2]).all()


def test_undistorted_image_holds_each_ideal_pixels_raw_sample():
    """``undistort_image`` (nearest) puts at every ideal pixel the raw pixel its ray lands on."""
    cam = Camera(K, LENSES["kinect"], 640, 480)
    raw = np.arange(640 * 480, dtype=np.int32).reshape(480, 640).astype(np.float32)
    ideal = cam.undistort_image(raw)
    v, u = np.mgrid[20:460:37, 20:620:41]
    lands = cam.distort_px(np.stack([u.ravel(), v.ravel()], 1).astype(float))
    want = raw[np.round(lands[:, 1]).astype(int), np.round(lands[:, 0]).astype(int)]
    assert np.mean(ideal[v.ravel(), u.ravel()] == want) > 0.98  # float32 map rounding at .5
    assert np.abs(ideal[v.ravel(), u.ravel()] - want).max() <= 641  # never more than a pixel
    bilinear = cam.undistort_image(raw, nearest=False)
    assert not np.array_equal(bilinear, ideal)
