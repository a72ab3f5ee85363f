"""Parameters of the synthetic capture rig, with one preset per difficulty."""

from __future__ import annotations

import json
from enum import StrEnum

from pydantic import Field

from graspcap.tasks.core.config import StageConfig

STAGE_VERSION = "synth/2"


class Difficulty(StrEnum):
    """How hard the generated sessions are for the pipeline (sensor noise, detector errors)."""

    EASY = "easy"
    REALISTIC = "realistic"
    HARD = "hard"
    REAL_DETECTOR = "real-detector"
    WILD = "wild"


class WildHandConfig(StageConfig):
    """The rig's own hand (:mod:`graspcap.synth.wild_hand`), drawn per session.

    Not the pipeline's 20-DoF model with other numbers: a twisted, offset MCP axis, a
    two-axis thumb CMC with its own twist, a palm arch that cups as the hand closes,
    per-segment capsules set off the bone axis. Ratios multiply the template's value;
    every range is (low, high), sampled uniformly and independently.
    """

    size: tuple[float, float] = (0.8, 1.2)
    """Overall size of the hand (every length and radius), relative to the template."""
    bone_length: tuple[float, float] = (0.85, 1.15)
    """Each of the 20 bones (5 metacarpals placing the finger bases, 15 phalanges) on its own."""
    thickness: tuple[float, float] = (0.8, 1.25)
    """Finger and palm radii (one factor per session, then +-5 % per segment)."""
    palm_width: tuple[float, float] = (0.85, 1.15)
    """Spread of the knuckles and the thumb base across the palm."""
    thumb_base_shift_m: float = 0.008
    """Largest shift of the thumb CMC along each palm axis (m, before the size)."""
    thumb_opposition_deg: tuple[float, float] = (35.0, 80.0)
    """Pronation of the thumb pad towards the index finger."""
    abduction_deg: tuple[float, float] = (-8.0, 10.0)
    """Per-session spread of the fingers added to every grasp (positive: wider)."""
    mcp_twist_deg: tuple[float, float] = (-12.0, 12.0)
    """Tilt of each MCP flexion axis away from the perpendicular of the bone (per finger)."""
    palm_arch_deg: tuple[float, float] = (5.0, 20.0)
    """Transverse arch of the knuckle row; the ring and little metacarpals also flex by up
    to this much as the fingers close (palm cupping)."""
    capsule_offset: tuple[float, float] = (0.05, 0.2)
    """Offset of each phalanx's capsule axis from the joint centres towards the back of
    the finger, as a share of the capsule's radius."""


class CaptureConfig(StageConfig):
    """Randomised capture geometry: camera model, distances and the operator's motion."""

    cameras: tuple[tuple[int, int, float], ...] = (
        (640, 480, 615.0), (960, 540, 540.0), (1280, 720, 920.0))
    """(width, height, focal px) to choose from: a 640x480 RGB-D colour stream (RealSense
    D4xx colour, fx ~ 615), Kinect v2 colour (1920x1080, fx ~ 1080) scaled to 960x540, and a
    720p webcam / RealSense 1280x720 (fx ~ 920)."""
    focal_jitter: float = 0.04
    """The focal length varies by +- this share between units."""
    hand_distance_m: tuple[float, float] = (0.4, 1.2)
    """Distance of the palm from the colour camera at the first steady frame."""
    turntable_distance_m: tuple[float, float] = (0.6, 1.0)
    """Distance from the colour camera to the platter centre."""
    camera_elevation_deg: tuple[float, float] = (15.0, 45.0)
    """Angle of the camera's optical axis below the horizontal (a Kinect on a tripod looks
    at the hand nearly level; a camera over the desk looks down)."""
    rotation_deg: tuple[float, float] = (20.0, 180.0)
    """Total rotation of the hand over the steady frames (largest angle between two of
    its poses), turned one way then back by a random share, either direction."""
    translation_m: float = 0.1
    """Largest translation of hand and object (per axis) away from the steady pose."""
    speed_irregularity: float = 0.8
    """Frame-to-frame speed varies by up to this share around its mean (no blur)."""
    max_lift_m: float = 0.3
    """Highest the operator lifts hand and object above the steady pose while turning them."""


