"""The capture-session manifest (``session.json``), format ``grasp-capture-session/1``.

Typed, frozen models that mirror ``/work/shared/design/session-format.md`` and the JSON
Schema beside this file (``session.schema.json``, for rig builders). Unknown keys are
rejected at every level. The models add the checks JSON Schema cannot express: a valid
intrinsic matrix (finite, principal point inside the image, a field of view a lens can
have), bounded distortion coefficients, rigid ``T_*`` transforms, frame patterns made of
literal text and ``{index}`` fields with an integer format spec, ``steady_from < count``,
and the size limits of :class:`SessionLimits` (frames, scan views, formatted path length).

Load a manifest with ``SessionManifest.model_validate(json.loads(text))`` (pass
``context={"limits": SessionLimits(...)}`` for other limits than the defaults); the session
loader (``graspcap.tasks.session.load_session``) adds the file checks and readers.
"""

from __future__ import annotations

import json
import math
import re
import string
from enum import StrEnum
from importlib import resources
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    ValidationInfo,
    field_validator,
    model_validator,
)

from graspcap.schemas.transforms import rigidity_problems

FORMAT = "grasp-capture-session/1"
"""The only manifest format this module reads."""

SCHEMA_RESOURCE = "session.schema.json"

RELATIVE_PATH_RE = r"^(?!/)(?!.*(?:^|/)\.\.(?:/|$))[^\x00-\x1f\x7f]+(?![\s\S])"
r"""A non-empty relative POSIX path without a ``..`` component or a control character (same
regex in the JSON Schema; ``(?![\s\S])`` ends the string, where ``$`` would let a trailing
newline through in Python)."""

MESH_PATH_RE = (
    r"^(?!/)(?!.*(?:^|/)\.\.(?:/|$))[^\x00-\x1f\x7f]+\.("
    r"[Pp][Ll][Yy]|[Oo][Bb][Jj]|[Ss][Tt][Ll])(?![\s\S])"
)
"""A relative path (as above) to a PLY, OBJ or STL mesh (any letter case)."""

INDEX_FIELD_RE = r"\{index[^{}]*\}"
"""A frame pattern holds at least one ``{index...}`` replacement field."""

INDEX_SPEC_RE = r"^(?:[^{}]?[<>=^])?0?(?P<width>[0-9]*)d?$"
"""The format spec an ``{index}`` field may carry: optional fill/align, zero padding, a
width and the ``d`` type (``{index}``, ``{index:06d}``, ``{index:>4}``)."""

SESSION_ID_RE = r"^(?!\.)[A-Za-z0-9._-]{1,128}(?![\s\S])"
r"""A session id: 1-128 characters from ``A-Z a-z 0-9 . _ -``, not starting with ``.``
(``(?![\s\S])`` ends the string in both ECMA and Python regexes; ``$`` would let a
trailing newline through in Python). The same regex is in the JSON Schema."""

SESSION_ID_RULE = "1-128 characters from A-Z a-z 0-9 . _ -, not starting with '.'"

DIST_LENGTHS = (4, 5, 8, 12, 14)
"""Lengths of OpenCV distortion vectors (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]])."""

SKEW_TOL = 1e-2
"""Largest accepted ``|K[0][1]| / fx`` (a small skew is tolerated, a large one is a typo)."""

FOV_DEG = (10.0, 170.0)
"""Accepted horizontal field of view ``2 atan(width / (2 fx))``, degrees: a telephoto of
10 degrees to a fisheye-like 170; outside it the focal length is a typo or in other units."""

ASPECT_MAX = 4.0
"""Largest accepted ``fy / fx`` or ``fx / fy`` (pixels are near square on real sensors)."""

DIST_MAX = 1000.0
"""Largest accepted ``|coefficient|`` of the distortion vector. Real calibrations stay far
below (a Kinect or webcam: ``|k1|, |k2|`` under 1; OpenCV's rational model: tens)."""

DEPTH_SCALE_RANGE = (1e-6, 0.1)
"""Accepted ``depth_scale_m``: from a micrometre to 10 cm per depth unit (millimetres are 1e-3)."""


