"""Poses of many frames against one fixed set of 3D points: robust PnP, refined in one batch.

``select_steady`` poses every frame of a video against the same hand, several times. The
per-frame work that does not need a loop (Levenberg-Marquardt on the reprojection error under
a Huber loss) runs here for all frames at once as (n, 6, 6) normal equations; only the
RANSAC start (``cv2.solvePnPRansac``) is per frame, and a warm start skips it.
Poses are ``T_c_w`` (world into camera); cameras are OpenCV pinholes without distortion.
"""

from __future__ import annotations

import numpy as np

from graspcap.tasks.core.geometry import make_T

# cv2, scipy: imported where used, so that importing the stage table stays cheap

def ransac_poses(
    K: np.ndarray, points_w: np.ndarray, uv: np.ndarray, use: np.ndarray, ransac_px: float,
    min_points: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame RANSAC PnP (AP3P minimal sets), not refined.

    points_w : (21, 3) float, NaN where unknown; uv : (n, 21, 2) pixels; use : (n, 21) bool.
    Returns T_c_w (n, 4, 4) (NaN where no pose was found) and inliers (n, 21) bool.
    """
    import cv2

    n, nj = use.shape
    T = np.full((n, 4, 4), np.nan)
    inliers = np.zeros((n, nj), bool)
    known = np.all(np.isfinite(points_w), axis=1)
    for i in range(n):
        sel = np.flatnonzero(use[i] & known)
        if len(sel) < max(min_points, 6):
            continue
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            points_w[sel], uv[i, sel].astype(float), K, None, iterationsCount=100,
            reprojectionError=ransac_px, confidence=0.999, flags=cv2.SOLVEPNP_AP3P,
        )  # fmt: skip
        if not ok or inl is None or len(inl) < max(min_points // 2, 4):
            continue
        T[i] = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
        inliers[i, sel[inl.ravel()]] = True
    return T, inliers


def residual_vectors(
    K: np.ndarray, T_c_w: np.ndarray, points_w: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Observed minus projected pixels (n, 21, 2) and camera-frame points (n, 21, 3)."""
    Xc = points_w @ T_c_w[:, :3, :3].transpose(0, 2, 1) + T_c_w[:, None, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = Xc[..., :2] / Xc[..., 2:] * np.diag(K)[:2] + K[:2, 2]
    return uv - proj, Xc


def refine_poses(
    K: np.ndarray, points_w: np.ndarray, uv: np.ndarray, use: np.ndarray, T_c_w: np.ndarray,
    *, huber_px: float, outlier_px: float, iterations: int = 8,
) -> np.ndarray:
    """Levenberg-Marquardt of every frame's pose at once under a Huber loss.

    Observations farther than ``outlier_px`` from the current projection get no weight (they
    are re-judged every iteration); frames with fewer than 4 weighted observations keep their
    pose. T_c_w : (n, 4, 4) start (NaN rows stay NaN). Returns the refined (n, 4, 4).
    """
    from scipy.spatial.transform import Rotation

    T = np.array(T_c_w, dtype=float)
    posed = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    X = np.nan_to_num(points_w)
    use = use & np.all(np.isfinite(points_w), axis=1)[None] & posed[:, None]
    fx, fy = K[0, 0], K[1, 1]
    lam = np.full(len(T), 1e-3)
    rho_max = huber_px * (outlier_px - 0.5 * huber_px)

    def cost_and_weights(T):
        e, Xc = residual_vectors(K, np.nan_to_num(T), X, uv)
        r = np.nan_to_num(np.linalg.norm(e, axis=2), nan=np.inf)
        front = use & (Xc[..., 2] > 0)
        w = front & (r < outlier_px)
        w_h = np.where(r <= huber_px, 1.0, huber_px / np.maximum(r, 1e-12)) * w
        rc = np.minimum(r, outlier_px)
        rho = np.where(rc <= huber_px, 0.5 * rc**2, huber_px * (rc - 0.5 * huber_px))
        # truncated Huber: an observation beyond outlier_px costs a constant, so costs of
        # different outlier sets compare; one behind the camera costs as much
        return np.where(use, np.where(front, rho, rho_max), 0.0).sum(1), w, w_h, e, Xc

    cost, w, w_h, e, Xc = cost_and_weights(T)
    for _ in range(iterations):
        x, y, z = Xc[..., 0], Xc[..., 1], np.where(w, Xc[..., 2], 1.0)
        J_p = np.zeros(Xc.shape[:2] + (2, 3))  # d pixel / d camera point
        J_p[..., 0, 0], J_p[..., 0, 2] = fx / z, -fx * x / z**2
        J_p[..., 1, 1], J_p[..., 1, 2] = fy / z, -fy * y / z**2
        J_x = np.zeros(Xc.shape[:2] + (3, 6))  # d camera point / d (rotation, translation)
        J_x[..., 0, 1], J_x[..., 0, 2] = Xc[..., 2], -Xc[..., 1]
        J_x[..., 1, 0], J_x[..., 1, 2] = -Xc[..., 2], Xc[..., 0]
        J_x[..., 2, 0], J_x[..., 2, 1] = Xc[..., 1], -Xc[..., 0]
        J_x[..., :, 3:] = np.eye(3)
        J = -(J_p @ J_x)  # d residual (observed - projected) / d update
        J = J.reshape(len(T), -1, 6)  # (n, 42, 6)
        Jw = J * np.repeat(w_h, 2, axis=1)[..., None]
        H = Jw.transpose(0, 2, 1) @ J
        g = (Jw.transpose(0, 2, 1) @ np.where(w[..., None], e, 0.0).reshape(len(T), -1, 1))[..., 0]
        active = (w.sum(1) >= 4) & posed
        H_d = H + lam[:, None, None] * (np.eye(6) * H.diagonal(axis1=1, axis2=2)[:, None, :])
        H_d[~active] = np.eye(6)
        g[~active] = 0.0
        delta = -np.linalg.solve(H_d, g[..., None])[..., 0]
        R_d = Rotation.from_rotvec(delta[:, :3]).as_matrix()
        T_new = T.copy()
        T_new[:, :3, :3] = R_d @ T[:, :3, :3]
        T_new[:, :3, 3] = np.einsum("nab,nb->na", R_d, T[:, :3, 3]) + delta[:, 3:]
        cost_new, *rest = cost_and_weights(T_new)
        better = active & (cost_new <= cost)
        T[better] = T_new[better]
        lam = np.where(better, lam * 0.3, lam * 10.0)
        cost, w, w_h, e, Xc = cost_and_weights(T)
        if np.all(np.abs(delta[active]) < 1e-7):
            break
    T[~posed] = np.nan
    return T
