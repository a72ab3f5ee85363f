"""The ``joint_solve`` stage's configuration (``hand_sfm.joint_solve``): which path gives the
hand (:class:`HandPath`) and every parameter of the joint solve (:class:`JointSolveConfig`)."""

from __future__ import annotations

from enum import StrEnum

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.hand import fit_hand as fit_hand_stage
from graspcap.tasks.hand.fit_hand import FitHandConfig
from graspcap.tasks.hand_sfm import reconstruct_hand as reconstruct_stage
from graspcap.tasks.hand_sfm.depth_links import DepthLinkConfig
from graspcap.tasks.hand_sfm.hand_depth import HandDepthConfig
from graspcap.tasks.hand_sfm.reconstruct_hand import ReconstructConfig


class HandPath(StrEnum):
    """Which path gives the session's cameras, joints and hand fit."""

    OFF = "off"
    """The staged path alone (``reconstruct_hand`` then ``fit_hand``); the stage returns None."""
    FALLBACK = "fallback"
    """The staged result where the staged path succeeds, the joint solve where it fails."""
    AUTO = "auto"
    """The staged result where its measured detection noise is at most ``auto_noise_share``
    of the hand's image size; the joint solve where the noise is larger or the staged path
    fails."""
    ALWAYS = "always"
    """The joint solve, from the staged solution where there is one, else from the depth."""


