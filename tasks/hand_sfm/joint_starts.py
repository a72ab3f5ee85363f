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
from graspcap.tasks.hand.model import SURFACE_OFFSET_M, HandModel, HandSide
from graspcap.tasks.hand_sfm.depth_init import (
    backprojected_joints,
    depth_initialisation,
    median_joints,
)
from graspcap.tasks.hand_sfm.depth_links import DepthLink
from graspcap.tasks.hand_sfm.joint_frames import depth_disagrees, off_smooth_path
from graspcap.tasks.hand_sfm.metric_scale import DepthLookup
from graspcap.tasks.hand_sfm.odometry_init import odometry_initialisation
from graspcap.tasks.hand_sfm.result import HandReconstruction
from graspcap.tasks.hand_sfm.solve import fill_poses

if TYPE_CHECKING:
    from graspcap.tasks.hand_sfm.joint_config import JointSolveConfig


@dataclass(frozen=True)
class Start:
    """A start of the joint solve: each frame's palm in its camera (NaN where unposed), the
    hand's angles and scale, which start it is ("staged", "depth", "chain") and, for the chain,
    the depth registrations that chained its cameras (``DepthLink``, see :func:`chain_links`)."""

    T_c_p: np.ndarray
    angles: np.ndarray
    scale: float
    name: str
    chain: tuple[DepthLink, ...] = ()


def chain_links(start: Start, active: np.ndarray) -> list[DepthLink]:
    """The chain's registrations as links between consecutive ``active`` frames (m,) bool:
    each pair the chain connects gets the relative pose its cameras give and the information
    of the registrations on the chain's path between them (their covariances summed).
    Measured once from rest, these hold the cameras the depth chained wherever the detections
    pull a frame away (a detector's run of wrong frames), where the links registered from the
    current solve (``depth_links``) are dropped for moving it more than
    ``max_correction_deg``."""
    parent = {k.b: (k.a, n) for n, k in enumerate(start.chain)}  # each chained frame's link

    def to_root(i: int) -> list[int]:  # the links from frame i up to the chain's start
        out = []
        while i in parent:
            i, n = parent[i]
            out.append(n)
        return out

    frames = [int(i) for i in np.flatnonzero(active & _chained(start))]
    out = []
    for p, q in zip(frames[:-1], frames[1:], strict=True):
        path = set(to_root(p)) ^ set(to_root(q))  # the links between them
        cov = sum(np.linalg.inv(start.chain[n].information) for n in path)
        out.append(DepthLink(p, q, start.T_c_p[p] @ inv_T(start.T_c_p[q]), np.linalg.inv(cov),
                             max(start.chain[n].rmse_m for n in path),
                             min(start.chain[n].overlap for n in path)))
    return out


def _chained(start: Start) -> np.ndarray:
    """(m,) the frames the start's chain registered (none for a start without a chain)."""
    out = np.zeros(len(start.T_c_p), bool)
    for k in start.chain:
        out[[k.a, k.b]] = True
    return out


def chain_fill(start: Start, T_c_p: np.ndarray, active: np.ndarray) -> np.ndarray:
    """``T_c_p`` (m, 4, 4) with the frames the chain posed but the solve did not (not
    ``active``: no or too few detections, dropped whole) placed by the chained cameras: each
    active chained frame's solved pose differs from its chained one by a palm-side transform
    (one for all frames where the chain and the solve agree), interpolated between the
    neighbouring active frames and applied to the frame's chained camera. Interpolating the
    solved cameras instead (``solve.fill_poses``) misses the motion inside a gap, which the
    depth measured. Other frames are left as they are."""
    chained = _chained(start)
    both = active & chained
    if not both.any():
        return T_c_p
    D = np.full_like(T_c_p, np.nan)
    for a in np.flatnonzero(both):
        D[a] = inv_T(start.T_c_p[a]) @ T_c_p[a]
    D, _ = fill_poses(D)
    out = T_c_p.copy()
    for i in np.flatnonzero(chained & ~active):
        out[i] = start.T_c_p[i] @ D[i]
    return out


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


def _template_fit(side: HandSide, cfg: JointSolveConfig) -> HandFit:
    """The template hand (rest pose, scale 1) as a fit in its own palm frame."""
    model = HandModel(side)
    return fit_hand_stage.fit_hand(model.keypoints(model.rest_angles()), side, cfg.fit)


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
    on the joints triangulated with the chained cameras (rigid, robust), else fitted to them,
    else to the joints the depth readings place (:func:`depth_joints`: a turn of 15-20 deg
    triangulates a far hand's joints to half its size, wild tuning ``[80929, 5]``), else the
    template hand placed on those: the chain's cameras are what this start is for."""
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
    if T_w_p is None:  # the hand fitted to the triangulated joints, else to the depth's
        by_depth = depth_joints(init.T_c_w, uv, readings, K)
        for points_w in (init.points_w, by_depth):
            try:
                fit = _fit_to_points(points_w, side, cfg)
                T_w_p = fit.T_w_p
                break
            except StageError:
                continue
        else:  # else the template hand placed on the depth's joints (the solve finds its size)
            fit = _template_fit(side, cfg)
            T_w_p = place_hand(fit, by_depth, np.all(np.isfinite(by_depth), axis=1))
            if T_w_p is None:
                return None
    return Start(np.einsum("mab,bc->mac", init.T_c_w, T_w_p), fit.angles_rad, fit.scale,
                 "chain", init.chain)


def depth_joints(T_c_w: np.ndarray, uv: np.ndarray, readings: np.ndarray, K: np.ndarray
                 ) -> np.ndarray:
    """(21, 3) each joint's median position over the frames posed in ``T_c_w`` (m, 4, 4) that
    read the depth at its detection (``readings`` (m, 21), skin depth plus the template's
    ``SURFACE_OFFSET_M`` to the joint's centre), NaN where fewer than 2 frames do. No
    parallax needed: the readings are metric."""
    P = backprojected_joints(uv, np.isfinite(readings), K, readings,
                             np.asarray(SURFACE_OFFSET_M, float), 0)
    return median_joints(T_c_w, P, min_frames=2)


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
