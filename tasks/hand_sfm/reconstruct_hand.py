"""The ``reconstruct_hand`` stage (the paper's stage 2): structure from motion of the static
hand seen by virtual cameras (GTSAM).

From the first steady frame on, the 2D keypoints are observations of one fixed set of 21
joints by a moving virtual camera. Two-view geometry with RANSAC starts it, PnP poses the
other frames, a GTSAM factor graph (projection factors, sigma scaled by confidence, Huber
loss) refines everything; observations with large residuals are rejected and the graph
re-solved. The metric scale comes from the aligned depth at the keypoints.

Beyond the paper (keypoints only), the aligned depth also enters the final solve: one range
factor per keypoint reading that agrees with the solve, and dense depth links (the depth of
the static hand and the object it holds registered between frames by point-to-plane ICP,
``hand_sfm.depth_links``) as between factors. From 21 keypoints of a hand ~0.15 m across at
0.35-0.6 m each camera's tilt trades against its sideways translation to about a degree;
the registered surface pins it to a few tenths (rig sessions: 1.6-2.2 deg -> 0.2-0.4 deg).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.threads import thread_budget
from graspcap.tasks.hand_sfm.depth_init import depth_initialisation
from graspcap.tasks.hand_sfm.depth_links import DepthLink, DepthLinkConfig, depth_links
from graspcap.tasks.hand_sfm.depth_sweep import DepthSweep, FrameDepth, frame_depth
from graspcap.tasks.hand_sfm.frame_screen import hand_size_px, screen_jumps
from graspcap.tasks.hand_sfm.metric_scale import (
    DepthLookup,
    depth_lookup_from_frames,
    estimate_scale,
)
from graspcap.tasks.hand_sfm.odometry_init import odometry_initialisation
from graspcap.tasks.hand_sfm.restart import solve_with_restarts
from graspcap.tasks.hand_sfm.result import HandReconstruction, SfmDiagnostics, assemble
from graspcap.tasks.hand_sfm.sanity import check_frames_in_depth, check_result
from graspcap.tasks.hand_sfm.solve import (
    STAGE,
    DepthUse,
    depth_scorer,
    sample_depth,
    solve_rgbd,
    solve_visual,
)
from graspcap.tasks.hand_sfm.surface_clouds import DepthFrame, surface_reader
from graspcap.tasks.hand_sfm.two_view_init import Initialisation, check_frames, initialise

__all__ = ["HandReconstruction", "PRESETS", "ReconstructConfig", "SfmDiagnostics",
           "STAGE_VERSION", "reconstruct_hand"]  # the result types live in sfm_result

STAGE_VERSION = "reconstruct_hand/15"


class ReconstructConfig(StageConfig):
    min_confidence: float = 0.2
    """Detections with a lower confidence are treated as missing."""
    sigma_px: float = 2.5
    """Pixel sigma of a detection with confidence 1; a detection's sigma is sigma_px / conf."""
    min_sigma_confidence: float = 0.3
    """Confidences are clipped below at this value before scaling the sigma."""
    huber_k: float = 2.0
    """Huber threshold in sigmas for the robust first solve."""
    outlier_px: float = 10.0
    """Observations whose residual exceeds this (pixels) are rejected before the re-solve."""
    outlier_sigmas: float = 3.0
    """With ``frame_rejection``: the inlier gate is the larger of ``outlier_px`` and this many
    measured noise sigmas (``hand_sfm.frame_screen.robust_sigma`` of the accepted frames'
    residuals after the robust solve): a real detector misses by 5-10 % of the hand's image
    size, 6-15 px on a 120 px hand, as far as a fixed gate."""
    outlier_rounds: int = 3
    """At most this many reject-and-re-solve rounds (stops early when the inliers settle)."""
    ransac_px: float = 8.0
    """RANSAC threshold (pixels) of the two-view and PnP initialisation (at least)."""
    ransac_hand_share: float = 0.0
    """With ``frame_rejection`` the RANSAC threshold is at least this share of the hand's
    image size (median bounding-box diagonal of the detections). Off (0): at 0.1 a 180 px
    hand with 2.5 px noise got an 18 px threshold and a two-view start wrong enough to end
    in a 197 mm bone (``test_sfm_restart``'s seed 0); noisy detections are left to the
    cameras chained by the depth (``odometry_noise_share``)."""
    frame_rejection: bool = True
    """Drop whole frames whose detections the static hand does not explain, each with its
    reason (``hand_sfm.frame_screen``; ``diagnostics.frame_rejected``): detections that jump
    away from their neighbours' (``jump_share``, ``jump_size_ratio``), frames with fewer than
    ``frame_min_inlier_share`` of their detections within the gate; and the detections of two
    fingers whose labels are exchanged (``swap_gain``). Gates scale with the measured noise
    (``outlier_sigmas``, ``ransac_hand_share``, ``rmse_hand_share``). Off: the fixed-pixel
    stage of reconstruct_hand/12."""
    jump_share: float = 0.35
    """A frame whose detected hand (median keypoint) lies further than this share of the
    hand's size from where its neighbours' motion puts it is rejected before the solve
    (``hand_sfm.frame_screen.screen_jumps``: off the longest chain of frames along which the
    hand moves smoothly; the camera moves smoothly, the rig's worst wrong frame jumps 60 %
    of the hand's size; a hand crossing the image at 90 px per frame is not a jump). Until
    reconstruct_hand/13 the reference was the median of the neighbours' positions, which
    rejected the start of every fast sweep."""
    jump_size_ratio: float = 1.5
    """...or whose hand's image size differs from its neighbours' by more than this factor."""
    jump_half_window: int = 6
    """Frames either side whose median size a frame's is compared with."""
    jump_max_gap: int = 8
    """Consecutive frames of the smooth chains (``jump_share``, ``pose_jump_gates``) are at
    most this many frames with detections apart: runs of up to 7 wrong frames are skipped
    (at 4, wild [9700, 3]'s run of 4 other-hand frames cut the chain and every good frame
    after it was rejected with the run)."""
    jump_motion_share: float = 0.5
    """Along the smooth chains a frame may also lie this share of the hand's own motion over
    the step (at its mean speed) from where its neighbours' motion puts it: a fast hand
    changes its velocity by more pixels than a slow one."""
    frame_min_inlier_share: float = 0.5
    """A posed frame with fewer of its detections within the gate is rejected whole (a
    mirrored hand, another hand the solve half explains)."""
    pose_jump_gates: float = 2.0
    """A posed frame whose camera puts the hand's projection further than this many inlier
    gates from where the motion of its neighbouring frames' cameras puts it is rejected
    whole (``hand_sfm.frame_screen.jumping_poses``: off the longest chain of frames along
    which the projected hand moves smoothly)."""
    swap_gain: float = 1.5
    """Two neighbouring fingers' detections count as label-swapped when exchanging their
    labels lowers their (gate-capped) residual sum by more than this factor."""
    odometry_noise_share: float = 0.025
    """With ``frame_rejection`` and the depth links: when the two-view solve measures a
    detection noise (sigma per coordinate) above this share of the hand's image size, the
    solve from the cameras chained by the depth surfaces (``hand_sfm.odometry_init``) is
    returned instead; when that fails the stage raises (rig: realistic 0.9-1.5 %,
    real-detector 3-5 %)."""
    max_rejected_share: float = 0.6
    """The stage raises when it rejects more than this share of the frames with enough
    detections (ContactPose's own optimiser kept 223 of 507 frames, 56 % rejected)."""
    outlier_rounds: int = 3
    pair_candidates: int = 12
    """Evenly spaced frames among which the initial pair is chosen by parallax."""
    min_parallax_deg: float = 2.0
    """Median triangulation angle the best initial pair must reach."""
    pnp_threads: int = 2
    """Threads of the initialisation's per-frame PnP (OpenCV's RANSAC runs without the GIL;
    the frames are split in two fixed halves): the same poses with 1 or 2."""
    min_points_per_frame: int = 6
    """A frame needs this many detected joints to be posed."""
    min_frames: int = 5
    """At least this many usable frames from the steady frame on."""
    max_iterations: int = 100
    """Levenberg-Marquardt iterations per solve."""
    visual_max_iterations: int = 100
    """Iterations of each reprojection-only solve when range factors follow (which then
    refine everything): pixels alone leave each camera's tilt weakly determined and LM can
    crawl along it for hundreds of iterations without changing the inliers or the scale."""
    visual_relative_tol: float = 1e-7
    """Levenberg-Marquardt's relative error decrease at which each reprojection-only solve
    stops when range factors follow."""
    robust_relative_tol: float = 1e-3
    """Relative error decrease at which the first, Huber-weighted solve stops: it only sorts
    the detections into inliers and outliers, and the inliers' plain solve that follows
    converges from it (under the Huber loss LM reweights every iteration and crawls: 35-55
    iterations to 1e-7, 10-15 to 1e-3, the same outliers)."""
    scale_prior_rel: float = 1e-3
    """Relative sigma of the soft prior holding the distance between the initial pair's cameras
    in the reprojection-only solves (the gauge of scale). A stiff prior makes LM crawl along
    the nearly flat scale direction; a soft one lets it converge."""
    depth_min_confidence: float = 0.5
    """Only inlier detections at least this confident sample the depth for the scale."""
    scale_rel_tol: float = 0.02
    """Depth ratios further than this (relative) from the median are rejected."""
    min_scale_samples: int = 10
    """Fewest depth samples that may fix the scale."""
    depth_use: DepthUse = DepthUse.FACTORS
    """Depth for the scale only, or also as range factors in the final solve."""
    depth_sigma_m: float = 0.002
    """Sigma of a range factor (depth noise plus the skin-to-joint-centre model error)."""
    depth_gate_m: float = 0.008
    """Range readings further than this from the scaled reprojection-only solve get no range
    factor (most rejected readings are the object or the hand's own palm and fingers in
    front of the joint, centimetres nearer)."""
    range_gate_sigmas: float = 3.0
    """After the first RGB-D solve, readings within this many ``depth_sigma_m`` of it get a
    range factor (re-gated from all readings each round)."""
    frame_gate_share: float = 0.5
    """A frame that keeps fewer than this share of its range readings at the gates while at
    least this share (and ``min_points_per_frame``) agree with each other around one offset
    is gated around that offset instead (``hand_sfm.solve.gate_readings``): pixels alone can
    leave a frame's pose 10-20 mm off in depth, and without range factors it would stay
    there. 0 = the plain gates only."""
    frame_gate_max_m: float = 0.03
    """...when that offset is at most this (synthetic frames solved 10-18 mm off): readings
    agreeing further off are more likely the object in front of the hand."""
    max_off_frame_share: float = 0.05
    """The stage raises when the final solve leaves the first steady frame (the output frame)
    or more than this share of the frames with their readings agreeing with each other but
    not with it (as above): the pixels and the depth then disagree on the cameras."""
    range_rounds: int = 3
    """At most this many RGB-D solves (stops early when the gated readings settle)."""
    bone_range_m: tuple[float, float] = (0.008, 0.13)
    """Shortest and longest plausible bone of the result (parent to child keypoint, metres);
    outside it the stage raises instead of returning a diverged hand."""
    distance_range_m: tuple[float, float] = (0.1, 2.5)
    """Plausible camera-to-joint distances (metres) of the result, else the stage raises."""
    min_rotation_deg: float = 12.0
    """The stage raises when no camera of the result is turned this far from the first: with
    less, the keypoints' rays are too nearly parallel to triangulate the joints from."""
    little_rotation_deg: float = 25.0
    """An implausible result of a hand turned less than this names the little motion as the
    likely cause (measured on a rig session: a hand truly turned 8 deg was solved as turned
    16 deg with a 187 mm bone; sessions turned 23-53 deg solve to 0.1-0.4 deg per camera)."""
    max_reproj_rmse_px: float = 8.0
    """The stage raises when the final inlier reprojection RMSE exceeds this (at least)."""
    rmse_hand_share: float = 0.12
    """With ``frame_rejection`` the RMSE limit is at least this share of the hand's image size
    (a real detector's inliers miss by 5-10 % of it)."""
    min_inlier_ratio: float = 0.6
    """The stage raises when fewer of the detections are inliers of the final solve (of the
    accepted frames with ``frame_rejection``; ``max_rejected_share`` bounds the rest)."""
    depth_links: DepthLinkConfig = DepthLinkConfig()
    """Dense depth links between frames (RGB-D only, see ``hand_sfm.depth_links``)."""
    prefetch_depth: bool = True
    """Do the depth work (``hand_sfm.depth_sweep``: each frame's readings at the keypoints and its
    surface) ahead on a second thread from the start of the stage, while the solves run;
    OpenCV decodes the depth PNGs without the GIL. Identical results (each frame is computed
    by one pure function, on whichever thread asks first); saves wall time when a core is
    free. Only with whole depth frames (``depth_frame``), and not when
    ``GRASPCAP_WORKER_THREADS`` is 1 (``graspcap.tasks.core.threads``, as every thread count
    here)."""
    depth_init_score: bool = True
    """Choose the initial pair among near-equally good ones by how many depth readings one
    scale explains: pixels of a small, distant hand barely tell the hand from its
    depth-reversed twin, the depth does."""
    depth_restart: bool = True
    """When the solve from the two-view start fails (an implausible hand, too little turn, too
    few posed frames), solve once more from the depth initialisation (``hand_sfm.depth_init``):
    the two-view start can pick an essential matrix that is wrong by tens of degrees. The
    checks stay, so a second wrong hand fails the same way."""
    restart_depth_share: float = 0.3
    """Also solve from the depth initialisation when fewer of the depth readings than this
    agree with the reprojection-only solve's scale or with the result (a hand settled in a
    wrong minimum that still looks plausible; measured: 0.10-0.29 for hands 33-83 mm off,
    0.32-0.87 for correct ones)..."""
    restart_share_margin: float = 0.15
    """...and keep the restart only when this much more of the readings agree with its
    result: a wrong hand can fit the wrong readings (a fingertip's pixel on the object) a
    little better (rig seed 9000 #8: a right hand 0.52, a restart 18 mm off 0.60; wrong
    hands restarted right: 0.22 -> 0.66, 0.37 -> 0.76)."""