class SessionLimits(BaseModel):
    """Bounds on what one session may hold, so that a malformed manifest or file fails with
    the limit named instead of exhausting time or memory. Real captures stay far below the
    defaults; raise one (``LoadSessionConfig.limits``) for a capture that legitimately needs
    more. Documented in ``docs/session-limits.md``."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    max_frames: int = Field(100_000, ge=1)
    """Largest ``grasp.count`` (100,000 frames is 55 minutes at 30 fps)."""
    max_scan_views: int = Field(720, ge=1)
    """Most ``scan.views`` (720 is one view every half degree)."""
    max_path_chars: int = Field(1024, ge=16)
    """Longest path, in characters, that a frame pattern may format to (checked from the
    pattern before formatting it)."""
    max_manifest_bytes: int = Field(4 * 2**20, ge=1024)
    """Largest ``session.json``, bytes."""
    max_keypoint_bytes: int = Field(8 * 2**20, ge=1024)
    """Largest OpenPose keypoint JSON file, bytes (a real one is a few kilobytes)."""
    max_json_depth: int = Field(64, ge=8)
    """Deepest nesting of arrays and objects in ``session.json`` or a keypoint file (both
    need under 10 levels)."""
    max_image_pixels: int = Field(40_000_000, ge=1)
    """Most pixels (width x height) of a camera and of any image, as its header claims
    (checked before decoding; 8K video is 33 million)."""
    max_mesh_faces: int = Field(1_000_000, ge=1)
    """Most faces of the object mesh (the largest real scans in ``shared/data``, ContactDB's
    controller and apple, have 75,788 and 59,354)."""
    max_mesh_vertices: int = Field(1_000_000, ge=1)
    """Most vertices of the object mesh (the same scans: 37,313 and 29,681)."""
    max_mesh_bytes: int = Field(512 * 2**20, ge=1024)
    """Largest object mesh file, bytes."""


DEFAULT_LIMITS = SessionLimits()
"""The limits every check uses unless given others."""


def limits_of(info: ValidationInfo | None) -> SessionLimits:
    """The :class:`SessionLimits` in a validation context, else :data:`DEFAULT_LIMITS`."""
    context = getattr(info, "context", None)
    limits = context.get("limits") if isinstance(context, dict) else None
    return limits if isinstance(limits, SessionLimits) else DEFAULT_LIMITS


def _integral_float_to_int(value: Any) -> Any:
    """JSON Schema counts 3.0 as an integer; accept it the same way (never bools or strings)."""
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


Number = Annotated[float, Strict(), AllowInfNan(False)]
"""A finite JSON number (ints accepted, bools, strings, NaN and infinity rejected)."""

Int = Annotated[int, BeforeValidator(_integral_float_to_int), Strict()]
"""A JSON integer (``3`` or ``3.0``; bools and strings rejected)."""

Text = Annotated[str, Strict(), Field(min_length=1)]
"""A non-empty string."""

RelPath = Annotated[str, Strict(), Field(pattern=RELATIVE_PATH_RE)]
"""A path relative to the session directory that stays inside it."""

Row3 = tuple[Number, Number, Number]
Row4 = tuple[Number, Number, Number, Number]
Matrix3 = tuple[Row3, Row3, Row3]
Matrix4 = tuple[Row4, Row4, Row4, Row4]


class Hand(StrEnum):
    """Which hand grasps the object."""

    RIGHT = "right"
    LEFT = "left"


class _Model(BaseModel):
    model_config = ConfigDict(
        frozen=True, extra="forbid", use_attribute_docstrings=True, regex_engine="python-re"
    )


def _check_rigid(value: Matrix4) -> Matrix4:
    problems = rigidity_problems(np.asarray(value, dtype=float))
    if problems:
        raise ValueError("not a rigid transform: " + "; ".join(problems))
    return value


class Camera(_Model):
    """Pinhole intrinsics with OpenCV distortion, shared by the colour and thermal cameras."""

    width: Annotated[Int, Field(ge=1)]
    """Image width in pixels."""
    height: Annotated[Int, Field(ge=1)]
    """Image height in pixels."""
    K: Matrix3
    """3x3 intrinsic matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels (OpenCV)."""
    dist: tuple[Number, ...]
    """OpenCV distortion coefficients: 4, 5, 8, 12 or 14 numbers (k1 k2 p1 p2 k3 ...)."""

    @field_validator("K")
    @classmethod
    def _valid_intrinsics(cls, K: Matrix3, info: ValidationInfo) -> Matrix3:
        (fx, s, cx), (k10, fy, cy), last = K
        problems = []
        if fx <= 0 or fy <= 0:
            problems.append(f"focal lengths must be > 0 (fx={fx}, fy={fy})")
        elif abs(s) > SKEW_TOL * fx:
            problems.append(f"skew K[0][1]={s} is larger than {SKEW_TOL} * fx")
        if k10 != 0 or tuple(last) != (0, 0, 1):
            problems.append("K[1][0] must be 0 and the last row [0, 0, 1]")
        width, height = info.data.get("width"), info.data.get("height")
        if width is not None and fx > 0 and fy > 0:
            fov = math.degrees(2 * math.atan(width / (2 * fx)))
            if not FOV_DEG[0] <= fov <= FOV_DEG[1]:
                problems.append(
                    f"fx={fx:.6g} gives a horizontal field of view of {fov:.3g} degrees over "
                    f"{width} pixels; a lens has {FOV_DEG[0]:g} to {FOV_DEG[1]:g} (focal length "
                    "in pixels, not mm?)")
            elif not 1 / ASPECT_MAX <= fy / fx <= ASPECT_MAX:
                problems.append(f"fy/fx = {fy / fx:.3g}, pixels are not that far from square")
        if width is not None and not 0 <= cx <= width:
            problems.append(f"principal point cx={cx} outside the image width {width}")
        if height is not None and not 0 <= cy <= height:
            problems.append(f"principal point cy={cy} outside the image height {height}")
        if problems:
            raise ValueError("invalid intrinsic matrix: " + "; ".join(problems))
        return K

    @field_validator("dist")
    @classmethod
    def _dist_length(cls, dist: tuple[float, ...]) -> tuple[float, ...]:
        if len(dist) not in DIST_LENGTHS:
            raise ValueError(f"{len(dist)} coefficients; OpenCV takes {DIST_LENGTHS}")
        big = [(i, v) for i, v in enumerate(dist) if abs(v) > DIST_MAX]
        if big:
            i, v = big[0]
            raise ValueError(f"coefficient [{i}] = {v:.3g} is beyond +-{DIST_MAX:g}; real "
                             "lens distortion stays far below (k1, k2 of a webcam are under 1)")
        return dist

    @field_validator("height")
    @classmethod
    def _pixels(cls, height: int, info: ValidationInfo) -> int:
        width, limit = info.data.get("width"), limits_of(info).max_image_pixels
        if width is not None and width * height > limit:
            raise ValueError(f"{width}x{height} is more than the {limit} pixels of "
                             "SessionLimits.max_image_pixels")
        return height

    def K_array(self) -> np.ndarray:
        """The intrinsic matrix, ``(3, 3) float64``."""
        return np.array(self.K, dtype=float)

    def dist_array(self) -> np.ndarray:
        """The distortion coefficients, ``(n,) float64``."""
        return np.array(self.dist, dtype=float)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height


class ColorCamera(Camera):
    """The RGB-D camera; its frame is the world frame ``w``. Depth is aligned to it."""


class ThermalCamera(Camera):
    """The thermal camera of the turntable scan, calibrated against the colour camera."""

    T_color_thermal: Matrix4
    """4x4 rigid transform mapping thermal-camera points into the colour camera frame (m)."""

    _rigid = field_validator("T_color_thermal")(_check_rigid)

    def T_color_thermal_array(self) -> np.ndarray:
        """``T_color_thermal`` as ``(4, 4) float64``."""
        return np.array(self.T_color_thermal, dtype=float)


class Turntable(_Model):
    """The turntable: origin at the centre of the platter top, z up along the rotation axis."""

    T_color_turntable: Matrix4
    """4x4 rigid transform mapping turntable points into the colour camera frame (m)."""

    _rigid = field_validator("T_color_turntable")(_check_rigid)

    def T_color_turntable_array(self) -> np.ndarray:
        """``T_color_turntable`` as ``(4, 4) float64``."""
        return np.array(self.T_color_turntable, dtype=float)


class Stage1(_Model):
    """The object alone on the turntable, before the grasp."""

    depth: RelPath
    """Depth PNG (uint16, millimetres, colour camera size), relative path."""
    color: RelPath | None = None
    """Optional colour image (8-bit, 3 channels, colour camera size), relative path."""


def pattern_problem(pattern: str, count: int | None, max_chars: int) -> str | None:
    """Why ``pattern`` is not a frame pattern, found without formatting it, or None.

    Allowed: literal text and ``{index}`` fields whose format spec matches
    :data:`INDEX_SPEC_RE`, formatting (for frames below ``count``) to at most
    ``max_chars`` characters.
    """
    try:
        parts = list(string.Formatter().parse(pattern))
    except ValueError as exc:
        return f"is not a format pattern ({exc}; write a literal brace as {{{{ or }}}})"
    fields, length = 0, 0
    digits = len(str(max(count - 1, 0))) if count is not None else 20
    for literal, name, spec, conversion in parts:
        length += len(literal)
        if name is None:
            continue
        if name != "index" or conversion is not None:
            field = "{" + name + ("!" + conversion if conversion else "") + "}"
            return (f"field {field[:60]} is not allowed: a frame pattern holds only "
                    "{index} fields, e.g. {index:06d}")
        match = re.fullmatch(INDEX_SPEC_RE, spec or "")
        if match is None:
            return (f"format spec {spec[:60]!r} of {{index}} is not an integer format "
                    "(e.g. 06d)")
        width = int(match["width"] or 0) if len(match["width"]) <= 9 else max_chars + 1
        fields += 1
        length += max(width, digits + 1)
        if length > max_chars:
            break
    if not fields:
        return "a frame pattern needs an {index...} field, e.g. {index:06d}"
    if length > max_chars:
        return (f"formats to paths longer than {max_chars} characters "
                "(SessionLimits.max_path_chars)")
    return None


def _check_frame_pattern(pattern: str | None, info: ValidationInfo) -> str | None:
    if pattern is None:
        return None
    count = info.data.get("count")
    problem = pattern_problem(pattern, count, limits_of(info).max_path_chars)
    if problem:
        raise ValueError(problem)
    first, second = pattern.format(index=0), pattern.format(index=1)
    if first == second:
        raise ValueError("gives the same path for every frame")
    if not re.search(RELATIVE_PATH_RE, first):
        raise ValueError(f"formats to {first!r}, not a relative path inside the session")
    return pattern


FramePattern = Annotated[str, Strict(), Field(pattern=RELATIVE_PATH_RE)]
"""A relative path pattern with an ``{index...}`` field (checked by ``_check_frame_pattern``)."""


class Grasp(_Model):
    """The grasp video: per-frame files named by format patterns over ``index``."""

    fps: Annotated[Number, Field(gt=0)]
    """Frame rate of the video, frames per second."""
    count: Annotated[Int, Field(ge=1)]
    """Number of frames; the frame index runs over 0 .. count-1 (at most
    ``SessionLimits.max_frames``)."""
    depth: FramePattern
    """Pattern of the aligned depth PNGs (uint16 mm), e.g. ``grasp/depth/{index:06d}.png``."""
    color: FramePattern | None = None
    """Pattern of the colour frames (8-bit, 3 channels); optional when keypoints are given."""
    keypoints: FramePattern | None = None
    """Pattern of OpenPose JSON files per frame; without it the builder detects keypoints."""
    steady_from: Annotated[Int, Field(ge=0)] | None = None
    """First frame after grasp adjustment (hand held still); null means detect it."""

    _patterns = field_validator("depth", "color", "keypoints")(_check_frame_pattern)

    @field_validator("count")
    @classmethod
    def _count_limit(cls, count: int, info: ValidationInfo) -> int:
        limit = limits_of(info).max_frames
        if count > limit:
            raise ValueError(f"{count} frames is more than the {limit} of "
                             "SessionLimits.max_frames")
        return count

    @field_validator("steady_from")
    @classmethod
    def _steady_in_range(cls, value: int | None, info: ValidationInfo) -> int | None:
        count = info.data.get("count")
        if value is not None and count is not None and value >= count:
            raise ValueError(f"steady_from {value} is not a frame index below count {count}")
        return value

    @model_validator(mode="after")
    def _color_or_keypoints(self) -> Grasp:
        if self.color is None and self.keypoints is None:
            raise ValueError("needs at least one of grasp.color and grasp.keypoints")
        return self

    def frame_path(self, kind: Literal["color", "depth", "keypoints"], index: int) -> str | None:
        """The relative path of frame ``index`` for ``kind``; None when the pattern is absent."""
        if not 0 <= index < self.count:
            raise IndexError(f"frame {index} outside 0..{self.count - 1}")
        pattern = getattr(self, kind)
        return None if pattern is None else pattern.format(index=index)


class ScanView(_Model):
    """One view of the post-grasp turntable scan."""

    thermal: RelPath
    """Thermal PNG (uint16 centi-kelvin, thermal camera size), relative path."""
    depth: RelPath
    """Depth PNG aligned to the colour camera (uint16 mm, colour camera size), relative path."""
    angle_deg: Number
    """Platter rotation about the turntable z axis (right-handed) from angle 0, degrees."""


class Scan(_Model):
    """The post-grasp turntable scan: thermal and depth views at known platter angles."""

    views: tuple[ScanView, ...]
    """The views, at least one."""

    @field_validator("views")
    @classmethod
    def _at_least_one(cls, views: tuple[ScanView, ...],
                      info: ValidationInfo) -> tuple[ScanView, ...]:
        # Not Field(min_length=1): pydantic would add a bogus "0 items" error to item errors.
        if not views:
            raise ValueError("needs at least one view")
        limit = limits_of(info).max_scan_views
        if len(views) > limit:
            raise ValueError(f"{len(views)} views is more than the {limit} of "
                             "SessionLimits.max_scan_views")
        return views

    def angles_rad(self) -> np.ndarray:
        """The platter angle of every view, ``(n,) float64`` radians."""
        return np.array([math.radians(v.angle_deg) for v in self.views])


class SessionManifest(_Model):
    """``session.json``: the manifest of one capture session."""

    format: Literal["grasp-capture-session/1"]
    """Format and version of this manifest; exactly ``grasp-capture-session/1``."""
    session_id: Annotated[str, Strict(), Field(pattern=SESSION_ID_RE)]
    """Identifier of the session, unique in a dataset (e.g. ``p03-mug-use-01``): 1-128
    characters from ``A-Z a-z 0-9 . _ -``, not starting with ``.``; data, never a path."""
    participant: Text
    """Identifier of the participant (e.g. ``p03``)."""
    object_id: Text
    """Identifier of the object (e.g. ``mug``)."""
    intent: Text
    """Grasp intent (e.g. ``use`` or ``handoff``)."""
    hand: Hand
    """The hand that grasps the object: ``right`` or ``left``."""
    object_mesh: Annotated[str, Strict(), Field(pattern=MESH_PATH_RE)]
    """Object mesh in its own frame, metres (PLY, OBJ or STL), relative path."""
    color_camera: ColorCamera
    """The RGB-D camera (world frame)."""
    depth_scale_m: Annotated[Number, Field(gt=0)]
    """Metres per depth-PNG unit (0.001 for millimetres; 1e-6 .. 0.1 accepted)."""

    @field_validator("depth_scale_m")
    @classmethod
    def _plausible_scale(cls, scale: float) -> float:
        low, high = DEPTH_SCALE_RANGE
        if not low <= scale <= high:
            raise ValueError(f"{scale:.3g} m per depth unit is outside {low:g} .. {high:g} "
                             "(0.001 for millimetres)")
        return scale
    thermal_camera: ThermalCamera
    """The thermal camera and its pose relative to the colour camera."""
    turntable: Turntable
    """The turntable and its pose relative to the colour camera."""
    stage1: Stage1
    """Stage 1: the object alone on the turntable."""
    grasp: Grasp
    """The grasp video."""
    scan: Scan
    """The post-grasp thermal turntable scan."""


def json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of ``session.json``, shipped as package data."""
    text = resources.files("graspcap.schemas").joinpath(SCHEMA_RESOURCE).read_text("utf-8")
    return json.loads(text)
