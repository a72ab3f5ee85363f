"""The capture-session manifest (``session.json``), format ``grasp-capture-session/1``.

Typed, frozen models that mirror ``/work/shared/design/session-format.md`` and the JSON
Schema beside this file (``session.schema.json``, for rig builders). Unknown keys are
rejected at every level. The models add the checks JSON Schema cannot express: a valid
intrinsic matrix (finite, principal point inside the image), rigid ``T_*`` transforms,
frame patterns that format with ``index`` alone, and ``steady_from < count``.

Load a manifest with ``SessionManifest.model_validate(json.loads(text))``; the session
loader (``graspcap.tasks.session.load_session``) adds the file checks and readers.
"""

from __future__ import annotations

import json
import math
import re
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

RELATIVE_PATH_RE = r"^(?!/)(?!.*(?:^|/)\.\.(?:/|$)).+$"
"""A non-empty relative POSIX path without a ``..`` component (same regex in the JSON Schema)."""

MESH_PATH_RE = r"^(?!/)(?!.*(?:^|/)\.\.(?:/|$)).+\.([Pp][Ll][Yy]|[Oo][Bb][Jj]|[Ss][Tt][Ll])$"
"""A relative path (as above) to a PLY, OBJ or STL mesh (any letter case)."""

INDEX_FIELD_RE = r"\{index[^{}]*\}"
"""A frame pattern holds at least one ``{index...}`` replacement field."""

DIST_LENGTHS = (4, 5, 8, 12, 14)
"""Lengths of OpenCV distortion vectors (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]])."""

SKEW_TOL = 1e-2
"""Largest accepted ``|K[0][1]| / fx`` (a small skew is tolerated, a large one is a typo)."""


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
        return dist

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


def _check_frame_pattern(pattern: str | None) -> str | None:
    if pattern is None:
        return None
    if not re.search(INDEX_FIELD_RE, pattern):
        raise ValueError("a frame pattern needs an {index...} field, e.g. {index:06d}")
    try:
        first, second = pattern.format(index=0), pattern.format(index=1)
    except (KeyError, IndexError, ValueError) as exc:
        raise ValueError(f"does not format with index alone: {exc!r}") from None
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
    """Number of frames; the frame index runs over 0 .. count-1."""
    depth: FramePattern
    """Pattern of the aligned depth PNGs (uint16 mm), e.g. ``grasp/depth/{index:06d}.png``."""
    color: FramePattern | None = None
    """Pattern of the colour frames (8-bit, 3 channels); optional when keypoints are given."""
    keypoints: FramePattern | None = None
    """Pattern of OpenPose JSON files per frame; without it the builder detects keypoints."""
    steady_from: Annotated[Int, Field(ge=0)] | None = None
    """First frame after grasp adjustment (hand held still); null means detect it."""

    _patterns = field_validator("depth", "color", "keypoints")(_check_frame_pattern)

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
    def _at_least_one(cls, views: tuple[ScanView, ...]) -> tuple[ScanView, ...]:
        # Not Field(min_length=1): pydantic would add a bogus "0 items" error to item errors.
        if not views:
            raise ValueError("needs at least one view")
        return views

    def angles_rad(self) -> np.ndarray:
        """The platter angle of every view, ``(n,) float64`` radians."""
        return np.array([math.radians(v.angle_deg) for v in self.views])


class SessionManifest(_Model):
    """``session.json``: the manifest of one capture session."""

    format: Literal["grasp-capture-session/1"]
    """Format and version of this manifest; exactly ``grasp-capture-session/1``."""
    session_id: Text
    """Identifier of the session, unique in a dataset (e.g. ``p03-mug-use-01``)."""
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
    """Metres per depth-PNG unit (0.001 for millimetres)."""
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
