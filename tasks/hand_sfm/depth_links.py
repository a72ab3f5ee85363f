"""Dense depth links between virtual cameras: point-to-plane ICP of the hand and held object.

A hand ~0.15 m across seen from 0.35-0.6 m pins each camera's tilt only to about a degree
from 21 keypoints (rotation about an axis in the image plane and a sideways translation
move the keypoints almost alike), and the skin readings at the keypoints carry a per-joint
bias of several millimetres (the ray hits a neighbouring finger or the skin off the joint
centre). The aligned depth of the whole static hand and the object it holds is a rigid
surface thousands of pixels large: registering one frame's surface onto another's
(point-to-plane ICP, Huber-weighted) measures their relative pose to about 0.1 deg, and no
surface offset model enters it.

Each accepted registration becomes a *link*: the relative pose ``T_a_b`` of two solve frames
with a 6x6 information matrix (tangent order rotation, translation, right perturbation of
``T_a_b`` as GTSAM's ``Pose3``) that ``hand_sfm.graph.bundle_adjust`` adds as a
``BetweenFactorPose3``. The information is the point-to-plane Gauss-Newton Hessian, scaled
down to ``effective_points`` independent points (neighbouring depth pixels share their
errors: sensor smoothing, the reference frame's own noise, surface sampling).

The surfaces registered are ``hand_sfm.surface_clouds``'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.core.threads import thread_budget
from graspcap.tasks.hand_sfm.surface_clouds import SurfaceCloud

# scipy: imported where used, so that importing the stage table stays cheap


class DepthLinkConfig(StageConfig):
    """Dense depth links of ``reconstruct_hand`` (part of its config)."""

    enabled: bool = True
    """Register the frames' depth of the hand and held object and add the relative poses to
    the final solve (needs the depth frames)."""
    reference: int = 5
    """Solve frame (counted from the steady frame) every other frame is registered onto: a
    few frames in, so that it is steady even when the onset was detected a little early (the
    first frame after it with a pose and a surface when it has none)."""
    rounds: int = 2
    """Registrations from the first RGB-D solve, then again from the solve they improved."""
    radius_m: float = 0.15
    """Radius around the hand's centre of the surface registered."""
    centre_below_skin_m: float = 0.01
    """The hand's centre lies this far behind the median skin reading at its keypoints."""
    stride_px: int = 3
    """Every this many pixels of the depth are sampled (rows and columns), at most: see
    ``spacing_m``."""
    spacing_m: float | None = 0.0025
    """The lattice is refined (down to every pixel) for its nodes to lie about this far
    apart at the hand's depth (``surface_clouds.surface_cloud``; None: ``stride_px`` at
    every distance)."""
    min_height_m: float = 0.015
    """Points less than this above the platter's top plane are the static scene."""
    max_points: int = 300
    """At most this many points of a frame are moved onto another (an even subsample)."""
    max_distance_m: float = 0.01
    """Farthest correspondence of an ICP iteration."""
    huber_m: float = 0.003
    """Huber threshold of the point-to-plane residuals."""
    iterations: int = 12
    """Most Gauss-Newton iterations of one registration."""
    sigma_m: float = 0.0015
    """Sigma of one point-to-plane residual."""
    effective_points: float = 300.0
    """A registration's information is that of at most this many independent points."""
    min_overlap: float = 0.5
    """Least share of a frame's surface that must find the other frame's."""
    max_rmse_m: float = 0.004
    """Largest RMS residual of an accepted registration."""
    max_correction_deg: float = 5.0
    """Largest rotation an accepted registration may apply to the keypoint solve."""
    max_correction_m: float = 0.03
    """Largest translation an accepted registration may apply to the keypoint solve."""
    consecutive_from_rest: bool = False
    """Register each frame onto its predecessor from no motion (identity) instead of from
    the keypoint solve's relative pose, and accept it by the motion it finds (at most
    ``max_step_*``) instead of by its correction: neighbouring frames move a few degrees, so
    the registration needs no keypoints, and a keypoint solve of a real detector's
    detections (errors of 5-10 % of the hand's size) is off by more than
    ``max_correction_deg`` (rig real-detector sessions: 6-35 deg); these links then chain
    the cameras."""
    max_step_deg: float = 25.0
    """Largest rotation between neighbouring frames a registration from rest may find (the
    rig's wild motion turns up to 7 deg per frame; with frames skipped, 20)."""
    max_step_m: float = 0.3
    """Largest translation between neighbouring frames a registration from rest may find (a
    turn about the hand moves the camera: 20 deg at 0.8 m is 0.28 m)."""
    threads: int = 2
    """The pairs are registered in two fixed halves (each pair's ICP is independent of the
    others); with 2 the second half runs on a second thread while the first runs on this
    one (numpy releases the GIL in the batched products), with 1 after it. The same links
    either way."""


