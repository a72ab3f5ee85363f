"""Where ``joint_solve`` starts: the staged solution, the depth (``hand_sfm.depth_init``), or,
on noisy detections, the cameras chained by the depth surfaces (``hand_sfm.odometry_init``)
with the staged hand placed on the joints they triangulate (``JointSolveConfig.chain_start``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, transform_points, umeyama
from graspcap.tasks.hand import fit_hand as fit_hand_stage
from graspcap.tasks.hand.fit_hand import HandFit
from graspcap.tasks.hand.model import SURFACE_OFFSET_M, HandSide
from graspcap.tasks.hand_sfm.depth_init import depth_initialisation
from graspcap.tasks.hand_sfm.joint_frames import depth_disagrees, off_smooth_path
from graspcap.tasks.hand_sfm.metric_scale import DepthLookup
from graspcap.tasks.hand_sfm.odometry_init import odometry_initialisation
from graspcap.tasks.hand_sfm.result import HandReconstruction

if TYPE_CHECKING:
    from graspcap.tasks.hand_sfm.joint_solve import JointSolveConfig


@dataclass(frozen=True)
class Start:
    """A start of the joint solve: each frame's palm in its camera (NaN where unposed), the
    hand's angles and scale, and which start it is ("staged", "depth", "chain")."""

    T_c_p: np.ndarray
    angles: np.ndarray
    scale: float
    name: str


def staged_start(rec: HandReconstruction, fit: HandFit) -> Start:
    """The staged solution's cameras and hand."""
    T_c_p = np.full((len(rec.frames), 4, 4), np.nan)
    for i in np.flatnonzero(rec.pose_valid):
        T_c_p[i] = inv_T(rec.T_w_c[i]) @ fit.T_w_p
    return Start(T_c_p, fit.angles_rad, fit.scale, "staged")


def _fit_to_points(points_w: np.ndarray, side: HandSide, cfg: JointSolveConfig) -> HandFit:
    """The hand fitted to an initialisation's joints (NaN: not triangulated, weight 0)."""
    known = np.all(np.isfinite(points_w), axis=1)
    return fit_hand_stage.fit_hand(np.where(known[:, None], points_w, 0.0), side, cfg.fit,
                                   weights=known.astype(float))


def depth_start(uv, ok, K, readings, steady_from, side, cfg) -> Start | str:
    """The start from the depth, or why there is none: ``hand_sfm.depth_init`` from each of
    up to ``start_references`` reference frames (spread over those with the most readings),
    the hand fitted to its joints; the start that the most frames agree with (the frame
    tests: depth agreement and the smooth turn) wins. A reference on another hand, or
    before the hand settled, poses few frames that agree."""
    offset = np.asarray(SURFACE_OFFSET_M)
    n = np.isfinite(readings).sum(1)
    rich = np.flatnonzero(n >= cfg.min_points_per_frame)
    if not len(rich):
        return "no frame has depth readings at enough detected joints"
    picks = rich[np.unique(np.linspace(0, len(rich) - 1, cfg.start_references).round()
                           .astype(int))]
    best: tuple[int, Start] | None = None
    why = "the depth initialisation posed fewer than two frames"
    for ref in picks:
        init = depth_initialisation(uv, ok, K, readings, offset, steady_from,
                                    ransac_px=cfg.ransac_px, min_points=cfg.min_points_per_frame,
                                    reference=int(ref))
        if init is None:
            continue
        try:
            fit = _fit_to_points(init.points_w, side, cfg)
        except StageError as exc:
            why = f"the hand fitted to the depth initialisation's joints: {exc.reason}"
            continue
        T_c_p = np.einsum("mab,bc->mac", init.T_c_w, fit.T_w_p)
        posed = np.all(np.isfinite(T_c_p.reshape(len(T_c_p), -1)), axis=1)
        J = fit.joints_fit_w @ fit.T_w_p[:3, :3] - fit.T_w_p[:3, 3] @ fit.T_w_p[:3, :3]
        agree = posed & ~depth_disagrees(T_c_p, J, fit.scale * offset, readings, cfg)
        agree &= ~off_smooth_path(T_c_p, agree, cfg)
        score = int(agree.sum())
        if best is None or score > best[0]:
            best = (score, Start(T_c_p, fit.angles_rad, fit.scale, "depth"))
    return why if best is None else best[1]