class LensConfig(StageConfig):
    """Radial-tangential (OpenCV k1 k2 p1 p2 k3) distortion of the colour camera.

    Colour, aligned depth and the clean keypoints are rendered through it; the manifest's
    ``color_camera.dist`` carries it. Sampled per session.
    """

    k1: tuple[float, float] = (-0.2, 0.1)
    """Second-order radial coefficient (webcams and Kinect v2 colour lie in this range)."""
    k2: tuple[float, float] = (-0.05, 0.12)
    """Fourth-order radial coefficient."""
    p: float = 0.0015
    """Largest |p1|, |p2| (tangential; decentred lens elements)."""
    k3: tuple[float, float] = (-0.03, 0.03)
    """Sixth-order radial coefficient."""


class ObjectSetConfig(StageConfig):
    """Which objects a session holds and how big they are."""

    names: tuple[str, ...] = (
        "mug", "bottle", "spray_bottle", "carton", "drill",
        "bulb", "small_box", "glass", "remote", "ball", "can")
    """Procedural objects drawn from (see :data:`graspcap.synth.objects.OBJECT_NAMES`)."""
    extent_m: tuple[float, float] = (0.05, 0.30)
    """Largest extent of the object; each object is scaled within the part of this range
    its shape allows (:data:`graspcap.synth.objects.EXTENT_RANGE_M`)."""


class RealDetectorConfig(StageConfig):
    """2D detections as a real detector on real grasping hands gives them.

    Calibrated to MediaPipe on FreiHAND grasps (misses by 9.5-12 px on 105-110 px hands,
    ~10 %, 2 of 8 gross failures) and ContactPose's optimiser (284 of 507 frames rejected,
    3.9 px inlier reprojection at a 7.5 px threshold). The hand's image size is the
    diagonal of its keypoints' bounding box.
    """

    error_share: tuple[float, float] = (0.05, 0.10)
    """Per-session mean per-joint error as a share of the hand's image size."""
    occluded_factor: float = 2.0
    """Error multiplier on joints hidden behind the object."""
    correlation: tuple[float, float] = (0.6, 0.9)
    """AR(1) coefficient of each joint's error from one frame to the next."""
    frame_failure_rate: tuple[float, float] = (0.08, 0.25)
    """Per-session share of frames where the whole detection is wrong: the hand somewhere
    else, mirrored, or another hand (confidences as high as good frames)."""
    swap_rate: float = 0.08
    """Share of frames with two neighbouring fingers' labels exchanged."""
    missing_run_rate: float = 0.025
    """Chance per frame that a run of frames without detection starts."""
    missing_run_frames: tuple[int, int] = (2, 8)
    """Length of a run of missing frames."""
    joint_missing_rate: float = 0.05
    """Share of single joints not reported (confidence 0)."""
    confidence_noise: float = 0.2
    """Spread of the confidence around its (weak) dependence on the error."""


class KinectDepthConfig(StageConfig):
    """Time-of-flight depth as a Kinect v2 registered to the colour camera gives it."""

    sigma_1m_m: float = 0.0015
    """Axial noise at 1 m (standard deviation); it grows with ``z ** sigma_exponent``."""
    sigma_exponent: float = 1.5
    """Growth of the axial noise with distance."""
    grazing_cos_min: float = 0.25
    """Pixels whose |cos| of incidence falls below this read as missing (0)."""
    dropout_rate: tuple[float, float] = (0.005, 0.02)
    """Per-session share of single pixels randomly missing."""
    dropout_blobs: int = 6
    """Missing patches (5-20 px wide, low-reflectance spots) per image."""
    flying_pixel_rate: float = 0.6
    """Share of pixels at a depth edge (> 2 cm jump) that read a depth between the sides."""
    misalignment_px: tuple[float, float] = (1.0, 3.0)
    """Offset of the depth image from the colour image (one direction per session)."""


