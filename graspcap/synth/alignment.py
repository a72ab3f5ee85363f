"""A camera trajectory aligned to the truth by one rigid transform fitted robustly over every
frame (the ATE-style evaluation of SLAM and SfM), for the synthetic evaluation.

Scoring each camera relative to one anchor camera (``evaluate._camera_errors``) carries the
anchor's error into every frame: one bad anchor turns a whole session's median. Here the
alignment ``T_true_est`` (estimated world -> true world) is the robust consensus of the
per-frame alignments ``T_true_c_i T_est_c_i^-1``: its rotation the L1 (geodesic median) mean
of their rotations by Weiszfeld iterations on SO(3) (Hartley et al., "L1 rotation averaging
using the Weiszfeld algorithm", CVPR 2011), started at their medoid; its translation the
geometric median of the camera centres' residuals. No scale: the reconstruction is metric.
"""

from __future__ import annotations

import numpy as np

from graspcap.tasks.core.geometry import make_T, transform_points

# scipy: imported where used


def _angles_rad(R: np.ndarray) -> np.ndarray:
    """Rotation angles of (..., 3, 3) rotations."""
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0))


def rotation_median(R: np.ndarray, iterations: int = 50) -> np.ndarray:
    """The geodesic L1 mean (3, 3) of rotations (n, 3, 3): argmin of the sum of angles to
    them, by Weiszfeld steps in the tangent space from the medoid."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    pair = _angles_rad(np.einsum("aji,bjk->abik", R, R))  # angle(R_a^T R_b)
    M = R[int(pair.sum(axis=1).argmin())]
    for _ in range(iterations):
        v = Rotation.from_matrix(np.einsum("ji,njk->nik", M, R)).as_rotvec()  # log(M^T R_i)
        step = _weiszfeld_step(v)
        M = M @ Rotation.from_rotvec(step).as_matrix()
        if np.linalg.norm(step) < 1e-10:
            break
    return M


def _weiszfeld_step(v: np.ndarray, at: float = 1e-12) -> np.ndarray:
    """The Weiszfeld step (d,) from the current point towards samples at offsets ``v`` (n, d),
    with Vardi and Zhang's correction where the point sits on samples (the medoid start):
    the step is shortened by their count over the pull of the others, nil when they hold it."""
    d = np.linalg.norm(v, axis=1)
    on = d < at
    if on.all():
        return np.zeros(v.shape[1])
    w = 1.0 / d[~on]
    pull = (w[:, None] * v[~on]).sum(axis=0)
    r = float(np.linalg.norm(pull))
    return max(0.0, 1.0 - on.sum() / r) * pull / w.sum() if r > 0 else np.zeros(v.shape[1])


def geometric_median(x: np.ndarray, iterations: int = 100) -> np.ndarray:
    """The point (d,) minimising the sum of distances to ``x`` (n, d) (Weiszfeld, from the
    componentwise median)."""
    x = np.asarray(x, dtype=float)
    m = np.median(x, axis=0)
    for _ in range(iterations):
        step = _weiszfeld_step(x - m)
        m = m + step
        if np.linalg.norm(step) < 1e-12:
            break
    return m


def robust_alignment(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """``T_true_est`` (4, 4): the rigid transform from the estimate's world to the truth's
    that best maps the cameras ``T_est`` (n, 4, 4, ``T_w_c`` in the estimate's world) onto
    ``T_true`` (n, 4, 4, the same frames' true cameras) in the L1 sense (module docstring)."""
    T_est, T_true = np.asarray(T_est, float), np.asarray(T_true, float)
    R = rotation_median(np.einsum("nij,nkj->nik", T_true[:, :3, :3], T_est[:, :3, :3]))
    t = geometric_median(T_true[:, :3, 3] - T_est[:, :3, 3] @ R.T)
    return make_T(R, t)


def aligned_errors(T_est: np.ndarray, T_true: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(T_true_est (4, 4), (n, 2) rotation deg / centre distance m of each camera after it)."""
    A = robust_alignment(T_est, T_true)
    moved = np.einsum("ij,njk->nik", A, np.asarray(T_est, float))
    rot = np.degrees(_angles_rad(np.einsum("nji,njk->nik", moved[:, :3, :3],
                                           np.asarray(T_true)[:, :3, :3])))
    trans = np.linalg.norm(moved[:, :3, 3] - np.asarray(T_true)[:, :3, 3], axis=1)
    return A, np.stack([rot, trans], axis=1)


def aligned_mpjpe_mm(joints_est_w: np.ndarray, joints_true_w: np.ndarray,
                     T_true_est: np.ndarray) -> float:
    """Mean joint error (mm) of the estimate's joints (21, 3) mapped by the alignment."""
    moved = transform_points(T_true_est, np.asarray(joints_est_w, float))
    return 1e3 * float(np.linalg.norm(moved - np.asarray(joints_true_w), axis=1).mean())
