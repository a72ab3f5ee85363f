"""The ``joint_solve`` stage: the hand model inside structure from motion (the paper's Eq. 2).

The staged path solves 21 free 3D points and the virtual cameras (``reconstruct_hand``), then
fits the 20-DoF hand to those points (``fit_hand``). Here the cameras, the 20 joint angles,
the hand's shape (per-bone length factors) and its metric scale are solved together against
the 2D detections (``hand_sfm.hand_graph``): the kinematic structure itself rejects what no
hand could produce, a robust loss takes a swapped finger, and frames whose detections no
pose of the hand explains (a detection on another hand, mirrored, somewhere else) are dropped
as whole frames before the solve is repeated. The range readings of the aligned depth at the
keypoints fix the metric scale, as in ``reconstruct_hand``, but one-sided: a reading is the
first surface on its ray, the skin or something in front of it (the held object, another
finger), so readings in front of the solved skin count ``range_front_weight`` times
(joint_solve/12; with symmetric residuals such readings pulled whole wild reconstructions 2-4 %
towards the camera).

It starts from the staged solution when the staged path succeeds, else from the depth
(``hand_sfm.depth_init``, the hand fitted to its backprojected joints); on noisy detections the
start's cameras are the depth surfaces' chain (``chain_start``), and the chain stays: its
registrations link the solved frames in every round (``joint_starts.chain_links``), the frames
the solve leaves unposed take its cameras (``joint_starts.chain_fill``), and the detections'
sigma follows the solve's residuals (``sigma_from_residuals``). ``mode`` says what the
stage returns: ``off`` nothing (``reconstruct_hand`` and ``fit_hand`` run the staged path),
``fallback`` the staged result where it succeeds and the joint solve where it fails,
``auto`` the staged result where its detections are clean (measured noise at most
``auto_noise_share`` of the hand's image size) and the joint solve where they are noisy or the
staged path fails, ``always`` the joint solve (from the staged start where there is one).
With a result, ``reconstruct_hand`` and ``fit_hand`` pass on its ``reconstruction`` and
``fit``, so every stage downstream (cross-check, adjustment, poses, QA, pictures, catalog rows)
reads the same types as from the staged path.

Where the joint solve ran from noisy detections (the staged result did not stand clean), its
final hand is refined against the hand's own depth fused over the kept frames, the cameras
held (``hand_sfm.hand_depth``, ``depth_refine``); the refined hand is the result's
(``joints_w``, the fit's pose, scale and angles, the residuals) and ``JointSolve.depth_refine``
records what the step did.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.hand import fit_hand as fit_hand_stage
from graspcap.tasks.hand.fit_hand import HandFit
from graspcap.tasks.hand.model import RIGID_PALM_POINTS, SURFACE_OFFSET_M, HandSide
from graspcap.tasks.hand_sfm import reconstruct_hand as reconstruct_stage
from graspcap.tasks.hand_sfm.depth_links import depth_links
from graspcap.tasks.hand_sfm.hand_depth import (
    DepthRefineReport,
    refine_solved_hand,
)
from graspcap.tasks.hand_sfm.hand_graph import (
    GraphSolve,
    HandKinematics,
    HandPriors,
    solve_graph,
)
from graspcap.tasks.hand_sfm.joint_config import HandPath, JointSolveConfig
from graspcap.tasks.hand_sfm.joint_frames import (
    depth_disagrees,
    frame_medians,
    frames_to_drop,
    off_smooth_path,
    residuals_px,
)
from graspcap.tasks.hand_sfm.joint_starts import (
    chain_fill,
    chain_links,
    chain_start,
    depth_readings,
    depth_start,
    staged_start,
)
from graspcap.tasks.hand_sfm.metric_scale import DepthLookup, depth_lookup_from_frames
from graspcap.tasks.hand_sfm.reconstruct_hand import ReconstructConfig
from graspcap.tasks.hand_sfm.result import HandReconstruction, SfmDiagnostics
from graspcap.tasks.hand_sfm.solve import fill_poses, rotation_span_deg
from graspcap.tasks.hand_sfm.surface_clouds import DepthFrame, surface_reader
from graspcap.tasks.hand_sfm.two_view_init import pnp, ray_angles_deg

# gtsam: imported where used, so that importing the stage table stays cheap

MEDIAN_PER_AXIS = float(np.sqrt(2 * np.log(2)))
"""The median length of a 2-D residual of per-axis sigma 1 (Rayleigh)."""

STAGE = "joint_solve"
STAGE_VERSION = "joint_solve/12"


PRESETS: dict[str, JointSolveConfig] = {
    "default": JointSolveConfig(),
    "staged": JointSolveConfig(mode=HandPath.OFF),
    "paper": JointSolveConfig(mode=HandPath.OFF),
    "joint": JointSolveConfig(mode=HandPath.ALWAYS),
    "joint_fallback": JointSolveConfig(mode=HandPath.FALLBACK),
}


@dataclass(frozen=True)
class JointSolve:
    """The stage's result.

    reconstruction, fit : what ``reconstruct_hand`` and ``fit_hand`` pass on (same types as
        the staged path; from the joint solve ``joints_w`` are the model's keypoints, so
        ``joints_fit_w`` equals them, and ``fit.residual_mm`` is each joint's RMS distance
        from the rays of its inlier detections).
    path : "staged" or "joint", which gave the result; start : "staged" or "depth", where the
        joint solve started (empty for a staged result).
    staged_error : why the staged path failed (empty when it succeeded).
    bone_scale : (20,) per-bone length factors (``SKELETON`` order) on top of ``fit.scale``;
        ones for a staged result.
    frame_rejected : (m,) bool, frames dropped whole (detections no hand pose explains).
    frame_median_px : (m,) each frame's median residual at the last solve it was in (NaN
        where never solved).
    rounds, iterations : solve rounds and the LM iterations of the last.
    depth_refine : what the depth refinement did (``hand_sfm.hand_depth.DepthRefineReport``;
        None where it did not run: a staged result, clean detections, disabled, no depth).
    """

    reconstruction: HandReconstruction
    fit: HandFit
    path: str
    start: str
    staged_error: str
    bone_scale: np.ndarray
    frame_rejected: np.ndarray
    frame_median_px: np.ndarray
    rounds: int
    iterations: int
    depth_refine: DepthRefineReport | None = None


def joint_solve(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int,
    depth_at: DepthLookup | np.ndarray,
    side: HandSide,
    config: JointSolveConfig = PRESETS["default"],
    *,
    depth_frame: DepthFrame | None = None,
    T_color_turntable: np.ndarray | None = None,
    why_missing: str = "",
) -> JointSolve | None:
    """Cameras, hand pose and shape from ``steady_from`` on; None with ``mode = off``.

    keypoints : (n, 21, 3) ideal pixels and confidence per video frame (0 = missed); K : (3, 3);
    depth_at : a ``DepthLookup`` or the aligned depth frames (n, h, w) in metres;
    side : the session's hand. ``depth_frame``, ``T_color_turntable`` and ``why_missing`` go
    to the staged ``reconstruct_hand`` (see there).
    Raises ``StageError`` when neither path gives a hand (naming both reasons).
    """
    cfg = config
    if cfg.mode is HandPath.OFF:
        return None
    if not callable(depth_at):
        frames_m = np.asarray(depth_at)
        depth_frame = depth_frame or (lambda i: frames_m[i])
        depth_at = depth_lookup_from_frames(frames_m)
    K = np.asarray(K, dtype=float)
    side = HandSide(side)

    def staged(config: ReconstructConfig) -> tuple[HandReconstruction, HandFit] | str:
        try:
            rec = reconstruct_stage.reconstruct_hand(
                keypoints, K, steady_from, depth_at, np.asarray(SURFACE_OFFSET_M), config,
                depth_frame=depth_frame, T_color_turntable=T_color_turntable,
                why_missing=why_missing,
            )  # fmt: skip
            return rec, fit_hand_stage.fit_hand(rec.joints_w, side, cfg.fit)
        except StageError as exc:
            return str(exc)

    surface_at = None
    link_cfg = cfg.depth_links
    if link_cfg.enabled and depth_frame is not None and T_color_turntable is not None:
        surface_at = surface_reader(
            depth_frame, K, steady_from, T_color_turntable,
            centre_below_skin_m=link_cfg.centre_below_skin_m, radius_m=link_cfg.radius_m,
            stride_px=link_cfg.stride_px, min_height_m=link_cfg.min_height_m,
            spacing_m=link_cfg.spacing_m,
        )

    def solve(rec=None, fit=None, staged_error=""):
        """The joint solve; where it fails from the depth chain's start, once more from the
        start it would have had without it (a chain that slid can leave no depth reading
        agreeing with the hand it places)."""
        args = (keypoints, K, steady_from, depth_at, side)
        extra = {"depth_frame": depth_frame, "T_color_turntable": T_color_turntable}
        try:
            return solve_from_start(*args, cfg, rec, fit, staged_error, surface_at, **extra)
        except StageError as chained:
            if not cfg.chain_start:
                raise
            unchained = cfg.model_copy(update={"chain_start": False})
            try:
                return solve_from_start(*args, unchained, rec, fit, staged_error, surface_at,
                                        **extra)
            except StageError as exc:  # both reasons (the chain's was hidden), the staged once
                last, _, tail = exc.reason.partition("; the staged path: ")
                first = chained.reason.partition("; the staged path: ")[0]
                if first == last:  # no chain start: the same start failed twice
                    raise
                staged_part = f"; the staged path: {tail}" if tail else ""
                raise StageError(STAGE, f"{last}; from the depth chain's start: {first}"
                                        f"{staged_part}") from exc

    found = staged(cfg.staged)
    if isinstance(found, str):  # the joint solve starts from the depth
        return solve(staged_error=found)
    rec, fit = found
    diag = rec.diagnostics
    if cfg.mode is HandPath.FALLBACK or (cfg.mode is HandPath.AUTO and not noisy(
            diag.noise_sigma_px, diag.hand_size_px, cfg.auto_noise_share)):
        m = len(rec.frames)
        return JointSolve(rec, fit, "staged", "", "", np.ones(20), np.zeros(m, bool),
                          np.full(m, np.nan), 0, 0)
    return solve(rec, fit)


def noisy(sigma_px: float, hand_px: float, share: float) -> bool:
    """Whether a measured detection noise ``sigma_px`` exceeds ``share`` of the hand's image
    size ``hand_px`` (unmeasured noise or size counts as clean: the staged result stands)."""
    return bool(np.isfinite(sigma_px) and np.isfinite(hand_px) and hand_px > 0
                and sigma_px > share * hand_px)


def solve_from_start(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int,
    depth_at: DepthLookup,
    side: HandSide,
    cfg: JointSolveConfig,
    rec: HandReconstruction | None = None,
    fit: HandFit | None = None,
    staged_error: str = "",
    surface_at: Callable[[int, np.ndarray, np.ndarray], Any] | None = None,
    *,
    depth_frame: DepthFrame | None = None,
    T_color_turntable: np.ndarray | None = None,
) -> JointSolve:
    """The joint solve from the staged solution (``rec``, ``fit``) or, without it, from the
    depth; whole-frame rejection rounds; the result in the staged path's types.
    ``surface_at(i, uv, depth) -> SurfaceCloud | None`` gives solve frame i's surface for the
    dense depth links (None: no links). ``depth_frame(video frame) -> (h, w)`` metres (and
    ``T_color_turntable``, which drops the platter) feed ``depth_refine`` (none without)."""
    import gtsam

    kp = np.asarray(keypoints, dtype=float)[steady_from:]
    m = len(kp)
    uv, conf = kp[..., :2], kp[..., 2]
    ok = (conf >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)

    def fail(reason: str) -> StageError:
        staged = f"; the staged path: {staged_error}" if staged_error else ""
        return StageError(STAGE, reason + staged)

    usable = ok.sum(1) >= cfg.min_points_per_frame
    if int(usable.sum()) < cfg.min_frames:
        raise fail(f"too few usable frames: fewer than {cfg.min_frames} frames from "
                   f"{steady_from} on have >= {cfg.min_points_per_frame} detected joints")
    readings = depth_readings(depth_at, uv, ok, conf, steady_from, cfg.depth_min_confidence)
    surfaces: list = [None] * m
    confident = ok & (conf >= cfg.depth_min_confidence) & np.isfinite(readings)
    if surface_at is not None:
        for i in np.flatnonzero(usable & confident.any(1)):
            surfaces[i] = surface_at(int(i), uv[i, confident[i]], readings[i, confident[i]])
    chained = None
    clean = rec is not None and not noisy(rec.diagnostics.noise_sigma_px,
                                          rec.diagnostics.hand_size_px, cfg.auto_noise_share)
    if cfg.chain_start and not clean and surface_at is not None:
        chained = chain_start(surfaces, surface_at, uv, ok, confident, readings, K, side, cfg,
                              int(usable.sum()), fit)
    if chained is not None:
        start = chained
    elif rec is not None and fit is not None:
        start = staged_start(rec, fit)
    else:
        found = depth_start(uv, ok, K, readings, steady_from, side, cfg)
        if isinstance(found, str):
            raise fail(f"no start for the joint solve: {found}")
        start = found
    kin = HandKinematics(side)
    angles = np.clip(start.angles, kin.model.lower_rad, kin.model.upper_rad)
    log_bone, log_scale = np.zeros(20), float(np.log(start.scale))
    J = kin.keypoints(angles, log_bone, log_scale)
    T_c_p = start.T_c_p.copy()
    for i in range(m):  # frames the start left unposed: PnP against its hand
        if not np.all(np.isfinite(T_c_p[i])) and ok[i].sum() >= cfg.min_points_per_frame:
            pose = pnp(K, J[ok[i]], uv[i, ok[i]], cfg.ransac_px, cfg.min_points_per_frame)
            if pose is not None:
                T_c_p[i] = pose
    posed = np.all(np.isfinite(T_c_p.reshape(m, -1)), axis=1)
    active = posed & usable
    offset = np.asarray(SURFACE_OFFSET_M)
    rejected = frames_to_drop(active, depth_disagrees(T_c_p, J, start.scale * offset, readings,
                                                      cfg), off_smooth_path(T_c_p, active, cfg),
                              max(cfg.min_frames, int(np.ceil(cfg.start_min_share * active.sum()))))
    if rejected is not None:
        active &= ~rejected  # else the start is too poor to judge frames by: solve them all
    conf_clipped = np.maximum(conf, cfg.min_sigma_confidence)
    sigma = cfg.sigma_px / conf_clipped
    priors = HandPriors(cfg.limit_sigma_rad, cfg.rest_sigma_rad, cfg.scale_sigma)
    gate = cfg.depth_gate_m
    frame_median = np.full(m, np.nan)
    sol: GraphSolve | None = None
    range_used = np.zeros((m, 21), bool)
    rounds = 0
    for rounds in range(1, cfg.frame_rounds + 1):  # noqa: B007 (returned)
        if active.sum() < cfg.min_frames:
            break
        z = (np.einsum("mab,jb->mja", T_c_p[:, :3, :3], J) + T_c_p[:, None, :3, 3])[..., 2]
        with np.errstate(invalid="ignore"):
            range_used = active[:, None] & (
                np.abs(z - readings - np.exp(log_scale) * offset) <= gate)
        sol = solve_graph(
            kin, K, uv, ok & active[:, None], sigma, T_c_p, angles, log_bone, log_scale,
            priors, robust=lambda: gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.cauchy_k),
            depth_m=np.where(range_used, readings, np.nan), depth_sigma_m=cfg.depth_sigma_m,
            range_front_weight=cfg.range_front_weight, max_iterations=cfg.max_iterations,
            relative_tol=cfg.relative_tol,
            motion_sigmas=((cfg.motion_sigma_rad, cfg.motion_sigma_m)
                           if cfg.motion_sigma_rad > 0 else None),
            links=(depth_links(surfaces, np.where(active[:, None, None], T_c_p, np.nan), K,
                               cfg.depth_links) if surface_at is not None else [])
            + chain_links(start, active),
        )  # fmt: skip
        T_c_p = np.where(active[:, None, None], sol.T_c_p, T_c_p)
        angles, log_bone, log_scale = sol.angles, sol.log_bone, sol.log_scale
        J = kin.keypoints(angles, log_bone, log_scale)
        gate = cfg.range_gate_sigmas * cfg.depth_sigma_m
        # every usable frame judged against the solved hand: the kept with their solved
        # cameras, the others posed by PnP against it (a frame dropped against a poor start
        # comes back once the hand is right)
        level = float(np.nanmedian(frame_medians(residuals_px(K, T_c_p, J, uv, ok))[active]))
        if cfg.sigma_from_residuals and np.isfinite(level):
            sigma = max(cfg.sigma_px, level / MEDIAN_PER_AXIS) / conf_clipped
        cand = np.where(active[:, None, None], T_c_p, np.nan)
        for i in np.flatnonzero(usable & ~active):
            pose = pnp(K, J[ok[i]], uv[i, ok[i]], max(cfg.ransac_px, 2 * level),
                       cfg.min_points_per_frame)
            if pose is not None:
                cand[i] = pose
        judged = np.all(np.isfinite(cand.reshape(m, -1)), axis=1)
        med = frame_medians(residuals_px(K, cand, J, uv, ok))
        frame_median = np.where(judged, med, frame_median)
        with np.errstate(invalid="ignore"):
            bad = med > max(cfg.frame_reject_factor * level, cfg.frame_reject_min_px)
        drop = frames_to_drop(judged, depth_disagrees(cand, J, np.exp(log_scale) * offset,
                                                      readings, cfg),
                              bad | off_smooth_path(cand, judged, cfg),
                              max(cfg.min_frames, int(np.ceil(cfg.start_min_share * judged.sum()))))
        keep = judged & ~(judged if drop is None else drop)
        if np.array_equal(keep, active) or rounds == cfg.frame_rounds or (
                keep.sum() < cfg.min_frames):
            break
        T_c_p = np.where((keep & ~active)[:, None, None], cand, T_c_p)
        active = keep
    rejected = usable & ~active
    if sol is None or active.sum() < cfg.min_frames:
        raise fail(f"too few frames explained by one hand: {int(active.sum())} kept of "
                   f"{int(posed.sum())} posed ({int(rejected.sum())} dropped as whole "
                   f"frames), need {cfg.min_frames}")
    if range_used.sum() < cfg.min_depth_readings:
        raise fail(f"no metric scale: only {int(range_used.sum())} depth readings agree with "
                   f"the solved hand, need {cfg.min_depth_readings}")
    scale = float(np.exp(log_scale))
    if not cfg.min_scale <= scale <= cfg.max_scale:
        raise fail(f"implausible hand: scale {scale:.3f} outside [{cfg.min_scale}, "
                   f"{cfg.max_scale}] of the adult template")
    T_c_p[~active] = np.nan
    span = rotation_span_deg(T_c_p)
    if span < cfg.min_rotation_deg:
        raise fail(f"the kept cameras turn at most {span:.1f} deg < {cfg.min_rotation_deg} "
                   "deg: too little motion to solve the hand from")
    pose_valid = active.copy()
    # frames between solved ones: where the depth chained them, placed by it (the motion in
    # a gap measured); elsewhere interpolated (``fill_poses`` works on T_c_p: a rigid map)
    T_c_p_filled, _ = fill_poses(chain_fill(start, T_c_p, active))
    report = None
    if cfg.depth_refine.enabled and not clean and depth_frame is not None:
        T_c_p_filled, angles, scale, report = refine_solved_hand(
            depth_frame, K, steady_from, T_c_p_filled, pose_valid, uv, ok, sigma, side, angles,
            np.exp(log_bone), scale, T_color_turntable, cfg.depth_refine)
        log_scale = float(np.log(scale))
    out = _assemble(kin, K, steady_from, uv, ok, T_c_p_filled, pose_valid, start, angles,
                    log_bone, log_scale, range_used, frame_median, rejected, sol, rounds,
                    staged_error, cfg)
    return out if report is None else replace(out, depth_refine=report)


def _assemble(kin, K, steady_from, uv, ok, T_c_p_filled, pose_valid, start, angles, log_bone,
              log_scale, range_used, frame_median, rejected, sol, rounds, staged_error,
              cfg) -> JointSolve:
    """The result in the staged path's types, world = the first steady camera; the palm in
    every frame's camera ``T_c_p_filled`` (m, 4, 4) filled, ``pose_valid`` (m,) where solved."""
    m = len(uv)
    J = kin.keypoints(angles, log_bone, log_scale)
    T_w_p = T_c_p_filled[0].copy()  # world = camera 0: the palm in it is T_c0_p
    T_w_c = np.stack([T_w_p @ inv_T(T) for T in T_c_p_filled])
    T_w_c[0] = np.eye(4)
    joints_w = J @ T_w_p[:3, :3].T + T_w_p[:3, 3]
    res = residuals_px(K, T_c_p_filled, J, uv, ok)
    res[~pose_valid] = np.nan
    level = float(np.nanmedian(res[pose_valid])) if pose_valid.any() else float("nan")
    inlier = ok & pose_valid[:, None] & (res < max(cfg.outlier_px, cfg.outlier_factor * level))
    n_inl = int(inlier.sum())
    kept = ok & pose_valid[:, None]
    # each joint's distance from its inlier detections' rays, in mm (pixels at its depth)
    z = (np.einsum("mab,jb->mja", T_c_p_filled[:, :3, :3], J) + T_c_p_filled[:, None, :3, 3])[
        ..., 2]
    ray_mm = np.where(inlier, 1e3 * res * z / K[0, 0], np.nan)
    seen = np.isfinite(ray_mm).any(0)
    residual_mm = np.full(21, np.nan)
    residual_mm[seen] = np.sqrt(np.nanmean(ray_mm[:, seen] ** 2, axis=0))
    model = kin.model
    scale = float(np.exp(log_scale))
    tol = np.radians(cfg.fit.at_limit_tol_deg)
    fit = HandFit(
        side=model.side, T_w_p=T_w_p, scale=scale, angles_rad=angles, joints_fit_w=joints_w,
        residual_mm=residual_mm, rmse_mm=float(np.sqrt(np.nanmean(residual_mm ** 2))),
        palm_rmse_mm=float(np.sqrt(np.nanmean(residual_mm[list(RIGID_PALM_POINTS)] ** 2))),
        at_limit=(angles <= model.lower_rad + tol) | (angles >= model.upper_rad - tol),
        bone_scale=np.exp(log_bone),
    )
    b = int(np.argmin(np.trace(T_w_c[:, :3, :3], axis1=1, axis2=2)))
    T_start = np.full((m, 4, 4), np.nan)
    posed0 = np.all(np.isfinite(start.T_c_p.reshape(m, -1)), axis=1)
    J0 = model.keypoints(np.clip(start.angles, model.lower_rad, model.upper_rad),
                         scale=start.scale)
    ref = int(np.flatnonzero(posed0)[0]) if posed0.any() else 0
    T_w_p0 = start.T_c_p[ref] if posed0.any() else np.eye(4)
    T_start[posed0] = np.stack([T_w_p0 @ inv_T(T) for T in start.T_c_p[posed0]])
    diagnostics = SfmDiagnostics(
        pair_frames=(steady_from, steady_from + b),
        parallax_deg=float(np.median(ray_angles_deg(inv_T(T_w_c[b]), joints_w))),
        rounds=rounds, lm_iterations=sol.iterations, error_initial=float("nan"),
        error_final=sol.error, scale_samples=int(range_used.sum()),
        scale_inliers=int(range_used.sum()), scale_spread=float("nan"),
        T_w_c_init=fill_poses(T_start)[0] if posed0.any() else T_w_c.copy(),
        joints_w_init=J0 @ T_w_p0[:3, :3].T + T_w_p0[:3, 3],
        T_w_c_visual=T_w_c.copy(), joints_w_visual=joints_w.copy(), inlier_visual=inlier.copy(),
        depth_inlier=range_used.copy(), range_factor=range_used.copy(),
        depth_links=np.zeros((0, 2), int), restarted_after=staged_error,
    )
    rec = HandReconstruction(
        steady_from=int(steady_from), frames=np.arange(steady_from, steady_from + m),
        T_w_c=T_w_c, pose_valid=pose_valid, joints_w=joints_w,
        joint_valid=np.ones(21, bool), residuals_px=res, inlier=inlier,
        reproj_rmse_px=float(np.sqrt(np.mean(res[inlier] ** 2))) if n_inl else float("nan"),
        inlier_ratio=n_inl / max(int(kept.sum()), 1), scale_m_per_unit=1.0,
        diagnostics=diagnostics,
    )
    return JointSolve(rec, fit, "joint", start.name, staged_error, np.exp(log_bone),
                      rejected, frame_median, rounds, sol.iterations)


__all__ = ["HandPath", "JointSolve", "JointSolveConfig", "PRESETS", "STAGE_VERSION",
           "joint_solve", "solve_from_start"]