class SynthConfig(StageConfig):
    """Everything that shapes a synthetic session; ranges are (low, high), sampled uniformly."""

    difficulty: Difficulty = Difficulty.REALISTIC
    """Recorded in the ground truth; the noise fields below carry the actual effect."""

    frames: int = Field(120, ge=4)
    """Number of grasp-video frames (at least 4: adjustment, then steady frames)."""
    fps: float = 30.0
    """Grasp-video frame rate."""
    width: int = 640
    """Colour (and aligned depth) image width in pixels."""
    height: int = 480
    """Colour (and aligned depth) image height in pixels."""
    f_px: float = 615.0
    """Colour camera focal length (fx = fy) in pixels; the principal point is the image centre."""

    thermal_width: int = 320
    """Thermal image width in pixels."""
    thermal_height: int = 256
    """Thermal image height in pixels."""
    thermal_f_px: float = 360.0
    """Thermal camera focal length in pixels."""
    thermal_offset_m: tuple[float, float] = (0.03, 0.06)
    """Distance of the thermal camera from the colour camera."""

    scan_views: tuple[int, int] = (8, 16)
    """Number of turntable views in the scan, evenly spaced over 360 deg."""
    adjust_fraction: tuple[float, float] = (0.15, 0.25)
    """Share of the grasp video taken by grasp adjustment (before the first steady frame)."""
    write_steady_from: bool = False
    """Write the true first steady frame into session.json instead of null (detect it)."""

    camera_distance_m: tuple[float, float] = (0.6, 0.8)
    """Distance from the colour camera to the platter centre."""
    camera_elevation_deg: tuple[float, float] = (30.0, 45.0)
    """Angle of the camera's optical axis below the horizontal."""
    platter_radius_m: float = 0.15
    """Turntable platter radius."""
    platter_thickness_m: float = 0.012
    """Turntable platter thickness (it rests on the table plane)."""
    object_offset_m: float = 0.03
    """Largest offset of the object from the platter centre."""

    hand_distance_m: tuple[float, float] = (0.35, 0.6)
    """Depth of the palm centre in the colour camera at the first steady frame."""
    adjust_rotation_deg: float = 35.0
    """Largest rotation of the object during grasp adjustment (the T_adj rotation)."""
    motion_rotation_deg: float = 60.0
    """Largest rotation of hand and object away from the steady pose during the video."""
    motion_translation_m: float = 0.04
    """Largest translation of hand and object away from the steady pose during the video."""
    hand_scale_spread: float = 0.1
    """Participants' hand scales lie in 1 +- this."""
    participants: int = 12
    """Number of distinct participant ids (p01 ...) drawn from."""

    grasp_attempts: int = 80
    """Candidate palm placements tried before giving up."""
    min_touching_fingers: int = 3
    """A grasp needs at least this many fingers touching the object."""
    touch_tolerance_m: float = 0.001
    """A capsule within this distance of the surface touches it."""
    max_penetration_m: float = 0.0015
    """Deepest allowed penetration of a hand capsule into the object."""

    depth_sigma_m: float = 0.0015
    """Axial depth noise (standard deviation) at 0.7 m; it grows with z squared."""
    grazing_cos_min: float = 0.2
    """Pixels whose |cos| of incidence falls below this read as missing (0)."""
    dropout_rate: float = 0.003
    """Share of pixels randomly missing in each depth image."""

    kp_sigma_px: float = 2.5
    """Keypoint noise, per coordinate, for inliers."""
    kp_outlier_rate: float = 0.05
    """Share of detected keypoints displaced far away with high confidence."""
    kp_outlier_px: tuple[float, float] = (20.0, 80.0)
    """Displacement of an outlier keypoint."""
    kp_missing_rate: float = 0.03
    """Share of keypoints not detected (confidence 0)."""
    kp_no_person_rate: float = 0.03
    """Share of frames with no hand detected (empty people list)."""
    kp_swap_rate: float = 0.0
    """Share of frames where two neighbouring fingers swap labels."""

    thermal_ambient_k: float = 295.0
    """Ambient (object and background) temperature."""
    thermal_rise_k: float = 3.5
    """Temperature rise of a fully contacted surface point."""
    thermal_noise_k: float = 0.07
    """Thermal sensor noise (standard deviation)."""
    thermal_blur_px: float = 0.7
    """Gaussian blur sigma of the thermal optics."""

    object_faces: int = 15000
    """Target face count of procedural objects (kept within 5k-30k)."""
    jpeg_quality: int = 90
    """Quality of the colour JPEGs."""

    wild_hand: WildHandConfig | None = None
    """The rig's own randomised hand instead of the 20-DoF model (None: the 20-DoF model
    with one scale per participant, as in ``synth/2``)."""
    capture: CaptureConfig | None = None
    """Randomised cameras, distances and motion (None: the fixed fields above)."""
    lens: LensConfig | None = None
    """Colour lens distortion (None: a pinhole, ``dist`` all zero)."""
    object_set: ObjectSetConfig | None = None
    """Objects and their sizes (None: the five original objects at their own size)."""
    detector: RealDetectorConfig | None = None
    """The real-detector keypoint model (None: the ``kp_*`` fields above)."""
    kinect_depth: KinectDepthConfig | None = None
    """Kinect v2-like depth (None: the ``depth_*`` and ``dropout_rate`` fields above)."""

    def canonical_json(self) -> str:
        """As :meth:`StageConfig.canonical_json`, leaving out the randomisation fields that
        are off, so that the presets of ``synth/2`` keep their digest."""
        data = self.model_dump(mode="json")
        for name in RANDOMISATION_FIELDS:
            if data[name] is None:
                del data[name]
        return json.dumps(data, sort_keys=True, separators=(",", ":"))


