"""Sensor models: depth noise and dropouts, shaded colour, thermal contact, 2D hand detections."""

from __future__ import annotations

import cv2
import numpy as np

from graspcap.synth.config import KinectDepthConfig, RealDetectorConfig, SynthConfig
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


# --- the wild profile's sensors -----------------------------------------------------------

DETECTOR_EVENTS = ("ok", "missing", "wrong_place", "mirrored", "other_hand")
"""Per-frame outcome of the real-detector model (a label swap is recorded separately)."""


def kinect_depth_mm(
    depth_m: np.ndarray, cos_incidence: np.ndarray, kc: KinectDepthConfig,
    dropout_rate: float, shift_px: tuple[int, int], rng: np.random.Generator,
) -> np.ndarray:
    """What a Kinect v2 registered to the colour camera reports, as uint16 millimetres.

    Flying pixels at depth edges (a depth between the near and the far side), axial noise
    ``kc.sigma_1m_m * z ** kc.sigma_exponent``, missing pixels at grazing incidence, single
    dropouts and a few missing blobs, then the whole image shifted by ``shift_px`` (dx, dy)
    against the colour image (the registration's error).
    """
    z = depth_m.astype(np.float32)
    h, w = z.shape
    valid = z > 0
    kernel = np.ones((3, 3), np.uint8)
    far = cv2.dilate(z, kernel)
    near = cv2.erode(np.where(valid, z, np.float32(1e3)), kernel)
    edge = valid & (far - near > 0.02) & (near < 1e2)
    alpha = rng.random(z.shape, dtype=np.float32)
    fly = edge & (rng.random(z.shape) < kc.flying_pixel_rate)
    z = np.where(fly, near + alpha * (far - near), z)
    sigma = np.float32(kc.sigma_1m_m) * np.power(np.maximum(z, 1e-3), np.float32(kc.sigma_exponent))
    noisy = z + sigma * rng.standard_normal(z.shape, dtype=np.float32)
    missing = ~valid | (cos_incidence < kc.grazing_cos_min) & ~fly
    missing |= rng.random(z.shape) < dropout_rate
    yy, xx = np.mgrid[0:h, 0:w]
    blobs = rng.uniform([0, 0, 2.5, 2.5], [w, h, 10, 10], (kc.dropout_blobs, 4))
    for cx, cy, rx, ry in blobs:
        x0, x1 = int(max(cx - rx, 0)), int(min(cx + rx + 1, w))
        y0, y1 = int(max(cy - ry, 0)), int(min(cy + ry + 1, h))
        win = (slice(y0, y1), slice(x0, x1))
        missing[win] |= ((xx[win] - cx) / rx) ** 2 + ((yy[win] - cy) / ry) ** 2 <= 1
    mm = np.clip(np.round(noisy * np.float32(1000.0)), 0, 65535)
    mm[missing] = 0
    dx, dy = shift_px
    out = np.zeros_like(mm)
    out[max(dy, 0): h + min(dy, 0), max(dx, 0): w + min(dx, 0)] = \
        mm[max(-dy, 0): h + min(-dy, 0), max(-dx, 0): w + min(-dx, 0)]
    return out.astype(np.uint16)


def depth_shift_px(kc: KinectDepthConfig, rng: np.random.Generator) -> tuple[int, int]:
    """A session's depth-to-colour offset (dx, dy): whole pixels, length in the range."""
    length, angle = rng.uniform(*kc.misalignment_px), rng.uniform(0, 2 * np.pi)
    dx, dy = int(round(length * np.cos(angle))), int(round(length * np.sin(angle)))
    return (dx, dy) if (dx, dy) != (0, 0) else (1, 0)


def _hand_size_px(uv: np.ndarray) -> float:
    """Diagonal of the bounding box of keypoints (21, 2)."""
    return float(np.linalg.norm(uv.max(axis=0) - uv.min(axis=0)))


