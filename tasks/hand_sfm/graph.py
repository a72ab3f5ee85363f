"""GTSAM bundle adjustment of virtual cameras around a static set of joints.

One ``GenericProjectionFactorCal3_S2`` per used observation, its pixel sigma given by the
caller (scaled by detection confidence), optionally under a Huber loss; the gauge is fixed
by a tight prior on one camera and the scale by a tight range prior to a second camera.
GTSAM's Python wheel is built without TBB, so the solve is single-threaded and deterministic.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.geometry import inv_T, project
from graspcap.tasks.hand_sfm.depth_links import DepthLink

# gtsam: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import gtsam

GAUGE_SIGMA = 1e-6
"""Sigma of the gauge priors (pose of the anchor camera, anchor-to-reference distance)."""


@dataclass(frozen=True)
class BundleResult:
    """A solved problem.

    T_c_w : (m, 4, 4) float, NaN for frames left out (too few observations).
    points_w : (21, 3) float, NaN for joints left out (seen in fewer than two frames).
    error_initial, error_final : GTSAM graph error (0.5 * sum of whitened squares, robust).
    iterations : LM iterations.
    """

    T_c_w: np.ndarray
    points_w: np.ndarray
    error_initial: float
    error_final: float
    iterations: int


def lm_params(
    max_iterations: int = 100, relative_tol: float = 1e-7
) -> gtsam.LevenbergMarquardtParams:
    """Levenberg-Marquardt settings used by every GTSAM solve of the project: Ceres' damping
    schedule (initial lambda 1e-4, adaptive lambda factor, diagonal damping). On the hand
    problems GTSAM's own defaults (lambda 1e-5, fixed factor 10) crawl along the weakly
    determined camera tilts: 100 and 64 iterations where these take 74 and 11, to a lower
    error."""
    import gtsam

    params = gtsam.LevenbergMarquardtParams.CeresDefaults()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_tol)
    params.setAbsoluteErrorTol(1e-12)
    params.setVerbosityLM("SILENT")
    return params


def reprojection_residuals(
    K: np.ndarray, T_c_w: np.ndarray, points_w: np.ndarray, uv: np.ndarray
) -> np.ndarray:
    """Pixel distance (m, 21) between ``uv`` (m, 21, 2) and the projections; NaN if unknown."""
    Xc = np.einsum("mab,jb->mja", T_c_w[:, :3, :3], points_w) + T_c_w[:, None, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = project(K, Xc.reshape(-1, 3)).reshape(Xc.shape[0], Xc.shape[1], 2)
        res = np.linalg.norm(proj - uv, axis=2)
        res[Xc[..., 2] <= 0] = np.inf
    res[~np.isfinite(Xc[..., 2])] = np.nan
    return res


def bundle_adjust(
    uv: np.ndarray,
    use: np.ndarray,
    sigma_px: np.ndarray,
    K: np.ndarray,
    T_c_w: np.ndarray,
    points_w: np.ndarray,
    *,
    anchor: int,
    scale_ref: int | None,
    huber_k: float | None,
    range_m: np.ndarray | None = None,
    range_sigma_m: float = 0.003,
    scale_sigma_rel: float | None = None,
    min_observations: int = 4,
    max_iterations: int = 100,
    links: Sequence[DepthLink] = (),
    link_huber_k: float = 3.0,
    relative_tol: float = 1e-7,
) -> BundleResult:
    """Refine poses and joints by Levenberg-Marquardt.

    Parameters
    ----------
    uv : (m, 21, 2) float pixels.
    use : (m, 21) bool, observations that get a factor.
    sigma_px : (m, 21) float, per-observation pixel sigma.
    T_c_w : (m, 4, 4) initial poses (NaN where unknown); points_w : (21, 3) initial joints.
    anchor, scale_ref : frames whose pose (anchor) and distance (anchor to scale_ref) are held;
        ``scale_ref`` None when range measurements fix the scale.
    huber_k : Huber threshold in sigmas, None for a plain Gaussian loss.
    scale_sigma_rel : relative sigma of the anchor-to-``scale_ref`` distance, None for the
        stiff ``GAUGE_SIGMA``. The stiff prior can make Levenberg-Marquardt crawl on a small,
        distant hand; a soft one (1e-3) converges in far fewer iterations when only the
        shape matters.
    range_m : (m, 21) float or None, measured distance from camera centre to joint (from the
        aligned depth), NaN where none; each gets a ``RangeFactor3D`` under a Huber loss.
    links : relative poses of frame pairs from dense depth (``hand_sfm.depth_links``), each a
        ``BetweenFactorPose3`` with the link's information under a Huber loss
        (``link_huber_k`` whitened units); links touching a frame left out are skipped.
    relative_tol : Levenberg-Marquardt stops when an iteration lowers the error by less than
        this share.
    """
    import gtsam
    from gtsam.symbol_shorthand import L, X

    m, nj = use.shape
    posed = np.all(np.isfinite(T_c_w.reshape(m, -1)), axis=1)
    known = np.all(np.isfinite(points_w), axis=1)
    use = use & posed[:, None] & known[None, :]
    frames = use.sum(1) >= min_observations
    held = [anchor] if scale_ref is None else [anchor, scale_ref]
    frames[held] = posed[held]
    use &= frames[:, None]
    joints = use.sum(0) >= 2
    use &= joints[None, :]

    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in np.flatnonzero(frames):
        values.insert(X(i), gtsam.Pose3(inv_T(T_c_w[i])))
    for j in np.flatnonzero(joints):
        values.insert(L(j), gtsam.Point3(*points_w[j]))
    huber = gtsam.noiseModel.mEstimator.Huber.Create(huber_k) if huber_k else None
    for i, j in zip(*np.nonzero(use), strict=True):
        base = gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_px[i, j]))
        noise = gtsam.noiseModel.Robust.Create(huber, base) if huber else base
        graph.add(gtsam.GenericProjectionFactorCal3_S2(uv[i, j], noise, X(i), L(j), cal))
    if range_m is not None:
        range_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(2.0),
            gtsam.noiseModel.Isotropic.Sigma(1, range_sigma_m),
        )
        has_range = use & np.isfinite(range_m)
        for i, j in zip(*np.nonzero(has_range), strict=True):
            graph.add(gtsam.RangeFactor3D(X(i), L(j), float(range_m[i, j]), range_noise))
    huber_link = gtsam.noiseModel.mEstimator.Huber.Create(link_huber_k)
    for link in links:
        if frames[link.a] and frames[link.b]:
            noise = gtsam.noiseModel.Robust.Create(
                huber_link, gtsam.noiseModel.Gaussian.Information(link.information)
            )
            graph.add(
                gtsam.BetweenFactorPose3(X(link.a), X(link.b), gtsam.Pose3(link.T_a_b), noise)
            )
    gauge = gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA)
    graph.add(gtsam.PriorFactorPose3(X(anchor), gtsam.Pose3(inv_T(T_c_w[anchor])), gauge))
    if scale_ref is not None:
        dist = float(np.linalg.norm(inv_T(T_c_w[scale_ref])[:3, 3] - inv_T(T_c_w[anchor])[:3, 3]))
        graph.add(
            gtsam.RangeFactorPose3(
                X(anchor),
                X(scale_ref),
                dist,
                gtsam.noiseModel.Isotropic.Sigma(
                    1, GAUGE_SIGMA if scale_sigma_rel is None else scale_sigma_rel * dist
                ),
            )
        )
    optimizer = gtsam.LevenbergMarquardtOptimizer(
        graph, values, lm_params(max_iterations, relative_tol)
    )
    error_initial = graph.error(values)
    result = optimizer.optimize()

    T_out = np.full((m, 4, 4), np.nan)
    for i in np.flatnonzero(frames):
        T_out[i] = inv_T(result.atPose3(X(i)).matrix())
    P_out = np.full((nj, 3), np.nan)
    for j in np.flatnonzero(joints):
        P_out[j] = result.atPoint3(L(j))
    return BundleResult(
        T_out, P_out, float(error_initial), float(graph.error(result)), optimizer.iterations()
    )