class JointSolveConfig(StageConfig):
    mode: HandPath = HandPath.AUTO
    """Which path the build uses (see :class:`HandPath`; ``docs/hand_solver.md`` says why)."""
    auto_noise_share: float = 0.025
    """``auto``: the staged result stands when the detection noise it measured
    (``SfmDiagnostics.noise_sigma_px``) is at most this share of the hand's image size
    (``hand_size_px``). Clean detectors measure 1-2 %, real ones 2.5-5 % (select_steady's
    ``max_noise_share`` draws the same line); there the joint solve's kinematic structure and
    whole-frame rejection are what hold (``docs/hand_solver.md``)."""
    staged: ReconstructConfig = reconstruct_stage.PRESETS["default"]
    """The staged reconstruction run first (its result starts the joint solve). A build sets
    it to its ``reconstruct_hand`` config (``pipeline.tie_configs``): set that one."""
    fit: FitHandConfig = fit_hand_stage.PRESETS["default"]
    """The staged hand fit (and the fit of the depth initialisation's joints); a build sets it
    to its ``fit_hand`` config."""
    min_confidence: float = 0.2
    """Detections with a lower confidence are treated as missing."""
    sigma_px: float = 4.0
    """Pixel sigma of a detection with confidence 1; a detection's sigma is sigma_px / conf."""
    sigma_from_residuals: bool = True
    """After each solve round the detections' sigma is measured from its residuals (the
    median of the kept frames' median residuals, as a per-axis sigma), never below
    ``sigma_px``: a real detector misses by 5-10 % of the hand's image size, 7-27 px on the
    wild rig, and at a fixed 4 px a frame's detections, whose errors are shared by its
    joints, outweigh the depth links that measured its camera (wild tuning ``[80929, 17]``:
    cameras p90 3.7 -> 0.7 deg)."""
    min_sigma_confidence: float = 0.3
    """Confidences are clipped below at this value before scaling the sigma."""
    cauchy_k: float = 2.0
    """Cauchy loss of the reprojections: residuals beyond this many sigmas count ever less
    (a swapped finger, a stray joint)."""
    depth_min_confidence: float = 0.5
    """Only detections at least this confident read the depth."""
    depth_sigma_m: float = 0.003
    """Sigma of a range factor (depth noise plus the skin-to-joint-centre model error)."""
    range_front_weight: float = 0.3
    """Weight of a range residual whose reading lies in front of the joint's skin (the first
    surface on the ray can be the held object or another finger; it is never behind the
    skin): below 1 such readings pull the hand towards the camera less than readings behind
    the skin push it away. Clean readings then place the hand a little deep (0.06-0.08 % of
    its distance in ``tests/tasks/hand_sfm/test_joint_solve.py``)."""
    depth_gate_m: float = 0.015
    """Readings further than this from the start get no range factor in the first round (the
    object or a nearer finger in front of the joint)."""
    range_gate_sigmas: float = 3.0
    """Later rounds keep the readings within this many ``depth_sigma_m`` of the last solve."""
    min_depth_readings: int = 10
    """Fewest range factors that may fix the metric scale; fewer fails the stage."""
    limit_sigma_rad: float = 0.01
    """Sigma of the one-sided joint-limit priors (radians beyond the limit)."""
    rest_sigma_rad: float = 1.0
    """Sigma of the weak pull of every angle towards the rest pose."""
    scale_sigma: float = 0.5
    """Sigma of the log scale around its start (the range factors fix it)."""
    chain_start: bool = True
    """Where the detections are noisy (the staged solve measured more than
    ``auto_noise_share`` of the hand's image size, or failed), start from the cameras chained
    by the depth surfaces (``hand_sfm.odometry_init``: each steady frame's hand-and-object
    surface registered onto its predecessor's, through frames without detections too; the
    staged fit's hand placed on the joints those cameras triangulate, or fitted to them where
    the staged path failed) when the chain poses at least ``chain_min_share`` of the usable
    frames. Noisy detections pose the cameras to several degrees at best (real-detector
    tuning sessions `[9700, i]`: 0.3-31 deg from the staged start); the surfaces chain them to
    0.4-1.7 deg, and the depth links hold them there (`docs/hand_solver.md`, "Session 13").
    Since ``joint_solve/11`` the chain's own registrations also link every pair of consecutive
    solved frames (``joint_starts.chain_links``) and place the frames the solve does not pose
    (``joint_starts.chain_fill``): the links registered from the current solve are dropped
    for a frame the detections pulled more than ``max_correction_deg`` away, and the chain
    held where they did not (wild tuning ``[80929]``, 60 frames: the chain 0.45-1.2 deg, the
    solve from it 0.7-8.3 deg before, `docs/benchmarks.md`, "Session 20")."""
    chain_min_share: float = 0.5
    """Least share of the usable frames the depth chain must pose to be the start."""
    start_references: int = 6
    """Reference frames tried by the depth start (when the staged path fails)."""
    start_min_share: float = 0.3
    """Frames the start's own tests reject are left out of the first solve only when at
    least this share of the posed frames pass them (else the start is too poor to judge by,
    and the robust first solve sees every posed frame)."""
    frame_reject_factor: float = 3.0
    """A frame whose median residual exceeds this many times the median of the frames'
    medians is dropped as a whole (no pose of the hand explains its detections)..."""
    frame_reject_min_px: float = 12.0
    """...and exceeds this many pixels."""
    depth_links: DepthLinkConfig = DepthLinkConfig(stride_px=2)
    """Dense depth links between the kept frames (as in ``reconstruct_hand``: keypoints alone
    leave each camera's tilt a degree loose, the registered surface pins it); measured from
    the last solve's cameras each round, and the surfaces the chain start registers. Needs
    whole depth frames and the turntable pose. The surfaces are sampled every 2 pixels, not
    ``reconstruct_hand``'s 3 (``joint_solve/9``): on the wild rig the hand stands 0.4-1.2 m
    from the camera and holds objects down to 5 cm, so a 3-pixel lattice left a frame 150-260
    points (4-5 mm apart at 0.9 m), each neighbour registration of the chain was 1-3 deg off
    and the chain drifted with the turn. Every 2 pixels, stage 2's cameras on wild tuning
    sessions ``[22921, 1 / 4 / 9]``: 3.69 / 1.96 / 2.85 deg -> 1.25 / 0.70 / 1.21 deg
    (``docs/benchmarks.md``, "Session 15"). The clean path (the staged result) is untouched."""
    motion_sigma_rad: float = 0.0
    """Constant-velocity prior of the virtual cameras: sigma of the change of the per-frame
    rotation (radians) between consecutive kept frames (Cauchy loss; 0 = no motion prior).
    Off: at 0.03 it turned a realistic session's cameras 1.2 -> 1.9 deg off (seed 9400 #4)."""
    motion_sigma_m: float = 0.015
    """...and of the per-frame translation (metres)."""
    frame_depth_gate_m: float = 0.02
    """A frame's depth reading agrees with its solved camera within this (metres)..."""
    frame_min_depth_share: float = 0.25
    """...and a frame with at least ``frame_min_readings`` readings of which fewer than this
    share agree is dropped (a detection on another hand or somewhere else lands on the
    background or the object: measured 0.00 on such frames, 0.42-0.85 on right ones)."""
    frame_min_readings: int = 5
    """Fewest readings for the depth test of a frame."""
    frame_turn_deg_per_frame: float = 8.0
    """Two solved cameras ``g`` frames apart agree when turned at most ``g`` times this from
    each other (or ``frame_turn_min_deg``): the hand turns smoothly in the video, so frames off
    the longest chain of agreeing cameras are dropped (a mirrored detection is explained by a
    camera on the other side of the hand, 100-180 deg away)..."""
    frame_turn_min_deg: float = 20.0
    """...(see ``frame_turn_deg_per_frame``)."""
    frame_rounds: int = 4
    """At most this many solve-and-drop rounds (stops when no frame is dropped)."""
    outlier_px: float = 10.0
    """A detection is an inlier of the result within this many pixels..."""
    outlier_factor: float = 3.0
    """...or within this many times the median residual of the kept frames, whichever is more
    (real detectors miss by 5-10 % of the hand's image size)."""
    ransac_px: float = 8.0
    """RANSAC threshold of the PnP that poses frames the start left unposed, and of the depth
    initialisation."""
    min_points_per_frame: int = 6
    """A frame needs this many detected joints to be solved."""
    min_frames: int = 5
    """At least this many frames must be kept."""
    min_rotation_deg: float = 12.0
    """The stage raises when no kept camera is turned this far from another."""
    min_scale: float = 0.6
    """Smallest plausible hand scale (the model at 1 is an adult mean)."""
    max_scale: float = 1.5
    """Largest plausible hand scale."""
    max_iterations: int = 50
    """Levenberg-Marquardt iterations per solve."""
    relative_tol: float = 1e-5
    """Levenberg-Marquardt stops when an iteration lowers the error by less than this share."""
    depth_refine: HandDepthConfig = HandDepthConfig()
    """The last step where the detections are noisy (the staged result did not stand clean:
    the staged path failed or measured more than ``auto_noise_share``): the solved hand's
    pose, scale and angles refined against its own depth fused over the kept frames, cameras
    and bone factors held (``hand_sfm.hand_depth``). The unrefined hand stands where the step
    fails or grows the median reprojection residual by more than its ``max_reproj_growth``.
    Needs the depth frames. ``enabled = false``: the hand of ``joint_solve/6``."""
