"""Rigid transforms, similarity fits and pinhole projection.

Conventions (``session-format.md``): ``T_a_b`` is a 4x4 homogeneous matrix
mapping points from frame ``b`` into frame ``a`` (``p_a = T_a_b @ p_b``);
metres and radians; OpenCV cameras (x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np

# scipy: imported where used, so that importing the stage table stays cheap


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Homogeneous transform from a rotation ``R`` (3, 3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4, 4), exact for rotations."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def rot_z(angle_rad: float) -> np.ndarray:
    """Right-handed rotation about z as a 4x4 transform."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def from_rotvec(rotvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from an axis-angle vector (3,) in radians and a translation (3,)."""
    from scipy.spatial.transform import Rotation

    return make_T(Rotation.from_rotvec(rotvec).as_matrix(), t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply ``T`` (4, 4) to ``points`` (n, 3); returns (n, 3)."""
    points = np.asarray(points, dtype=float)
    return points @ T[:3, :3].T + T[:3, 3]


def project(K: np.ndarray, points_c: np.ndarray) -> np.ndarray:
    """Pinhole projection of camera-frame ``points_c`` (n, 3) to pixels (n, 2)."""
    points_c = np.asarray(points_c, dtype=float)
    uvw = points_c @ np.asarray(K, dtype=float).T
    return uvw[:, :2] / uvw[:, 2:3]


def backproject(K: np.ndarray, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Pixels ``uv`` (n, 2) at depths ``z`` (n,) metres -> camera-frame points (n, 3)."""
    uv = np.asarray(uv, dtype=float)
    z = np.asarray(z, dtype=float)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


def depth_to_points(depth_m: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels of a depth image (h, w) in metres.

    Returns (points (n, 3) in the camera frame, pixel indices (n, 2) as v, u).
    """
    v, u = np.nonzero(depth_m > 0)
    pts = backproject(K, np.stack([u, v], axis=1), depth_m[v, u])
    return pts, np.stack([v, u], axis=1)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[np.ndarray, float]:
    """Least-squares similarity with ``dst ~ s * R @ src + t`` (Umeyama 1991).

    Parameters
    ----------
    src, dst : (n, 3) float
        Corresponding points, n >= 3 and not collinear.

    Returns
    -------
    T : (4, 4) float
        Rigid part ``[R | t]`` (the scale is not folded in).
    s : float
        Scale (1.0 when ``with_scale`` is False).
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / xs.var(0).sum()) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return make_T(R, t), s


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of ``R_a^T R_b`` in degrees."""
    cos = (np.trace(np.asarray(R_a)[:3, :3].T @ np.asarray(R_b)[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two poses."""
    return (
        rotation_error_deg(T_est[:3, :3], T_true[:3, :3]),
        float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])),
    )