PRESETS: dict[str, ReconstructConfig] = {
    "default": ReconstructConfig(),
    "openpose": ReconstructConfig(sigma_px=4.0, outlier_px=15.0, ransac_px=12.0),
    "strict": ReconstructConfig(outlier_px=6.0, min_parallax_deg=5.0, min_frames=20),
    "paper": ReconstructConfig(depth_use=DepthUse.SCALE),
}


def reconstruct_hand(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int,
    depth_at: DepthLookup | np.ndarray,
    surface_offset_m: np.ndarray,
    config: ReconstructConfig = PRESETS["default"],
    *,
    depth_frame: DepthFrame | None = None,
    T_color_turntable: np.ndarray | None = None,
    why_missing: str = "",
) -> HandReconstruction:
    """Structure from motion of the hand from ``steady_from`` on.

    Solved from the two-view start; when that fails and ``config.depth_restart`` is set,
    once more from the depth initialisation (``diagnostics.restarted_after`` then holds
    the first failure). When both fail the error names both reasons.

    Parameters
    ----------
    keypoints : (n, 21, 3) float, x, y pixels and confidence per video frame (0 = missed).
    K : (3, 3) colour intrinsics.
    steady_from : first steady video frame.
    depth_at : a :data:`~graspcap.tasks.hand_sfm.metric_scale.DepthLookup` (video frame index,
        pixels -> metres) or the aligned depth frames (n, h, w) in metres.
    surface_offset_m : (21,) depth of each joint centre below the skin the camera sees.
    depth_frame : whole aligned depth frames by video frame index, for the dense depth links
        (``depth_icp``); taken from ``depth_at`` when that is the frames array. Each frame's
        depth work is done once per call (``hand_sfm.depth_sweep``), with ``prefetch_depth`` on a
        second thread: ``depth_frame`` should be the cached reader behind ``depth_at`` (as
        ``pipeline`` passes it), so that a frame decodes once for both.
    T_color_turntable : (4, 4) turntable pose in the colour camera: the platter and table
        below its top plane are cut from the depth links' surfaces; without it there are no
        depth links.
    why_missing : why frames lack detections (``Keypoints2D.missing_summary``), added to the
        error when too few frames have enough joints.
    """
    if not callable(depth_at):
        frames_m = np.asarray(depth_at)
        depth_frame = depth_frame or (lambda i: frames_m[i])
        depth_at = depth_lookup_from_frames(frames_m)
    cfg = config
    K = np.asarray(K, dtype=float)
    kp = np.asarray(keypoints, dtype=float)[steady_from:]
    ok = (kp[..., 2] >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)
    shortage = _too_few(ok, steady_from, cfg)
    if shortage:
        raise StageError(STAGE, shortage + (f"; {why_missing}" if why_missing else ""))
    prescreen: dict[int, str] = {}
    hand_px = float("nan")
    if cfg.frame_rejection:  # before any solve: detections that jump away from their neighbours
        prescreen = screen_jumps(
            kp[..., :2], ok, jump_share=cfg.jump_share, size_ratio=cfg.jump_size_ratio,
            half_window=cfg.jump_half_window, min_points=cfg.min_points_per_frame,
            first_frame=steady_from, max_gap=cfg.jump_max_gap,
            motion_share=cfg.jump_motion_share,
        )  # fmt: skip
        sizes = hand_size_px(kp[..., :2], ok, cfg.min_points_per_frame)
        sizes[list(prescreen)] = np.nan
        hand_px = float(np.nanmedian(sizes)) if np.isfinite(sizes).any() else float("nan")
    ransac_px = _ransac_px(cfg, hand_px)
    confident = ok & (kp[..., 2] >= cfg.depth_min_confidence)
    link_cfg = cfg.depth_links
    use_links = (  # without the turntable the static scene would be registered too
        cfg.depth_use is DepthUse.FACTORS
        and link_cfg.enabled
        and depth_frame is not None
        and T_color_turntable is not None
    )

    surface_at = surface_reader(
        depth_frame, K, steady_from, T_color_turntable,
        centre_below_skin_m=link_cfg.centre_below_skin_m, radius_m=link_cfg.radius_m,
        stride_px=link_cfg.stride_px, min_height_m=link_cfg.min_height_m,
        spacing_m=link_cfg.spacing_m,
    )

    compute = partial(
        frame_depth, uv=kp[..., :2], usable=ok, depth_at=depth_at, first_frame=steady_from,
        surface_at=surface_at if use_links else None, confident=confident,
    )  # fmt: skip
    # ahead: the pair scoring's frames first, then every other frame the sweep samples
    swept = np.flatnonzero(confident.any(1))
    first = np.intersect1d(check_frames(len(kp)), swept)
    order = np.concatenate([first, np.setdiff1d(swept, first)])
    background = cfg.prefetch_depth and depth_frame is not None and thread_budget(2) > 1
    with DepthSweep(compute, order, background=background) as sweep:
        solve = partial(
            _reconstruct, keypoints, K, steady_from, sweep.get, surface_offset_m, cfg,
            use_links=use_links, prescreen=prescreen, hand_px=hand_px,
        )  # fmt: skip
        ok_init = ok.copy()
        ok_init[list(prescreen)] = False

        def odometry():
            """The solve from the cameras chained by the depth surfaces, or None."""
            odo = odometry_initialisation(
                [sweep.get(i).surface if ok_init[i].sum() >= cfg.min_points_per_frame
                 else None for i in range(len(kp))],
                kp[..., :2], ok_init, K, link_cfg, ransac_px=ransac_px,
                min_points=cfg.min_points_per_frame, min_frames=cfg.min_frames,
            )  # fmt: skip
            return None if odo is None else partial(solve, initialisation=odo,
                                                    rgbd_from_start=True)

        def first_solve():
            """The two-view solve; when its detections are noisy (measured sigma above
            ``odometry_noise_share`` of the hand's size) the odometry solve instead, and a
            ``StageError`` naming both when that fails: cameras posed from such keypoints
            are off by degrees (rig real-detector sessions: 5-35 deg, passing every check),
            the chained depth surfaces by tenths."""
            rec = solve()
            share = rec.diagnostics.noise_sigma_px / hand_px
            if not (cfg.frame_rejection and use_links and share > cfg.odometry_noise_share):
                return rec
            noisy = (f"the detections are too noisy to pose the cameras from (measured "
                     f"{rec.diagnostics.noise_sigma_px:.1f} px, {share:.1%} of the hand's "
                     f"{hand_px:.0f} px > {cfg.odometry_noise_share:.1%})")
            attempt = odometry()
            if attempt is None:
                raise StageError(STAGE, f"{noisy}, and the depth surfaces of fewer than "
                                 f"{cfg.min_frames} frames chain into cameras")
            try:
                again = attempt()
            except StageError as e:
                raise StageError(STAGE, f"{noisy}, and the solve from the cameras the depth "
                                 f"surfaces chain failed: {e.reason}") from e
            why = (f"detections noisy ({share:.1%} of the hand's size): cameras from the "
                   "depth surfaces")
            return replace(again, diagnostics=replace(again.diagnostics, restarted_after=why))

        def restarts():
            """Solves from the depth initialisation: through the reprojection-only solve
            like the first, then straight into the RGB-D solve (pixels alone may prefer a
            wrong hand even from a right start). With ``frame_rejection`` first from the
            cameras chained by the depth surfaces (``hand_sfm.odometry_init``), straight into
            the RGB-D solve."""
            if cfg.frame_rejection and use_links:
                attempt = odometry()
                if attempt is not None:
                    yield attempt
            init = depth_initialisation(
                kp[..., :2], ok_init, K, sweep.readings(range(len(kp))),
                np.broadcast_to(np.asarray(surface_offset_m, dtype=float), (21,)),
                steady_from, ransac_px=ransac_px, min_points=cfg.min_points_per_frame,
            )  # fmt: skip
            if init is not None:
                yield partial(solve, initialisation=init)
                yield partial(solve, initialisation=init, rgbd_from_start=True)

        return solve_with_restarts(
            first_solve, restarts, enabled=cfg.depth_restart, min_share=cfg.restart_depth_share,
            margin=cfg.restart_share_margin,
        )