def chain_start(
    surfaces: list, surface_at: Callable[[int, np.ndarray, np.ndarray], Any], uv: np.ndarray,
    ok: np.ndarray, confident: np.ndarray, readings: np.ndarray, K: np.ndarray, side: HandSide,
    cfg: JointSolveConfig, usable: int, fit: HandFit | None,
) -> Start | None:
    """The start from the cameras chained by the depth surfaces (``chain_start``), or None
    where no frame has a surface, or the chain poses fewer than ``chain_min_share`` of the
    ``usable`` frames. ``surfaces`` are the frames' own (None without); the chain also runs
    through frames without one (a detector's runs of missed frames would break it), each
    cropped by ``surface_at`` around its nearest detected neighbour's ``confident`` readings.
    The hand is the staged ``fit``'s (its articulation from every frame's detections) placed
    on the joints triangulated with the chained cameras (rigid, robust), else fitted to them."""
    own = np.array([i for i, s in enumerate(surfaces) if s is not None], dtype=int)
    if not len(own):
        return None
    chain_surfaces = list(surfaces)
    for i in np.setdiff1d(np.arange(len(surfaces)), own):
        j = int(own[np.argmin(np.abs(own - i))])
        chain_surfaces[i] = surface_at(int(i), uv[j, confident[j]], readings[j, confident[j]])
    init = odometry_initialisation(chain_surfaces, uv, ok, K, cfg.depth_links,
                                   ransac_px=cfg.ransac_px, min_points=cfg.min_points_per_frame,
                                   min_frames=max(cfg.min_frames,
                                                  int(np.ceil(cfg.chain_min_share * usable))))
    if init is None:
        return None
    T_w_p = None if fit is None else place_hand(
        fit, init.points_w, np.all(np.isfinite(init.points_w), axis=1))
    if T_w_p is None:
        try:
            fit = _fit_to_points(init.points_w, side, cfg)
        except StageError:
            return None
        T_w_p = fit.T_w_p
    return Start(np.einsum("mab,bc->mac", init.T_c_w, T_w_p), fit.angles_rad, fit.scale,
                 "chain")


def place_hand(fit: HandFit, points_w: np.ndarray, known: np.ndarray) -> np.ndarray | None:
    """T_w_p placing ``fit``'s hand (its joints in its palm frame) on ``points_w`` (rigid
    Umeyama over the ``known`` joints, refitted once without those beyond twice the median
    distance); None with fewer than 4 known joints."""
    J_p = transform_points(inv_T(fit.T_w_p), fit.joints_fit_w)
    use = known.copy()
    T = None
    for _ in range(2):
        if use.sum() < 4:
            return T
        T, _ = umeyama(J_p[use], points_w[use], with_scale=False)
        d = np.linalg.norm(transform_points(T, J_p) - points_w, axis=1)
        use = known & (d <= 2.0 * np.median(d[known]))
    return T


def depth_readings(depth_at: DepthLookup, uv, ok, conf, steady_from, min_conf) -> np.ndarray:
    """Depth (m, 21) at the confident detections (NaN elsewhere or without a reading)."""
    sample = ok & (conf >= min_conf)
    out = np.full(ok.shape, np.nan)
    for i in np.flatnonzero(sample.any(1)):
        d = np.asarray(depth_at(steady_from + int(i), uv[i, sample[i]]), dtype=float)
        out[i, sample[i]] = np.where(np.isfinite(d) & (d > 0), d, np.nan)
    return out


__all__ = ["Start", "chain_start", "depth_readings", "depth_start", "place_hand",
           "staged_start"]