RANDOMISATION_FIELDS = ("wild_hand", "capture", "lens", "object_set", "detector",
                         "kinect_depth")


_EASY = SynthConfig(
    difficulty=Difficulty.EASY,
    depth_sigma_m=0.001,
    grazing_cos_min=0.1,
    dropout_rate=0.0,
    kp_sigma_px=1.0,
    kp_outlier_rate=0.0,
    kp_missing_rate=0.0,
    kp_no_person_rate=0.0,
    kp_swap_rate=0.0,
    motion_rotation_deg=45.0,
)
_REALISTIC = SynthConfig()
_HARD = SynthConfig(
    difficulty=Difficulty.HARD,
    depth_sigma_m=0.0025,
    grazing_cos_min=0.3,
    dropout_rate=0.01,
    kp_sigma_px=4.0,
    kp_outlier_rate=0.12,
    kp_missing_rate=0.06,
    kp_no_person_rate=0.06,
    kp_swap_rate=0.05,
    thermal_noise_k=0.1,
    thermal_blur_px=1.0,
)

_REAL_DETECTOR = SynthConfig(difficulty=Difficulty.REAL_DETECTOR, detector=RealDetectorConfig())
_WILD = SynthConfig(
    difficulty=Difficulty.WILD,
    wild_hand=WildHandConfig(),
    capture=CaptureConfig(),
    lens=LensConfig(),
    object_set=ObjectSetConfig(),
    detector=RealDetectorConfig(),
    kinect_depth=KinectDepthConfig(),
    thermal_noise_k=0.1,
)

PRESETS: dict[str, SynthConfig] = {
    "default": _REALISTIC,
    "easy": _EASY,
    "realistic": _REALISTIC,
    "hard": _HARD,
    "real-detector": _REAL_DETECTOR,
    "wild": _WILD,
}
"""Profiles by name: ``easy``, ``realistic`` (the default), ``hard`` (``synth/2``'s
difficulties), ``real-detector`` (realistic with the real-detector keypoint model) and
``wild`` (every randomisation factor on)."""
