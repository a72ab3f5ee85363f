"""Sensor models: depth noise and dropouts, shaded colour, thermal contact, 2D hand detections."""

from __future__ import annotations

import cv2
import numpy as np

from graspcap.synth.config import SynthConfig
from graspcap.tasks.core.render import RayHits

# Albedo (RGB, 0-1) of the scene parts, by role.
ALBEDO = {
    "object": (0.2, 0.45, 0.8),
    "hand": (0.87, 0.67, 0.55),
    "platter": (0.55, 0.55, 0.55),
    "table": (0.55, 0.42, 0.3),
}
BACKGROUND_RGB = (0.12, 0.12, 0.14)

# Per-finger keypoint rows (thumb, index, middle, ring, little).
FINGER_ROWS = [list(range(1 + 4 * f, 5 + 4 * f)) for f in range(5)]


def noisy_depth_mm(
    depth_m: np.ndarray, cos_incidence: np.ndarray, cfg: SynthConfig, rng: np.random.Generator
) -> np.ndarray:
    """What a structured-light / stereo depth camera reports, as uint16 millimetres.

    Axial noise ``cfg.depth_sigma_m * (z / 0.7)^2``, rounded to whole millimetres;
    missing (0) where nothing is hit, at grazing incidence and at random dropouts.

    Parameters
    ----------
    depth_m, cos_incidence : (h, w) float
        Ideal depth and |cos| of incidence from a ray cast.
    """
    z = depth_m.astype(np.float32)
    sigma = np.float32(cfg.depth_sigma_m / 0.49) * z * z
    noisy = z + sigma * rng.standard_normal(z.shape, dtype=np.float32)
    missing = (z <= 0) | (cos_incidence < cfg.grazing_cos_min)
    if cfg.dropout_rate > 0:
        missing |= rng.random(z.shape) < cfg.dropout_rate
    mm = np.clip(np.round(noisy * np.float32(1000.0)), 0, 65535)
    mm[missing] = 0
    return mm.astype(np.uint16)


def shaded_rgb(hits: RayHits, albedo: list[tuple[float, float, float]],
               rng: np.random.Generator) -> np.ndarray:
    """A cheap Lambert-shaded colour image (h, w, 3) uint8 RGB; ``albedo`` per mesh index."""
    table = np.array([*albedo, BACKGROUND_RGB], dtype=np.float32) * 255.0  # -1 -> background
    light = np.where(hits.mesh_index >= 0, 0.3 + 0.7 * hits.cos_incidence, 1.0).astype(np.float32)
    rgb = np.take(table, hits.mesh_index, axis=0, mode="wrap") * light[..., None]
    rgb += rng.integers(-3, 4, rgb.shape, dtype=np.int16)  # sensor noise, about 2 levels
    return np.clip(rgb + 0.5, 0, 255).astype(np.uint8)


def thermal_centikelvin(
    hits: RayHits, faces: np.ndarray, contact: np.ndarray,
    cfg: SynthConfig, rng: np.random.Generator,
) -> np.ndarray:
    """Thermal image (h, w) uint16 in centi-kelvin: ambient plus heat left by the hand.

    The object's surface is ``ambient + rise * contact`` at each hit point
    (per-vertex ``contact`` interpolated barycentrically); the rest of the scene
    sits at ambient with a slight, smooth variation; then optics blur and noise.
    ``hits`` come from casting (object, platter, table) in that order.
    """
    h, w = hits.depth_m.shape
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    gradient = rng.uniform(-0.2, 0.2) * xx + rng.uniform(-0.2, 0.2) * yy
    offsets = np.array([0.0, -0.3, -0.5, 0.2])  # object, platter, table, background
    part = np.where(hits.mesh_index >= 0, np.minimum(hits.mesh_index, 2), 3)
    temp = cfg.thermal_ambient_k + gradient + offsets[part]
    temp += cfg.thermal_rise_k * hits.interpolate(0, faces, contact)
    if cfg.thermal_blur_px > 0:
        temp = cv2.GaussianBlur(temp, (0, 0), cfg.thermal_blur_px)
    temp += cfg.thermal_noise_k * rng.standard_normal(temp.shape)
    return np.clip(np.round(temp * 100.0), 0, 65535).astype(np.uint16)


def detect_keypoints(
    clean_px: np.ndarray, occluded: np.ndarray, width: int, height: int,
    cfg: SynthConfig, rng: np.random.Generator,
) -> np.ndarray | None:
    """What an OpenPose-like detector reports for one frame, or None when it finds no hand.

    Parameters
    ----------
    clean_px : (21, 2) float
        True joint projections.
    occluded : (21,) bool
        Joints hidden behind the object (still reported, with lower confidence).

    Returns
    -------
    (21, 3) float: x, y, confidence; (0, 0, 0) for a joint not detected.
    """
    draws = rng.random(5)  # fixed number of draws per frame keeps streams aligned
    noise = rng.standard_normal((21, 2)) * cfg.kp_sigma_px
    conf = np.where(occluded, rng.uniform(0.15, 0.45, 21), rng.uniform(0.55, 0.95, 21))
    u_out, u_miss = rng.random(21), rng.random(21)
    radius = rng.uniform(*cfg.kp_outlier_px, 21)
    angle = rng.uniform(0, 2 * np.pi, 21)
    out_conf = rng.uniform(0.6, 0.9, 21)
    swap_pair = int(rng.integers(1, 4))
    if draws[0] < cfg.kp_no_person_rate:
        return None
    kp = np.concatenate([clean_px + noise, conf[:, None]], axis=1)
    if draws[1] < cfg.kp_swap_rate:  # labels of two neighbouring fingers exchanged
        a, b = FINGER_ROWS[swap_pair], FINGER_ROWS[swap_pair + 1]
        kp[a + b] = kp[b + a]
    outlier = u_out < cfg.kp_outlier_rate
    kp[outlier, :2] += radius[outlier, None] * np.stack([np.cos(angle), np.sin(angle)], 1)[outlier]
    kp[outlier, 2] = out_conf[outlier]
    outside = (clean_px[:, 0] < 0) | (clean_px[:, 0] >= width) | (clean_px[:, 1] < 0) | (
        clean_px[:, 1] >= height)
    kp[(u_miss < cfg.kp_missing_rate) | outside] = 0.0
    return kp


def openpose_json(kp: np.ndarray | None) -> dict:
    """The OpenPose per-frame JSON document for a right-hand detection (or none)."""
    people = []
    if kp is not None:
        flat = [round(float(x), 3) for x in kp.reshape(-1)]
        people.append({"person_id": [-1], "pose_keypoints_2d": [],
                       "face_keypoints_2d": [], "hand_left_keypoints_2d": [],
                       "hand_right_keypoints_2d": flat})
    return {"version": 1.3, "people": people}
