"""Parameters of the synthetic capture rig, with one preset per difficulty."""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field

from graspcap.tasks.core.config import StageConfig

STAGE_VERSION = "synth/2"


class Difficulty(StrEnum):
    """How hard the generated sessions are for the pipeline (sensor noise, detector errors)."""

    EASY = "easy"
    REALISTIC = "realistic"
    HARD = "hard"


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

PRESETS: dict[str, SynthConfig] = {
    "default": _REALISTIC,
    "easy": _EASY,
    "realistic": _REALISTIC,
    "hard": _HARD,
}
