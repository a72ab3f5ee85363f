"""Stage: the first steady frame, from the manifest or detected from the keypoints.

Detection, a change point in how rigid the hand is:

1. The end of the video is certainly steady, so a fixed 3D hand is reconstructed (up to
   scale) from a window of final frames.
2. Every frame is posed against that hand (RANSAC PnP, then a robust Levenberg-Marquardt of
   all frames at once); its residual vectors (21 x 2 px) are what no rigid motion of the fixed
   hand explains. Gross detection errors are dropped.
3. Coarse onset: the residual vectors averaged over a short centred window, their energy
   standardised by the median and robust spread (MAD) over the steady reference frames, and
   the change point ``t`` maximising ``sum_{i < t} (z_i - drift)`` (a CUSUM). The hand is
   rebuilt from the frames found steady and the frames re-scored.
   A hand fitted to late viewpoints only can fit early steady frames so poorly that they
   look moving (the onset 40-60 frames late). So the model then grows backwards: refitted
   with the block of frames just before its own, the block is kept while it fits as well as
   the model's frames did before (a moving block, pulled into the fit, still stands out);
   a block that does not is halved and tried again, so the model ends within two frames of
   the motion rather than within a block.
4. Refined onset: a hand that settles slows down, and in its last moving frames the fingers
   are a fraction of a pixel to a few pixels from their final place, which an energy (a sum
   over 42 noisy coordinates) cannot tell from noise. But a smooth motion arrives at its end
   along one direction, so those frames' residual vectors share one pattern: the sum of the
   residual vectors of the frames just before the coarse onset. Each frame's residual is
   projected on that pattern (leaving the frame itself out of it), a matched filter whose
   noise is one coordinate's, not 42's; standardised by the steady frames, its CUSUM from
   the start of the pattern window gives the onset, at most ``pattern_frames / 2`` after the
   coarse one and never before it (the filter finds motion the energy missed; it cannot
   unsee the motion the energy found). Pattern and onset are re-estimated until the onset
   settles.
5. Depth onset (with the aligned depth): under a real detector's keypoint noise (5-10 % of
   the hand's image size, correlated over frames) steps 3-4 find the onset 6-15 frames early.
   The depth is far less noisy: before the onset the hand-and-object surface deforms from
   frame to frame (the fingers close, the palm approaches, the object is lifted), after it
   two frames' surfaces differ by one rigid motion. ``hand_sfm.steady_depth`` registers each
   frame's surface rigidly onto the one ``depth_gap`` frames later and measures the share of
   it that the other frame sees through; that share's change point (a CUSUM standardised by
   the last known frames), searched from ``depth_before`` frames before the keypoint onset to
   ``depth_after`` frames after it (from the first frame when the change lands on the
   window's first frame: the keypoint onset was late), moved ``depth_lag_frames`` later,
   replaces the keypoint onset when enough frames have a surface (``depth_min_share``);
   with clean keypoints the later of the two stands (``later_of_both``).
6. Whether the depth's onset can be trusted: the last frame the grasp is seen deforming in
   (a share of at least ``depth_strong_share``, or still falling towards the steady level)
   and the onset must be at most ``depth_max_span`` frames apart; weak non-rigidity that does
   not fall (a misfit the depth cannot tell from a settling hand), frames without a surface
   or without the hand detected between them leave the onset anywhere in that span. A surface
   that turned rigid and deformed again (two candidate ends), or a change on the searched
   window's last frame (the deformation goes on past it), are ambiguous too, and so is a
   change with no deformation seen before it. Each marks the selection uncertain with its
   reason.
7. A marked onset is moved to the first frame from which the depth reads rigid for
   ``depth_settled_frames`` frames after it read the grasp deforming (the mark kept): a fast
   turn of the held grasp, misregistered, can fill the change point's reference and hide a
   plain deformation at the start; an early onset spoils every later stage.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.hand_sfm import steady_depth, steady_keypoints
from graspcap.tasks.hand_sfm.frame_screen import hand_size_px

STAGE = "select_steady"
STAGE_VERSION = "select_steady/13"


class SteadyMethod(StrEnum):
    """Where ``steady_from`` came from."""

    MANIFEST = "manifest"
    DETECTED = "detected"


class SelectSteadyConfig(StageConfig):
    window_frames: int = 60
    """Final frames assumed steady for the first hand model (at most ``window_share``)."""
    window_share: float = 0.7
    """Largest share of the video the first window may take."""
    model_frames: int = 24
    """Evenly spaced frames of a window that the hand model is reconstructed from."""
    pair_candidates: int = 10
    """Evenly spaced frames of the first window among which the two-view start is chosen."""
    pair_hypotheses: int = 6
    """Two-view hypotheses (largest parallax first) grown and compared by agreement."""
    check_frames: int = 15
    """Evenly spaced frames of the window each hypothesis is grown on to compare them."""
    min_confidence: float = 0.2
    """Detections with a lower confidence are treated as missing."""
    ransac_px: float = 8.0
    """RANSAC threshold (pixels) of the initialisation and of the per-frame PnP."""
    huber_px: float = 5.0
    """Huber threshold (pixels) of the per-frame pose refinement (about twice the noise)."""
    outlier_px: float = 15.0
    """Residuals longer than this (pixels) are gross detection errors and ignored."""
    smooth_frames: int = 3
    """Centred window (frames) over which residual vectors are averaged (coarse onset)."""
    drift_sigmas: float = 2.0
    """Coarse CUSUM drift: how many noise spreads a frame must stand out by to count as
    moving."""
    pattern_frames: int = 8
    """Frames before the onset whose summed residual vectors give the direction in which the
    hand was still moving (refined onset)."""
    pattern_drift_sigmas: float = 1.0
    """Refined CUSUM drift, in noise spreads of the projection on that direction: half the
    smallest shift to detect (2 spreads, what a frame 3-4 frames before a smooth stop shows
    under 2.5 px noise)."""
    pattern_passes: int = 3
    """At most this many re-estimates of the direction and the refined onset."""
    min_points: int = 6
    """A frame needs this many detected joints to be scored."""
    refinements: int = 2
    """At most this many times the hand is re-adjusted over the frames found steady and the
    frames re-scored (stops when the coarse onset settles)."""
    grow_frames: int = 8
    """Block of frames before the model's that the hand is refitted with, growing the model
    backwards while the block fits like the steady frames (0: no growth)."""
    grow_min_frames: int = 2
    """A rejected block is halved and tried again down to this many frames, so the model
    reaches the onset to within that many frames rather than a block (``grow_frames``: no
    halving; below the scores' smoothing window, 3, a block's mean is partly its neighbour's)."""
    grow_z: float = 1.0
    """Largest mean score of a refitted block, standardised by the model's frames before the
    refit, for it to count as steady (about 1.6 standard errors of a mean of 8 windowed
    scores)."""
    ba_iterations: int = 60
    """Levenberg-Marquardt iterations of the hand model's bundle adjustment."""
    max_noise_share: float = 0.025
    """The detected onset is marked uncertain (``SteadySelection.uncertain``, a QA flag) when
    the steady frames' residual score (median ``scores_px``) exceeds this share of the hand's
    image size (median bounding-box diagonal of the detections): the last frames of a
    settling grasp move the fingers by a few per cent of the hand, which such noise hides
    (rig: realistic scores 1-2 % of the hand, onsets within 3 frames; real-detector 2.5-4 %,
    every onset 10-15 frames early). An onset the depth found (step 5) is not marked for
    this."""
    depth_onset: bool = True
    """Refine the onset from the depth's non-rigidity (step 5) when the depth is given."""
    depth_gap: int = 4
    """Each frame's surface is registered onto the one this many frames later: the frames
    just before the onset then show all the deformation left, not one frame's worth."""
    depth_far_m: float = 0.004
    """A surface point counts as not explained by the rigid motion when the other frame sees
    this far behind it (about 3 sigma of the sensor's noise at a hand's distance)."""
    depth_drift_sigmas: float = 2.0
    """CUSUM drift of the depth onset, in spreads of the steady frames' share."""
    depth_min_spread: float = 0.01
    """Smallest spread of the steady frames' share (a share of 0 on every steady frame has no
    noise scale)."""
    depth_before: int = 3
    """The depth onset is searched from this many frames before the keypoint onset..."""
    depth_after: int = 20
    """... to this many after it (the keypoint onset is early under noise, not late)."""
    depth_ref_after: int = 12
    """The steady reference of the depth's share: its last 20 known frames at least this many
    frames after the keypoint onset."""
    depth_min_share: float = 0.5
    """The depth onset is used only when at least this share of the frames has a share."""
    depth_lag_frames: int = 1
    """The depth onset is moved this many frames later: the last frames of a settling grasp
    move the surface by less than ``depth_far_m`` in all, so the share reaches the steady
    level 1-2 frames before the motion ends (tuning: 60-frame realistic onsets -1 to -4,
    median -2, without it). Never past a frame without the hand detected: the change point
    itself is kept then."""
    later_of_both: bool = True
    """Where the keypoints are clean (noise within ``max_noise_share`` of the hand), the onset
    is the later of the keypoints' and the depth's: both change points can only be early by
    missing motion below their sensitivity (the keypoints' by a settling that their noise
    hides, the depth's by the last frames moving the surface less than ``depth_far_m`` over
    ``depth_gap`` frames: at 120 frames the same grasp settles over twice the frames, and
    the depth's onset came 4 frames early on 8 of 10 realistic tuning sessions while the
    keypoints' was within 3 on 9), and a hand either sees moving is not steady. Noisy
    keypoints move their change point at random, late as well: the depth's stands alone.
    Where the keypoints' onset stands this way, the depth's own doubts (step 6: deformation
    last seen several frames before the onset) are not raised: they describe the depth's
    change point, which was not taken."""
    depth_strong_share: float = 0.2
    """A frame whose share is at least this is seen deforming (the fingers closing, the
    object lifted: 0.3-1 of the surface), above the misfits of a rigid surface (0-0.12 on
    the steady frames of wild sessions: a symmetric object slid by the registration, the
    turn hiding or uncovering surface). Frames after the last such frame whose share keeps
    falling are the settling tail (a decelerating motion deforms less every frame)."""
    depth_max_span: int = 3
    """The depth onset is marked uncertain when it lies more than this many frames (besides
    ``depth_lag_frames``) after the last frame seen deforming: the frames between are weak
    non-rigidity that is not a settling tail, frames without a surface, or frames without the
    hand detected, and the end of the grasp can lie anywhere among them; also when the
    surface is rigid more than this many frames before the depth's change point and seen
    deforming again between them (two candidate ends)."""
    max_undetected_skip: int = 3
    """The onset is marked uncertain when the frames without the hand detected that follow the
    change point (the depth's, else the keypoints') put it more than this many frames after
    it, ``depth_lag_frames`` included: the grasp may have ended anywhere among them (tuning
    wild ``[94397, 22]``: the right change point, on a frame without a detection, 3 more
    after it, the onset +4 and unmarked)."""
    depth_settled_frames: int = 2
    """Where the onset is marked uncertain, it is moved to the first frame (plus
    ``depth_lag_frames``) from which this many frames in a row share below
    ``depth_settled_share`` after a frame read deforming (``depth_strong_share``), within the
    searched window (``steady_depth.settled_after_deforming``), the mark kept. 0: off.
    Two frames (5 before session 27): the surface that reads rigid and then 'deforms again'
    is, on every such tuning session, the held grasp turning faster than the registration
    follows (46-81 deg between the registered frames), and its first rigid run lasted 2-4
    frames; taken there, 5 of 5 such wild 40-frame onsets 6-9 frames late came within 1
    frame, and no other onset of 164 tuning sessions moved (``docs/benchmarks.md``,
    "Session 27")."""
    depth_settled_share: float = 0.1
    """A share below this reads rigid for ``depth_settled_frames`` (steady frames: 0-0.03)."""
    depth_radius_m: float = 0.15
    """Radius of the sphere around the hand's centre that cuts each frame's surface."""
    depth_stride_px: int = 3
    """Pixel lattice of the surfaces (its coarsest: see ``depth_spacing_m``)."""
    depth_spacing_m: float | None = 0.0025
    """The surfaces' lattice is refined (down to every pixel) for its nodes to lie about this
    far apart at the hand's depth (``surface_clouds.surface_cloud``): a hand 1 m away on a
    960 px wide Kinect v2 image is sampled every pixel, one at 0.45 m on a 640 px camera every
    3 (None: ``depth_stride_px`` at every distance)."""
    depth_min_height_m: float = 0.015
    """Depth less than this above the platter's top plane (platter, table) is dropped."""
    depth_max_points: int = 600
    """At most this many points of a surface in its registration."""
    depth_iterations: int = 12
    """Point-to-plane ICP iterations of a registration."""


PRESETS: dict[str, SelectSteadyConfig] = {
    "default": SelectSteadyConfig(),
    "openpose": SelectSteadyConfig(ransac_px=12.0, huber_px=8.0, outlier_px=25.0,
                                   drift_sigmas=2.5),
}  # fmt: skip


@dataclass(frozen=True)
class SteadySelection:
    """The chosen first steady frame and how it was chosen.

    steady_from : video frame index; method : manifest or detected.
    scores_px : (n,) float, per frame the RMS length (px) of the window-averaged residual
        vectors against the fixed hand, scaled to one frame's noise (NaN where not scored;
        all NaN from the manifest).
    threshold_px : the score a frame needs to count as moving in the coarse onset, median +
        drift * spread of the reference frames (NaN from the manifest).
    coarse_from : the coarse onset (CUSUM of ``scores_px``); -1 from the manifest.
    pattern_px : (21, 2) float, unit direction of the last residual vectors before the onset
        (the refined onset's matched filter; empty from the manifest).
    z : (n,) float, each frame's residual projected on ``pattern_px``, standardised by the
        steady reference frames (NaN where not scored).
    cusum : (n + 1,) float, ``sum_{start <= i < t} (z_i - drift)`` for every candidate onset
        ``t`` (-inf before ``start``, the start of the pattern window); the onset is its
        argmax (empty from the manifest).
    model_frames : (k,) int, video frames the final hand model was reconstructed from.
    uncertain : why the detected onset may be wrong by more than a few frames ("" when it is
        not, and from the manifest): no frame stood out as moving, or the keypoint noise is
        too large a share of the hand to see the last motion (and the depth did not find
        the onset). QA flags such a session.
    keypoint_from : the onset from the keypoints alone (steps 1-4); -1 from the manifest.
    depth_share : (n,) float, per frame the share of its surface that no rigid motion onto
        the frame ``depth_gap`` later explains (step 5; NaN where unknown; empty without
        depth or from the manifest).
    depth_from : the depth's change point (step 5, before ``depth_lag_frames``), -1 when
        not used.
    depth_moving_to : the last frame the depth sees the grasp deforming in (step 6), -1 when
        none or the depth is not used.
    """

    steady_from: int
    method: SteadyMethod
    scores_px: np.ndarray
    threshold_px: float
    coarse_from: int
    pattern_px: np.ndarray
    z: np.ndarray
    cusum: np.ndarray
    model_frames: np.ndarray
    uncertain: str = ""
    keypoint_from: int = -1
    depth_share: np.ndarray = field(default_factory=lambda: np.empty(0))
    depth_from: int = -1
    depth_moving_to: int = -1


def _keypoint_noise(uv, ok, scores, onset, detected) -> tuple[float, float, float]:
    """(noise px, hand px, noise share): the steady frames' median residual score from
    ``onset`` on, the hand's image size (median bounding-box diagonal of the detections)."""
    steady = scores[onset:][np.isfinite(scores[onset:])]
    noise = float(np.median(steady)) if len(steady) else float("nan")
    sizes = hand_size_px(uv[detected], ok[detected], min_points=1)
    hand = float(np.median(sizes)) if len(sizes) else float("nan")
    return noise, hand, noise / hand if hand > 0 else float("nan")


def _uncertainty(uv, ok, scores, onset, detected, cfg, by_depth=False) -> str:
    """Why the detected ``onset`` may be wrong by more than a few frames, "" if not."""
    noise, hand, share = _keypoint_noise(uv, ok, scores, onset, detected)
    if onset <= detected[0]:
        return (f"no frame before {onset} stands out as moving above the keypoint noise "
                f"({noise:.1f} px, {share:.1%} of the hand's {hand:.0f} px): the adjustment "
                "phase is not seen; set grasp.steady_from in session.json if there is one")
    if share > cfg.max_noise_share and not by_depth:
        return (f"the keypoint noise ({noise:.1f} px, {share:.1%} of the hand's {hand:.0f} px "
                f"> {cfg.max_noise_share:.1%}) hides the last motion of the grasp: the onset "
                f"(frame {onset}) may be several frames early; set grasp.steady_from in "
                "session.json")
    return ""


def select_steady(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int | None,
    config: SelectSteadyConfig = PRESETS["default"],
    *,
    why_missing: str = "",
    depth_frame: Callable[[int], np.ndarray] | None = None,
    T_color_turntable: np.ndarray | None = None,
) -> SteadySelection:
    """The first steady frame: the manifest's ``steady_from`` when given, else detected.

    Parameters
    ----------
    keypoints : (n, 21, 3) float, x, y pixels and confidence per video frame (a frame without
        a detection has confidence 0 everywhere).
    K : (3, 3) colour intrinsics.
    steady_from : the manifest's value, or None to detect it.
    why_missing : why frames lack detections (``Keypoints2D.missing_summary``), added to the
        error when too few frames have enough joints.
    depth_frame : ``depth_frame(frame) -> (h, w)`` metres of the aligned depth, 0 where no
        reading; with ``T_color_turntable`` (4, 4) it gives the depth onset (step 5).
    """
    cfg = config
    kp = np.asarray(keypoints, dtype=float)
    n = len(kp)
    if steady_from is not None:
        if not 0 <= steady_from < n:
            raise StageError(STAGE, f"grasp.steady_from = {steady_from} is outside 0..{n - 1}")
        nan = np.full(n, np.nan)
        return SteadySelection(int(steady_from), SteadyMethod.MANIFEST, nan, np.nan, -1,
                               np.empty((0, 2)), nan, np.empty(0), np.empty(0, int))  # fmt: skip
    K = np.asarray(K, dtype=float)
    uv = kp[..., :2]
    ok = (kp[..., 2] >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)
    if (ok.sum(1) >= cfg.min_points).sum() < 5:
        raise StageError(
            STAGE,
            f"cannot detect the steady phase: fewer than 5 frames have >= "
            f"{cfg.min_points} detected joints" + (f"; {why_missing}" if why_missing else ""),
        )
    coarse, scores, threshold, matched, model = steady_keypoints.detect_onset(uv, ok, K, cfg)
    if matched is None:  # nothing moved before the coarse onset: it stands
        pattern, z = np.empty((0, 2)), np.full(n, np.nan)
        cusum = np.concatenate([np.full(coarse, -np.inf), np.zeros(n + 1 - coarse)])
        onset = coarse
    else:
        pattern, z, cusum, onset = matched
    # the first steady frame anchors the hand's cameras: a frame without the hand detected
    # (dropped detection) has no pose of its own, so the onset moves to the next detected one
    detected = np.flatnonzero(ok.sum(1) >= cfg.min_points)
    keypoint_from, depth_from, share_of = onset, -1, np.empty(0)
    candidate = onset  # the change point taken, before the lag and the move to a detected frame
    by_keypoints = False  # the clean keypoints' onset stood against an earlier depth one
    z_depth, at_end = None, False
    if cfg.depth_onset and depth_frame is not None and T_color_turntable is not None:
        depth_from, share_of, z_depth, at_end = steady_depth.onset_from_depth(
            uv, ok, K, onset, depth_frame, np.asarray(T_color_turntable, float), cfg)
        if depth_from >= 0:  # the lag never carries the onset past frames without the hand
            candidate = depth_from
            want = min(depth_from + cfg.depth_lag_frames, n - 1)
            near = detected[(detected >= depth_from) & (detected <= want)]
            onset = int(near[-1]) if len(near) else want
            clean = _keypoint_noise(uv, ok, scores, keypoint_from, detected)[2] <= (
                cfg.max_noise_share)
            if cfg.later_of_both and clean and keypoint_from > onset:
                onset, candidate, by_keypoints = keypoint_from, keypoint_from, True
    onset = int(detected[np.searchsorted(detected, onset)]) if onset <= detected[-1] else n
    if onset >= n - 2:
        raise StageError(
            STAGE,
            "cannot detect the steady phase: the final frames are not explained by "
            "one rigid hand; set grasp.steady_from in session.json",
        )
    uncertain, moving_to = _uncertainty(uv, ok, scores, onset, detected, cfg,
                                        depth_from >= 0), -1
    if depth_from >= 0 and not uncertain and not by_keypoints:
        uncertain, moving_to = steady_depth.depth_doubt(share_of, z_depth, depth_from, onset,
                                                        at_end, cfg)
    if not uncertain and onset - candidate > cfg.max_undetected_skip:
        uncertain = (f"the hand is not detected in frames {candidate}-{onset - 1}, where the "
                     "grasp may have ended")
    if uncertain and cfg.depth_settled_frames > 0 and len(share_of):
        settled = steady_depth.settled_after_deforming(
            share_of, cfg.depth_strong_share, cfg.depth_settled_share, cfg.depth_settled_frames,
            keypoint_from + cfg.depth_after)
        later = detected[detected >= settled + cfg.depth_lag_frames]
        if settled >= 0 and len(later) and later[0] < n - 2 and later[0] != onset:
            uncertain += (f" (taken at frame {later[0]}, not {onset}: the first of "
                          f"{cfg.depth_settled_frames} frames the depth sees rigid after it saw "
                          "the grasp deforming)")
            onset = int(later[0])
    return SteadySelection(
        steady_from=onset,
        uncertain=uncertain,
        method=SteadyMethod.DETECTED,
        scores_px=scores,
        threshold_px=threshold,
        coarse_from=coarse,
        pattern_px=pattern,
        z=z,
        cusum=cusum,
        model_frames=model,
        keypoint_from=keypoint_from,
        depth_share=share_of,
        depth_from=depth_from,
        depth_moving_to=moving_to,
    )
