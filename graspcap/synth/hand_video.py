"""Synthetic 2D keypoint tracks of a hand that settles a grasp and then holds still.

The camera is static; the hand moves. As everywhere in the project this is written as
virtual cameras ``T_w_c[i]`` orbiting a static hand (``T_w_c[steady_from] = I``). Before
``steady_from`` the fingers are still closing (their flexion changes at a steady rate), after
it the joints hold still. Observations get pixel noise, confident outliers and misses; a
depth lookup returns the distance to the skin above each joint, with some samples hitting
the object in front of the finger instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from graspcap.tasks.core.geometry import inv_T, make_T, project

K_DEFAULT = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])

# Hand frame: wrist at the origin, fingers along +y, palm in the x-y plane, flexion to -z.
_BASES = {  # first joint of each chain (thumb CMC, finger MCPs), metres
    "thumb": (0.022, 0.025, -0.012),
    "index": (0.024, 0.088, 0.0),
    "middle": (0.004, 0.093, 0.0),
    "ring": (-0.015, 0.087, 0.0),
    "little": (-0.032, 0.077, 0.0),
}
_LENGTHS = {
    "thumb": (0.040, 0.032, 0.028),
    "index": (0.045, 0.026, 0.022),
    "middle": (0.050, 0.030, 0.024),
    "ring": (0.047, 0.028, 0.022),
    "little": (0.037, 0.021, 0.019),
}
_FINGERS = ("thumb", "index", "middle", "ring", "little")
HALF_CLOSED_DEG = np.array([[20.0, 25.0, 20.0]] + [[35.0, 45.0, 25.0]] * 4)
"""Flexion (5 fingers x 3 joints) of a half-closed grasp, degrees."""


def hand_keypoints(flexion_deg: np.ndarray = HALF_CLOSED_DEG) -> np.ndarray:
    """21 keypoints (21, 3) in metres in the hand frame for a flexion (5, 3) in degrees."""
    pts = [np.zeros(3)]
    for f, name in enumerate(_FINGERS):
        base = np.array(_BASES[name])
        if name == "thumb":
            u = np.array([0.7, 0.7, -0.2])
            axis = np.array([0.5, -0.5, 0.7])
        else:
            u, axis = np.array([0.0, 1.0, 0.0]), np.array([-1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        axis -= axis @ u * u
        axis /= np.linalg.norm(axis)
        p, angle = base, 0.0
        pts.append(p.copy())
        for k, length in enumerate(_LENGTHS[name]):
            angle += np.radians(flexion_deg[f, k])
            p = p + length * Rotation.from_rotvec(angle * axis).apply(u)
            pts.append(p.copy())
    return np.array(pts)


@dataclass(frozen=True)
class HandVideo:
    """A synthetic grasp video's keypoints with ground truth.

    keypoints : (n, 21, 3) float, x, y pixels and confidence (0 = missed).
    K : (3, 3); steady_from : first steady frame.
    T_w_c : (n, 4, 4) virtual cameras for every frame (truth), ``T_w_c[steady_from] = I``.
    joints_w : (21, 3) metres, the static hand from ``steady_from`` on.
    joints_c : (n, 21, 3) metres, each frame's (possibly still moving) joints in its camera.
    outlier : (n, 21) bool, observations replaced by a gross error.
    skin_depth_m : (n, 21) what the depth sensor reads at each joint (0 = no reading).
    surface_offset_m : (21,) joint centre below the skin.
    """

    keypoints: np.ndarray
    K: np.ndarray
    steady_from: int
    T_w_c: np.ndarray
    joints_w: np.ndarray
    joints_c: np.ndarray
    outlier: np.ndarray
    skin_depth_m: np.ndarray
    surface_offset_m: np.ndarray

    def depth_at(self, frame: int, uv_px: np.ndarray) -> np.ndarray:
        """Depth lookup: the reading of the joint whose true projection is nearest (<= 12 px)."""
        true_uv = project(self.K, self.joints_c[frame])
        dist = np.linalg.norm(np.asarray(uv_px)[:, None] - true_uv[None], axis=2)
        j = dist.argmin(1)
        return np.where(dist.min(1) <= 12.0, self.skin_depth_m[frame, j], 0.0)


def make_hand_video(
    n_frames: int = 120,
    steady_from: int = 30,
    *,
    seed: int = 0,
    noise_px: float = 2.5,
    outlier_rate: float = 0.05,
    missing_rate: float = 0.03,
    max_rotation_deg: float = 60.0,
    closing_deg_per_frame: float = 2.0,
    depth_noise_m: float = 0.0015,
    occluded_rate: float = 0.05,
    surface_offset_m: float = 0.009,
    static_camera: bool = False,
    width: int = 640,
    height: int = 480,
) -> HandVideo:
    """A hand held at 0.35-0.6 m, turned by up to ``max_rotation_deg``, fingers closing first."""
    rng = np.random.default_rng(seed)
    K = K_DEFAULT
    final = HALF_CLOSED_DEG + rng.uniform(-8, 8, size=(5, 3))
    tilt_deg = [rng.uniform(-30, 30), rng.uniform(-20, 20), 180.0]
    T_w_h = make_T(Rotation.from_euler("xyz", tilt_deg, degrees=True).as_matrix(), np.zeros(3))
    pts_h = hand_keypoints(final)
    centre_h = pts_h.mean(0)
    T_w_h[:3, 3] = np.array([0.0, 0.0, 0.45]) - T_w_h[:3, :3] @ centre_h
    centre_w = np.array([0.0, 0.0, 0.45])

    k = np.arange(n_frames) - steady_from
    amp = np.radians(max_rotation_deg) / 2 * rng.uniform(0.6, 1.0, size=3) * [1.0, 1.0, 0.5]
    period = rng.uniform(90, 160, size=3)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    rotvec = amp * (np.sin(2 * np.pi * k[:, None] / period + phase) - np.sin(phase))
    dist = 0.45 + 0.1 * np.sin(2 * np.pi * k / rng.uniform(60, 120))
    lateral = 0.02 * np.sin(
        2 * np.pi * k[:, None] / rng.uniform(40, 80, size=2) + rng.uniform(0, 6, 2)
    )
    if static_camera:
        rotvec[:] = rotvec[steady_from]
        dist[:] = 0.45
        lateral[:] = 0.0
    lateral -= lateral[steady_from]
    T_w_c = np.empty((n_frames, 4, 4))
    for i in range(n_frames):
        R = Rotation.from_rotvec(rotvec[i]).as_matrix()
        centre = centre_w - dist[i] * R[:, 2] + R[:, :2] @ lateral[i]
        T_w_c[i] = make_T(R, centre)

    joints_w = pts_h @ T_w_h[:3, :3].T + T_w_h[:3, 3]
    joints_c = np.empty((n_frames, 21, 3))
    for i in range(n_frames):
        behind = max(steady_from - i, 0)
        flex = final - np.clip(closing_deg_per_frame * behind, 0, 60) * (final > 0)
        pts = hand_keypoints(flex) @ T_w_h[:3, :3].T + T_w_h[:3, 3]
        T_c_w = inv_T(T_w_c[i])
        joints_c[i] = pts @ T_c_w[:3, :3].T + T_c_w[:3, 3]

    uv = project(K, joints_c.reshape(-1, 3)).reshape(n_frames, 21, 2)
    conf = rng.uniform(0.5, 1.0, size=(n_frames, 21))
    obs = uv + rng.normal(0.0, noise_px, size=uv.shape)
    outlier = rng.random((n_frames, 21)) < outlier_rate
    ang = rng.uniform(0, 2 * np.pi, size=(n_frames, 21))
    mag = rng.uniform(20, 80, size=(n_frames, 21))
    obs[outlier] += (mag[..., None] * np.stack([np.cos(ang), np.sin(ang)], -1))[outlier]
    conf[outlier] = rng.uniform(0.7, 1.0, size=outlier.sum())
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)
    missing = (rng.random((n_frames, 21)) < missing_rate) | ~inside
    conf[missing] = 0.0
    obs[missing] = 0.0
    outlier &= ~missing

    offset = np.full(21, surface_offset_m)
    skin = joints_c[..., 2] - offset + rng.normal(0.0, depth_noise_m, size=(n_frames, 21))
    occluded = rng.random((n_frames, 21)) < occluded_rate
    skin[occluded] -= rng.uniform(0.02, 0.1, size=occluded.sum())
    return HandVideo(
        keypoints=np.concatenate([obs, conf[..., None]], axis=2),
        K=K,
        steady_from=steady_from,
        T_w_c=T_w_c,
        joints_w=joints_w,
        joints_c=joints_c,
        outlier=outlier,
        skin_depth_m=skin,
        surface_offset_m=offset,
    )