def real_detections(
    clean_px: np.ndarray, occluded: np.ndarray, width: int, height: int,
    dc: RealDetectorConfig, rng: np.random.Generator,
) -> tuple[list[np.ndarray | None], list[str], np.ndarray, float]:
    """A real detector's output over a whole video (errors correlate across frames).

    Parameters
    ----------
    clean_px : (n, 21, 2) float
        True joint projections per frame.
    occluded : (n, 21) bool
        Joints hidden behind the object per frame.

    Returns
    -------
    detections : n x ((21, 3) x, y, confidence, or None for no hand)
    events : n labels from :data:`DETECTOR_EVENTS`
    swapped : (n,) bool, frames with two fingers' labels exchanged
    error_share : the session's mean per-joint error share (visible joints, good frames)
    """
    n = len(clean_px)
    share = rng.uniform(*dc.error_share)
    rho = rng.uniform(*dc.correlation)
    fail_rate = rng.uniform(*dc.frame_failure_rate)
    # AR(1) errors, unit variance: a per-joint part and a whole-hand part
    e = np.empty((n, 21, 2))
    common = np.empty((n, 1, 2))
    e[0], common[0] = rng.standard_normal((21, 2)), rng.standard_normal((1, 2))
    innov = np.sqrt(1 - rho * rho)
    for i in range(1, n):
        e[i] = rho * e[i - 1] + innov * rng.standard_normal((21, 2))
        common[i] = rho * common[i - 1] + innov * rng.standard_normal((1, 2))
    unit = np.sqrt(0.7) * e + np.sqrt(0.3) * common
    weight = np.where(occluded, dc.occluded_factor, 1.0)
    weight[:, [4, 8, 12, 16, 20]] *= 1.2
    events = ["ok"] * n
    i = 0
    while i < n:  # runs of missing frames, then runs of whole-frame failures
        if rng.random() < dc.missing_run_rate:
            run = int(rng.integers(dc.missing_run_frames[0], dc.missing_run_frames[1] + 1))
            events[i: i + run] = ["missing"] * len(events[i: i + run])
            i += run
        elif rng.random() < fail_rate:
            kind = str(rng.choice(["wrong_place", "mirrored", "other_hand"]))
            run = 1 + int(rng.random() < 0.4) + int(rng.random() < 0.2)
            events[i: i + run] = [kind] * len(events[i: i + run])
            i += run
        else:
            i += 1
    swapped = (rng.random(n) < dc.swap_rate) & (np.array(events) != "missing")
    out: list[np.ndarray | None] = []
    for i in range(n):
        # fixed draws per frame keep the streams aligned whatever the events
        size = max(_hand_size_px(clean_px[i]), 1.0)
        sigma = share * size / np.sqrt(np.pi / 2)  # mean norm of a 2D Gaussian: sigma sqrt(pi/2)
        uv = clean_px[i] + unit[i] * (sigma * weight[i])[:, None]
        shift_dir, shift_len = rng.uniform(0, 2 * np.pi), rng.uniform(0.6, 2.0) * size
        turn, other, zoom = rng.uniform(-0.7, 0.7), int(rng.integers(n)), rng.uniform(0.7, 1.3)
        place = rng.uniform([0.1 * width, 0.1 * height], [0.9 * width, 0.9 * height])
        swap_pair = int(rng.integers(1, 4))
        conf_noise = rng.normal(0.0, dc.confidence_noise, 21)
        lost = rng.random(21) < dc.joint_missing_rate
        kind = events[i]
        if kind == "missing":
            out.append(None)
            continue
        if kind == "wrong_place":
            c = uv.mean(axis=0)
            uv = c + (uv - c) @ _rot2(turn).T + shift_len * np.array([np.cos(shift_dir),
                                                                      np.sin(shift_dir)])
        elif kind == "mirrored":  # reflected across the wrist - middle MCP line
            a, b = uv[0], uv[9]
            d = (b - a) / max(np.linalg.norm(b - a), 1e-9)
            rel = uv - a
            uv = a + 2 * (rel @ d)[:, None] * d - rel
        elif kind == "other_hand":
            src = clean_px[other] + unit[other] * sigma
            c = src.mean(axis=0)
            uv = place + zoom * (src - c) @ _rot2(3 * turn).T
        err = np.linalg.norm(uv - clean_px[i], axis=1) / size
        if kind == "ok":
            conf = 0.9 - 0.35 * np.minimum(err / 0.25, 1.0) + conf_noise
        else:  # a confident wrong answer
            conf = 0.85 - 0.2 * rng.random() + conf_noise
        conf = np.clip(conf - 0.15 * occluded[i], 0.05, 1.0)
        kp = np.concatenate([uv, conf[:, None]], axis=1)
        if swapped[i]:
            a_rows, b_rows = FINGER_ROWS[swap_pair], FINGER_ROWS[swap_pair + 1]
            kp[a_rows + b_rows] = kp[b_rows + a_rows]
        outside = (kp[:, 0] < 0) | (kp[:, 0] >= width) | (kp[:, 1] < 0) | (kp[:, 1] >= height)
        kp[lost | outside] = 0.0
        out.append(kp)
    return out, events, swapped, float(share)


def _rot2(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])