def _ransac_px(cfg: ReconstructConfig, hand_px: float) -> float:
    """The initialisation's RANSAC threshold: ``ransac_px``, with ``frame_rejection`` at least
    ``ransac_hand_share`` of the hand's image size ``hand_px``."""
    if cfg.frame_rejection and np.isfinite(hand_px):
        return max(cfg.ransac_px, cfg.ransac_hand_share * hand_px)
    return cfg.ransac_px


def _too_few(ok: np.ndarray, steady_from: int, cfg: ReconstructConfig) -> str | None:
    """Why the detections ``ok (m, 21)`` from ``steady_from`` on are too few to solve; None
    when they are not."""
    m = len(ok)
    if not ok.any():
        return (f"no keypoint detected with confidence >= {cfg.min_confidence} "
                f"in frames {steady_from}..{steady_from + m - 1}")
    usable = int((ok.sum(1) >= cfg.min_points_per_frame).sum())
    if usable < cfg.min_frames:
        return (f"too few usable frames: {usable} of {m} frames from {steady_from} on have "
                f">= {cfg.min_points_per_frame} detected joints, need {cfg.min_frames}")
    return None


def _reconstruct(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int,
    frame_at: Callable[[int], FrameDepth],
    surface_offset_m: np.ndarray,
    config: ReconstructConfig,
    *,
    use_links: bool,
    initialisation: Initialisation | None = None,
    rgbd_from_start: bool = False,
    prescreen: dict[int, str] | None = None,
    hand_px: float = float("nan"),
) -> HandReconstruction:
    """One solve of :func:`reconstruct_hand`, from the two-view start or from a metric
    ``initialisation`` (``hand_sfm.depth_init``); with ``rgbd_from_start`` that also starts the
    RGB-D solve (instead of the scaled reprojection-only solve). ``prescreen`` (solve row ->
    reason) are frames rejected before the solve, ``hand_px`` the hand's image size."""
    cfg = config
    K = np.asarray(K, dtype=float)
    offset = np.broadcast_to(np.asarray(surface_offset_m, dtype=float), (21,))
    kp = np.asarray(keypoints, dtype=float)[steady_from:]
    m = len(kp)
    uv, conf = kp[..., :2], kp[..., 2]
    ok = (conf >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)
    shortage = _too_few(ok, steady_from, cfg)
    if shortage:
        raise StageError(STAGE, shortage)
    prescreen = dict(prescreen or {})
    ok_init = ok.copy()
    ok_init[list(prescreen)] = False
    ransac_px = _ransac_px(cfg, hand_px)
    init, best_parallax = (initialisation, 0.0) if initialisation is not None else initialise(
        uv,
        ok_init,
        K,
        n_candidates=cfg.pair_candidates,
        ransac_px=ransac_px,
        min_points=cfg.min_points_per_frame,
        min_parallax_deg=cfg.min_parallax_deg,
        threads=thread_budget(cfg.pnp_threads),
        depth_score=(
            depth_scorer(cfg, conf, ok_init, frame_at, offset)
            if cfg.depth_init_score
            else None
        ),
    )
    if init is None:
        raise StageError(
            STAGE,
            "insufficient parallax, no motion to triangulate from: the best of the "
            f"candidate frame pairs has a median triangulation angle of {best_parallax:.2f} deg "
            f"< {cfg.min_parallax_deg} deg; the hand must turn relative to the camera "
            "during the steady phase",
        )
    pair = init.pair

    sigma = cfg.sigma_px / np.maximum(conf, cfg.min_sigma_confidence)
    ba, res, inlier, rounds, screen = solve_visual(
        cfg, uv, ok, sigma, K, init.T_c_w, init.points_w, pair, rejected=prescreen,
        first_frame=steady_from,
    )  # fmt: skip
    sigma = sigma * screen.noise_factor
    T_c_w, X = ba.T_c_w, ba.points_w
    posed_frames = int(np.all(np.isfinite(T_c_w.reshape(m, -1)), axis=1).sum())
    if posed_frames < cfg.min_frames:
        rejected = f" ({len(screen.rejected)} rejected whole)" if screen.rejected else ""
        raise StageError(
            STAGE,
            f"too few usable frames: only {posed_frames} frames could be posed "
            f"with >= {cfg.min_points_per_frame // 2 + 1} inlier joints{rejected}, need "
            f"{cfg.min_frames}",
        )

    link_cfg = cfg.depth_links
    depth, z, surfaces = sample_depth(cfg, conf, inlier, T_c_w, X, frame_at)
    sampled = np.isfinite(depth)
    scale = estimate_scale(
        z[sampled],
        depth[sampled],
        np.broadcast_to(offset, depth.shape)[sampled],
        rel_tol=cfg.scale_rel_tol,
        min_samples=cfg.min_scale_samples,
    )
    if scale is None:
        raise StageError(
            STAGE,
            f"no valid depth for the scale: fewer than {cfg.min_scale_samples} inlier "
            "keypoints have a depth reading consistent with the others",
        )
    s = scale.scale_m_per_unit
    depth_inlier = np.zeros_like(sampled)
    depth_inlier[sampled] = scale.inlier
    T_vis, X_vis, inlier_vis = T_c_w.copy(), X * s, inlier.copy()
    T_vis[:, :3, 3] *= s

    range_used = np.zeros((m, 21), bool)
    links: list[DepthLink] = []
    if cfg.depth_use is DepthUse.FACTORS:
        link_fn = None
        if use_links:

            def link_fn(T: np.ndarray) -> list[DepthLink]:
                return depth_links(surfaces, T, K, link_cfg)

        T_start, X_start = T_vis, X_vis
        if rgbd_from_start:  # metric: start from it, the pixels alone may prefer a
            T_start = np.where(np.isfinite(init.T_c_w), init.T_c_w, T_vis)  # wrong hand
            X_start = np.where(np.isfinite(init.points_w), init.points_w, X_vis)
        first_link_round = 2
        if use_links and rgbd_from_start and init.links_from_start:
            T_links = init.T_c_w  # the chained depth cameras: the links hold them from round 1

            def link_fn(T: np.ndarray) -> list[DepthLink]:
                return depth_links(surfaces, T_links, K, link_cfg)

            first_link_round = 1
        T_c_w, X, res, inlier, n, range_used, links, off = solve_rgbd(
            cfg, K, uv, ok, inlier, sigma, T_start, X_start, depth, offset, pair.a, link_fn,
            screen=screen if cfg.frame_rejection else None, first_link_round=first_link_round,
        )
        rounds += n
        check_frames_in_depth(off, cfg.max_off_frame_share)
    else:
        T_c_w, X = T_vis, X_vis

    accepted = screen.accepted(m) if cfg.frame_rejection else None
    rmse_limit = cfg.max_reproj_rmse_px
    if cfg.frame_rejection and np.isfinite(hand_px):
        rmse_limit = max(rmse_limit, cfg.rmse_hand_share * hand_px)
    check_result(cfg, X, T_c_w, res, inlier, ok, steady_from, accepted=accepted,
                 rmse_limit_px=rmse_limit, rejected=screen.rejected)  # fmt: skip
    return assemble(
        steady_from, T_c_w, X, res, ok, inlier, init=init, s=s, T_vis=T_vis, X_vis=X_vis,
        inlier_vis=inlier_vis, rounds=rounds, ba=ba, scale=scale, depth_inlier=depth_inlier,
        range_used=range_used, links=links, screen=screen, hand_px=hand_px,
    )