@dataclass(frozen=True)
class DepthLink:
    """A relative pose between solve frames ``a`` and ``b`` measured by ICP.

    T_a_b : (4, 4) maps camera ``b`` into camera ``a``.
    information : (6, 6) inverse covariance, tangent order (rotation, translation).
    rmse_m : RMS point-to-plane residual of the inliers; overlap : share of source points
        with a correspondence.
    """

    a: int
    b: int
    T_a_b: np.ndarray
    information: np.ndarray
    rmse_m: float
    overlap: float


def _exp_batch(step: np.ndarray) -> np.ndarray:
    """(k, 4, 4) transforms of (k, 6) steps (rotation vector, translation)."""
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (len(step), 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(step[:, :3]).as_matrix()
    T[:, :3, 3] = step[:, 3:]
    return T


def _even(points: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` of ``points`` (n, 3), evenly spread over their order."""
    if len(points) <= max_points:
        return points
    return points[np.linspace(0, len(points) - 1, max_points).round().astype(int)]


def icp_batch(
    clouds: Sequence[SurfaceCloud],
    pairs: np.ndarray,
    T_a_b: np.ndarray,
    K: np.ndarray,
    *,
    max_points: int,
    max_distance_m: float,
    huber_m: float,
    iterations: int,
    sigma_m: float,
    effective_points: float,
    prior_rad: float = np.radians(2.0),
    prior_m: float = 0.01,
    damping: float = 1e-3,
    max_step_rad: float = np.radians(2.0),
    max_step_m: float = 0.01,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Point-to-plane ICP of many frame pairs at once: cloud ``b`` onto cloud ``a``.

    Gauss-Newton on Huber-weighted point-to-plane residuals with projective data association
    (each source point, moved into camera ``a``, is paired with the target's lattice node
    at its pixel when that lies within ``max_distance_m``), re-found each iteration;
    Levenberg damping ``damping`` and steps clamped to ``max_step_*``. ``K`` (3, 3) is the
    camera of every cloud. A Gaussian prior (sigmas ``prior_rad``, ``prior_m``) holds the
    pose near its start where the surface leaves it free (a rotation about the optical axis
    of faces turned to the camera, a slide along a cylinder); the returned information is
    that of the surface alone.

    Parameters
    ----------
    clouds : the frames' surfaces.
    pairs : (k, 2) int, indices (a, b) into ``clouds``.
    T_a_b : (k, 4, 4) initial relative poses (cloud b into cloud a).
    max_points : at most this many points of each source cloud (an even subsample).

    Returns
    -------
    T_a_b : (k, 4, 4) refined; information : (k, 6, 6) (rotation, translation; the
    Gauss-Newton Hessian over ``sigma_m``^2, scaled down to ``effective_points``);
    rmse_m : (k,) RMS residual of the points within 3 Huber widths; overlap : (k,) share
    of source points with a correspondence.
    """
    from scipy.spatial.transform import Rotation

    k = len(pairs)
    shape = np.array([c.index.shape for c in clouds])
    grid_base = np.concatenate([[0], np.cumsum(shape[:, 0] * shape[:, 1])])[:-1]
    point_base = np.concatenate([[0], np.cumsum([len(c.points) for c in clouds])])[:-1]
    index = np.concatenate(
        [np.where(c.index >= 0, c.index + b, -1).ravel() for c, b in zip(clouds, point_base,
                                                                         strict=True)]
    )
    surface = np.concatenate([np.hstack([c.points, c.normals]) for c in clouds])
    # every pair's source points in one padded (k, P, 3) block: per-pair products are then
    # batched matrix products instead of per-point gathers and sparse sums
    src = [_even(clouds[b].points, max_points) for b in pairs[:, 1]]
    P = max(len(s) for s in src)
    p = np.zeros((k, P, 3))
    valid = np.zeros((k, P), bool)
    for n, s in enumerate(src):
        p[n, : len(s)], valid[n, : len(s)] = s, True
    total = valid.sum(1).astype(float)
    tgt = pairs[:, 0]
    t_first = np.array([clouds[a].first_px for a in tgt], dtype=float)[:, None, :]
    t_stride = np.array([clouds[a].stride_px for a in tgt], dtype=float)[:, None, None]
    t_shape, t_base = shape[tgt][:, None, :], grid_base[tgt][:, None]
    f, c0 = np.array([K[0, 0], K[1, 1]]), np.array([K[0, 2], K[1, 2]])
    T = np.array(T_a_b, dtype=float)
    T0_inv = np.stack([inv_T(X) for X in T])
    prior = np.diag([prior_rad**-2] * 3 + [prior_m**-2] * 3) * sigma_m**2  # in residual units
    H = np.zeros((k, 6, 6))
    rmse = np.full(k, np.inf)
    used = np.zeros(k)
    active = np.ones(k, bool)
    for _ in range(iterations):
        R = T[:, :3, :3]
        moved = p @ R.transpose(0, 2, 1) + T[:, None, :3, 3]
        with np.errstate(invalid="ignore", divide="ignore"):
            node = np.rint(((moved[..., :2] / moved[..., 2:]) * f + c0 - t_first) / t_stride)
            ok = valid & (moved[..., 2] > 0) & np.all((node >= 0) & (node < t_shape[..., ::-1]),
                                                      axis=2)  # fmt: skip
        row = np.full((k, P), -1)
        flat = (t_base + node[..., 1] * t_shape[..., 1] + node[..., 0])[ok]
        row[ok] = index[flat.astype(np.int64)]
        ok &= row >= 0
        qn = np.take(surface, row, axis=0)  # row -1 (not ok) reads a real point, weighted 0
        q, nq = qn[..., :3], qn[..., 3:]
        d = moved - q
        ok &= np.einsum("kpi,kpi->kp", d, d) < max_distance_m**2
        r = np.where(ok, np.einsum("kpi,kpi->kp", nq, d), 0.0)
        a = np.abs(r)
        wgt = np.where(ok, np.where(a <= huber_m, 1.0, huber_m / np.maximum(a, 1e-12)), 0.0)
        m = nq @ R  # target normal in the source frame
        J = np.empty((k, P, 6))
        J[..., 0] = p[..., 1] * m[..., 2] - p[..., 2] * m[..., 1]  # p x m
        J[..., 1] = p[..., 2] * m[..., 0] - p[..., 0] * m[..., 2]
        J[..., 2] = p[..., 0] * m[..., 1] - p[..., 1] * m[..., 0]
        J[..., 3:] = m
        Jw = J * wgt[..., None]
        H = Jw.transpose(0, 2, 1) @ J
        g = np.einsum("kpi,kp->ki", Jw, r)
        used = ok.sum(1).astype(float)
        inl = ok & (a <= 3 * huber_m)
        with np.errstate(invalid="ignore", divide="ignore"):
            rmse = np.sqrt(np.sum(r**2 * inl, axis=1) / inl.sum(1))
        active &= used >= 12
        D = T0_inv @ T
        delta = np.concatenate([Rotation.from_matrix(D[:, :3, :3]).as_rotvec(), D[:, :3, 3]], 1)
        A = H + prior + damping * H * np.eye(6)
        step = -np.linalg.solve(A, (g + delta @ prior)[:, :, None])[:, :, 0]
        step[~active] = 0.0
        big = np.maximum(
            np.linalg.norm(step[:, :3], axis=1) / max_step_rad,
            np.linalg.norm(step[:, 3:], axis=1) / max_step_m,
        )
        step /= np.maximum(big, 1.0)[:, None]
        T = T @ _exp_batch(step)
        if np.all(np.linalg.norm(step[:, :3], axis=1) < 1e-6) and np.all(
            np.linalg.norm(step[:, 3:], axis=1) < 1e-7
        ):
            break
    scale = np.minimum(1.0, effective_points / np.maximum(used, 1.0)) / sigma_m**2
    info = H * scale[:, None, None]
    info[~active] = 0.0
    rmse[~active] = np.inf
    return T, info, rmse, used / np.maximum(total, 1.0)


def depth_links(
    surfaces: Sequence[SurfaceCloud | None],
    T_c_w: np.ndarray,
    K: np.ndarray,
    config: DepthLinkConfig,
) -> list[DepthLink]:
    """ICP links of every posed solve frame to the reference frame and to its predecessor.

    Parameters
    ----------
    surfaces : (m) each solve frame's surface, None where it has none.
    T_c_w : (m, 4, 4) current poses (NaN rows for unposed frames), initialising the ICP.
    K : (3, 3) colour (and aligned depth) intrinsics.

    A registration is kept when it overlaps by ``min_overlap``, fits within ``max_rmse_m``
    and moves the initial relative pose by at most ``max_correction_*`` (a larger change is
    a wrong basin, not a refinement of a keypoint solve); with ``consecutive_from_rest`` a
    frame registered onto its predecessor starts from no motion and may find up to
    ``max_step_*``.
    """
    cfg = config
    m = len(T_c_w)
    posed = np.all(np.isfinite(T_c_w.reshape(m, -1)), axis=1)
    have = np.array([i for i in range(m) if posed[i] and surfaces[i] is not None], dtype=int)
    if len(have) < 2:
        return []
    # the first frame with a pose and a surface from the configured one on (a frame without
    # detections there would otherwise leave the whole solve without links)
    later = have[have >= min(cfg.reference, m - 1)]
    reference = int(later[0] if len(later) else have[-1])
    pairs = {(reference, int(i)) for i in have if i != reference}
    pairs |= {(int(a), int(b)) for a, b in zip(have[:-1], have[1:], strict=True)
              if (b, a) not in pairs}  # the reference's predecessor is linked once
    ab = np.array(sorted(pairs))
    node = np.full(m, -1)
    node[have] = np.arange(len(have))
    T0 = np.einsum("nij,njk->nik", T_c_w[ab[:, 0]], np.stack([inv_T(T_c_w[b]) for b in ab[:, 1]]))
    successor = {int(a): int(b) for a, b in zip(have[:-1], have[1:], strict=True)}
    from_rest = np.array([cfg.consecutive_from_rest and successor.get(int(a)) == int(b)
                          and a != reference for a, b in ab], dtype=bool)  # fmt: skip
    T0[from_rest] = np.eye(4)
    clouds = [surfaces[i] for i in have]

    def register(idx: np.ndarray) -> tuple[np.ndarray, ...]:
        return icp_batch(
            clouds, node[ab[idx]], T0[idx], K, max_points=cfg.max_points,
            max_distance_m=cfg.max_distance_m, huber_m=cfg.huber_m, iterations=cfg.iterations,
            sigma_m=cfg.sigma_m, effective_points=cfg.effective_points,
        )  # fmt: skip

    halves = np.array_split(np.arange(len(ab)), 2)
    if thread_budget(cfg.threads) > 1 and len(halves[1]):
        with ThreadPoolExecutor(max_workers=1) as pool:
            second = pool.submit(register, halves[1])
            first = register(halves[0])
            parts = [first, second.result()]
    else:
        parts = [register(h) for h in halves if len(h)]
    T, info, rmse, overlap = (np.concatenate(x) for x in zip(*parts, strict=True))
    links = []
    for n, (a, b) in enumerate(ab):
        dT = inv_T(T0[n]) @ T[n]
        angle = np.degrees(np.arccos(np.clip((np.trace(dT[:3, :3]) - 1) / 2, -1, 1)))
        max_deg, max_m = ((cfg.max_step_deg, cfg.max_step_m) if from_rest[n]
                          else (cfg.max_correction_deg, cfg.max_correction_m))  # fmt: skip
        if (
            overlap[n] >= cfg.min_overlap
            and rmse[n] <= cfg.max_rmse_m
            and angle <= max_deg
            and np.linalg.norm(dT[:3, 3]) <= max_m
        ):
            links.append(DepthLink(int(a), int(b), T[n], info[n], float(rmse[n]), overlap[n]))
    return links
