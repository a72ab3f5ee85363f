"""The ``load_session`` stage: find, validate and open capture sessions (no Prefect here).

A session is a directory with ``session.json`` laid out as in ``session-format.md``.
:func:`validate_session` collects every problem of a session, each naming the session,
the file and the field, and never stops at the first; :func:`load_session` raises
:class:`SessionInvalid` with all of them or returns a :class:`Session` whose readers
convert to the units of the code (metres, kelvin).

Validation never raises and never hangs on a malformed session: only regular files are
opened (a directory, FIFO, device, socket or symlink loop is a problem line), JSON nesting,
file sizes, frame counts, pattern lengths, image dimensions (from the header, before any
decode) and mesh sizes are bounded by :class:`SessionLimits` (``LoadSessionConfig.limits``),
and a library's error is reported with what it means for the file.

A problem inside one grasp frame's colour image or keypoint file (corrupt or truncated
JPEG, wrong size, keypoint JSON with bad values) is :attr:`Severity.FRAME`: reported, but
the session loads and ``detect_keypoints`` treats that frame as a missing detection.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from functools import lru_cache
from pathlib import Path, PurePosixPath
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ValidationError

from graspcap.schemas.session import (
    DEFAULT_LIMITS,
    FORMAT,
    MESH_PATH_RE,
    RELATIVE_PATH_RE,
    SESSION_ID_RE,
    SESSION_ID_RULE,
    Grasp,
    ScanView,
    SessionLimits,
    SessionManifest,
    Stage1,
)
from graspcap.tasks.core.camera import Camera
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.session.discover import MANIFEST
from graspcap.tasks.session.files import (
    ImageKind,
    JsonSyntaxError,
    Unreadable,
    decode,
    image_problems,
    load_json,
    mesh_problems,
    not_regular,
    openpose_hands,
    openpose_problems,
    read_regular,
    size_problem,
)

# cv2, trimesh: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "load_session/1"


class LoadSessionConfig(StageConfig):
    check_images: bool = True
    """Decode every image to check its size and dtype (False: only that the files exist)."""
    limits: SessionLimits = DEFAULT_LIMITS
    """Bounds on frames, views, file sizes, image and mesh sizes (``docs/session-limits.md``)."""


PRESETS = {"default": LoadSessionConfig(), "fast": LoadSessionConfig(check_images=False)}
WHOLE_FILE = "(file)"
"""The ``field`` of a problem that concerns a whole file (missing manifest, JSON syntax)."""
MISSING = "file does not exist"
"""The message of a path that names nothing (see ``session_files.not_regular``)."""
MAX_LISTED = 20
"""Missing frames listed one by one per pattern before the rest are summarised."""

FrameKind = Literal["color", "depth", "keypoints"]


class Severity(StrEnum):
    ERROR = "error"
    """The session cannot be built."""
    FRAME = "frame"
    """One grasp frame's colour image or keypoint file: that frame is a missing detection;
    the session still loads and builds."""


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a session, located by file (relative to the session) and field."""

    session: str
    file: str
    field: str
    message: str
    severity: Severity = Severity.ERROR

    def __str__(self) -> str:
        text = f"session {self.session}: file {self.file}: field {self.field}: {self.message}"
        return text + (" (frame skipped)" if self.severity is Severity.FRAME else "")


class SessionInvalid(StageError):
    """A session that does not meet the contract; ``problems`` lists every problem found."""

    def __init__(self, problems: Sequence[Problem]):
        self.problems = list(problems)
        session = self.problems[0].session if self.problems else None
        lines = "\n".join(f"  file {p.file}: field {p.field}: {p.message}" for p in self.problems)
        reason = f"{len(self.problems)} problem(s)\n{lines}"
        super().__init__("load_session", reason, session=session)


class _Resolver:
    """Resolves paths relative to one session directory, checking that they stay inside it.

    Equivalent to ``(root / rel).resolve()`` followed by a containment check, but each
    directory is resolved once: frames share their folder, so a file costs one ``lstat``
    (whether it is itself a symlink, which is then followed) instead of one per component.
    """

    def __init__(self, root: Path):
        self.root = Path(root)
        self.real_root = self.root.resolve()
        self._dirs: dict[str, Path] = {}

    def __call__(self, rel: str | Path) -> tuple[Path | None, str | None]:
        """``root / rel`` resolved, or why it is not a path inside the session directory."""
        if PurePosixPath(rel).is_absolute() or Path(rel).is_absolute():
            return None, f"absolute path {str(rel)!r}; paths are relative to the session directory"
        if ".." in PurePosixPath(rel).parts:
            return None, f"path {str(rel)!r} climbs out with '..'"
        if "\0" in os.fspath(rel):
            return None, f"path {str(rel)!r} holds a NUL character"
        parent, name = os.path.split(os.fspath(rel))
        try:
            real_dir = self._dirs.get(parent)
            if real_dir is None:
                real_dir = self._dirs[parent] = (self.root / parent).resolve()
            resolved = real_dir / name
            if name and os.path.islink(resolved):
                resolved = resolved.resolve()
        except (OSError, RuntimeError):  # RuntimeError: Python 3.11's "Symlink loop"
            return None, f"path {str(rel)!r} is a symlink loop (too many levels of symbolic links)"
        if not resolved.is_relative_to(self.real_root):
            return None, f"path {str(rel)!r} leaves the session directory (resolves to {resolved})"
        return resolved, None


@dataclass(frozen=True)
class Session:
    """A validated session: its root directory and manifest, with readers in code units."""

    root: Path
    manifest: SessionManifest
    check_read: Callable[[Path], None] | None = field(default=None, repr=False, compare=False)
    """Called with every path the session resolves for reading (``manifest_guard``: a stage
    reads only the files of the roles it declares); None lets every file through."""
    _resolve: _Resolver = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_resolve", _Resolver(self.root))

    @property
    def session_id(self) -> str:
        return self.manifest.session_id

    def path(self, rel: str | Path) -> Path:
        """``rel`` resolved against the root; raises :class:`SessionInvalid` if it leaves it."""
        path, why = self._resolve(rel)
        if path is None:
            raise SessionInvalid([Problem(self.session_id, str(rel), WHOLE_FILE, why or "")])
        if self.check_read is not None:
            self.check_read(path)
        return path

    def _any(self, rel_or_path: str | Path) -> Path:
        if isinstance(rel_or_path, Path) and rel_or_path.is_absolute():
            rel_or_path = os.path.relpath(rel_or_path.resolve(), self.root.resolve())
        return self.path(rel_or_path)

    def grasp_path(self, kind: FrameKind, index: int) -> Path | None:
        """File of grasp frame ``index`` for ``kind``; None when the session has no such pattern."""
        rel = self.manifest.grasp.frame_path(kind, index)
        return None if rel is None else self.path(rel)

    def _read(self, rel_or_path: str | Path, kind: ImageKind, flags: int) -> np.ndarray:
        path = self._any(rel_or_path)
        rel = os.path.relpath(path, self.root)
        data = read_regular(path)
        why = data.message if isinstance(data, Unreadable) else (
            size_problem(data, None, DEFAULT_LIMITS.max_image_pixels))
        if why is not None:
            raise SessionInvalid([Problem(self.session_id, rel, WHOLE_FILE, f"{kind}: {why}")])
        image = decode(data, flags)  # type: ignore[arg-type]
        want = np.uint8 if kind is ImageKind.COLOR else np.uint16
        single = kind is ImageKind.COLOR or (image is not None and image.ndim == 2)
        if image is None or image.dtype != want or not single:
            what = "unreadable" if image is None else f"{image.dtype} {image.shape}"
            raise SessionInvalid([Problem(self.session_id, rel, WHOLE_FILE, f"{kind}: {what}")])
        return image

    def read_depth_m(self, rel_or_path: str | Path, *, ideal: bool = True) -> np.ndarray:
        """Depth PNG as ``(h, w) float32`` metres; 0 means no measurement.

        The depth is aligned to the colour camera, so it has the colour lens: with ``ideal``
        (the default) it is resampled into the ideal pinhole image of ``color_camera.K``
        (:meth:`Camera.undistort_image`, nearest raw pixel), the frame every stage's geometry
        works in; untouched when ``color_camera.dist`` is zero. ``ideal=False``: the raw image.
        """
        import cv2

        raw = self._read(rel_or_path, ImageKind.DEPTH, cv2.IMREAD_UNCHANGED)
        if ideal:
            raw = self.color_camera.undistort_image(raw, nearest=True)
        return raw.astype(np.float32) * np.float32(self.manifest.depth_scale_m)

    def read_thermal_k(self, rel_or_path: str | Path) -> np.ndarray:
        """Thermal PNG (centi-kelvin) as ``(h, w) float32`` kelvin."""
        import cv2

        raw = self._read(rel_or_path, ImageKind.THERMAL, cv2.IMREAD_UNCHANGED)
        return raw.astype(np.float32) * np.float32(0.01)

    def read_color(self, rel_or_path: str | Path) -> np.ndarray:
        """Colour image as ``(h, w, 3) uint8`` BGR."""
        import cv2

        return self._read(rel_or_path, ImageKind.COLOR, cv2.IMREAD_COLOR)

    @property
    def color_K(self) -> np.ndarray:
        """The colour camera's intrinsics ``(3, 3)`` float, pixels."""
        return np.asarray(self.manifest.color_camera.K, dtype=float)

    @property
    def color_camera(self) -> Camera:
        """The colour camera's lens (``color_camera``: K, dist, width, height), shared by the
        aligned depth: keypoints go through its :meth:`Camera.undistort_keypoints` before any
        geometry."""
        return Camera.of(self.manifest.color_camera)

    @property
    def thermal_camera(self) -> Camera:
        """The thermal camera's lens (``thermal_camera``: K, dist, width, height)."""
        return Camera.of(self.manifest.thermal_camera)

    @property
    def T_color_turntable(self) -> np.ndarray:
        """The turntable frame in the colour camera ``(4, 4)`` float, metres."""
        return np.asarray(self.manifest.turntable.T_color_turntable, dtype=float)

    @property
    def mesh_name(self) -> str:
        """The object mesh as messages name it: ``object_mesh <file>``."""
        return f"object_mesh {self.manifest.object_mesh}"

    def read_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The object mesh as (vertices (n, 3) float, faces (m, 3) int), in file vertex order."""
        import trimesh

        mesh = trimesh.load(self.path(self.manifest.object_mesh), force="mesh", process=False)
        return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)

    def grasp_depth_reader(self, cached_frames: int = 4) -> Callable[[int], np.ndarray]:
        """``read(frame) -> (h, w) float32`` metres of grasp depth frame ``frame``, the last
        ``cached_frames`` frames read kept (a session's depth video does not fit in memory as
        float)."""
        return lru_cache(maxsize=cached_frames)(
            lambda i: self.read_depth_m(self.grasp_path("depth", i)))

    def read_keypoints(self, index: int) -> list[np.ndarray]:
        """Frame ``index``'s OpenPose hands: one ``(21, 3)`` (x_px, y_px, conf) per person.

        Only the manifest's hand; ``[]`` when ``people`` is empty. Raises ``ValueError`` when
        the session has no keypoint files.
        """
        path = self.grasp_path("keypoints", index)
        if path is None:
            raise ValueError(f"session {self.session_id} has no grasp.keypoints")
        document = load_json(path, DEFAULT_LIMITS.max_keypoint_bytes)
        rel = os.path.relpath(path, self.root)
        if isinstance(document, JsonSyntaxError):
            raise SessionInvalid([Problem(self.session_id, rel, WHOLE_FILE, document.message)])
        problems = openpose_problems(document)
        if problems:
            raise SessionInvalid([Problem(self.session_id, rel, f, m) for f, m in problems])
        return openpose_hands(document, str(self.manifest.hand))

    def input_files(self) -> dict[str, list[Path]]:
        """Every file the builder reads, by role (for cache keys)."""
        m, grasp = self.manifest, self.manifest.grasp

        def frames(kind: FrameKind) -> list[Path]:
            if getattr(grasp, kind) is None:
                return []
            return [self.grasp_path(kind, i) for i in range(grasp.count)]  # type: ignore[misc]

        return {
            "manifest": [self.path(MANIFEST)],
            "object_mesh": [self.path(m.object_mesh)],
            "stage1": [self.path(r) for r in (m.stage1.depth, m.stage1.color) if r is not None],
            "grasp_color": frames("color"),
            "grasp_depth": frames("depth"),
            "grasp_keypoints": frames("keypoints"),
            "scan_thermal": [self.path(v.thermal) for v in m.scan.views],
            "scan_depth": [self.path(v.depth) for v in m.scan.views],
        }


def _field(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or WHOLE_FILE


def _message(error: dict[str, Any]) -> str:
    kind, ctx = error["type"], error.get("ctx") or {}
    if kind == "extra_forbidden":
        return f"unknown key (not part of {FORMAT})"
    if kind == "missing":
        return "required key is missing"
    if kind == "literal_error" and error["loc"] == ("format",):
        return f"format {error['input']!r} is not {FORMAT!r}, the only version this builder reads"
    if kind == "string_pattern_mismatch" and ctx.get("pattern") == SESSION_ID_RE:
        return f"{_shown(error.get('input'))} is not a session id: {SESSION_ID_RULE}"
    if kind == "string_pattern_mismatch" and ctx.get("pattern") in (RELATIVE_PATH_RE, MESH_PATH_RE):
        mesh = " ending in .ply, .obj or .stl" if ctx["pattern"] == MESH_PATH_RE else ""
        return (f"{_shown(error['input'])} is not a relative path inside the session{mesh} "
                "(no leading '/', no '..', no control character)")
    message = error["msg"].removeprefix("Value error, ")
    got = repr(error.get("input"))
    return message if kind == "value_error" else f"{message} (got {got[:60]})"


def _shown(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters (a 300-character id stays one short line)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _section(model: type[BaseModel], raw: Any, context: dict[str, Any]) -> Any:
    """``raw`` validated as ``model``, or None; used to keep checking files of a bad manifest.

    Keys with errors are dropped and validation retried once, so that e.g. a bad
    ``steady_from`` does not stop the checks of the frames.
    """
    try:
        return model.model_validate(raw, context=context)
    except ValidationError as exc:
        if not isinstance(raw, dict) or any(not e["loc"] for e in exc.errors()):
            return None
        bad = {e["loc"][0] for e in exc.errors()}
    if "count" in bad:  # frame files cannot be checked without a valid count
        return None
    try:
        return model.model_validate({k: v for k, v in raw.items() if k not in bad},
                                    context=context)
    except ValidationError:
        return None


def _size(camera: Any) -> tuple[int, int] | None:
    """``(width, height)`` of a raw camera section when both are positive ints, else None."""
    if isinstance(camera, dict):
        size = camera.get("width"), camera.get("height")
        if all(type(v) is int and v >= 1 for v in size):
            return size  # type: ignore[return-value]
    return None


def _views(raw_scan: Any, limits: SessionLimits) -> list[tuple[int, ScanView]]:
    """The scan views that are valid by themselves, with their index (none past the limit)."""
    views = raw_scan.get("views") if isinstance(raw_scan, dict) else None
    if not isinstance(views, list) or len(views) > limits.max_scan_views:
        return []
    context = {"limits": limits}
    valid = ((j, _section(ScanView, view, context)) for j, view in enumerate(views))
    return [(j, view) for j, view in valid if view is not None]


class _Checker:
    """Collects problems of one session."""

    def __init__(self, root: Path, session: str, limits: SessionLimits = DEFAULT_LIMITS):
        self.root, self.session, self.problems = root, session, []
        self.limits = limits
        self.inside = _Resolver(root)

    def add(self, file: str, field: str, message: str,
            severity: Severity = Severity.ERROR) -> None:
        self.problems.append(Problem(self.session, file, field, message, severity))

    def existing(self, rel: str, field: str, report_missing: bool = True) -> Path | None:
        path, why = self.inside(rel)
        if path is None:
            self.add(rel, field, why or "")
        elif (why := not_regular(path)) is not None:
            if report_missing or why != MISSING:
                self.add(rel, field, why)
            return None
        return path

    def image(self, rel: str | None, field: str, kind: ImageKind, size, check: bool) -> None:
        if rel is not None and (path := self.existing(rel, field)) is not None and check:
            for message in image_problems(path, kind, size, limits=self.limits):
                self.add(rel, field, message)

    def grasp_frames(self, grasp: Grasp, kind: FrameKind, size, check: bool) -> None:
        field, missing, unusable = f"grasp.{kind}", [], []
        for i in range(grasp.count):
            rel = grasp.frame_path(kind, i) or ""
            path, why = self.inside(rel)
            if path is not None:
                why = not_regular(path)
            if why == MISSING:
                missing.append(i)
            elif why is not None:  # leaves the session, a directory, a FIFO, ...
                unusable.append((rel, why))
            elif kind == "keypoints":
                self.keypoints(path, rel, field)
            elif check:
                # a bad colour frame is one missing detection; a bad depth frame stops stages
                image_kind = ImageKind.COLOR if kind == "color" else ImageKind.DEPTH
                severity = Severity.FRAME if kind == "color" else Severity.ERROR
                for message in image_problems(path, image_kind, size, limits=self.limits):
                    self.add(rel, field, message, severity)
        pattern, count = getattr(grasp, kind), grasp.count
        for rel, why in unusable[:MAX_LISTED]:
            self.add(rel, field, why)
        if len(unusable) > MAX_LISTED:
            self.add(pattern, field, f"{len(unusable) - MAX_LISTED} more frames are not "
                     f"readable files (the first: {unusable[MAX_LISTED][1]})")
        if missing and missing == list(range(missing[0], count)):
            self.add(pattern.format(index=missing[0]), "grasp.count",
                     f"count is {count} but {field} has files for frames 0..{missing[0] - 1} "
                     f"only (missing from {pattern.format(index=missing[0])} on)")
        else:
            for i in missing[:MAX_LISTED]:
                self.add(pattern.format(index=i), field, "file does not exist")
            if len(missing) > MAX_LISTED:
                self.add(pattern, field, f"{len(missing) - MAX_LISTED} more frames missing")
        beyond = pattern.format(index=count)
        if (path := self.inside(beyond)[0]) is not None and not_regular(path) is None:
            self.add(beyond, "grasp.count", f"frame {count} exists but count is {count}")

    def keypoints(self, path: Path, rel: str, field: str) -> None:
        document = load_json(path, self.limits.max_keypoint_bytes, self.limits.max_json_depth)
        if isinstance(document, JsonSyntaxError):
            self.add(rel, field, document.message, Severity.FRAME)
            return
        for inner, message in openpose_problems(document):
            self.add(rel, inner, message, Severity.FRAME)


def _label(name: str) -> str:
    """A session's name for problem lines: as is when it is a valid id, else its repr, cut."""
    return name if re.search(SESSION_ID_RE, name) else _shown(name, 60)


def _validate(directory: Path, check_images: bool,
              limits: SessionLimits) -> tuple[SessionManifest | None, list[Problem]]:
    directory = Path(directory)
    checker = _Checker(directory, _label(directory.name), limits)
    manifest_path = directory / MANIFEST
    if (why := not_regular(manifest_path)) is not None:
        message = f"missing: {directory} holds no {MANIFEST}" if why == MISSING else why
        checker.add(MANIFEST, WHOLE_FILE, message)
        return None, checker.problems
    raw = load_json(manifest_path, limits.max_manifest_bytes, limits.max_json_depth)
    if isinstance(raw, JsonSyntaxError):
        checker.add(MANIFEST, WHOLE_FILE, raw.message)
        return None, checker.problems
    if not isinstance(raw, dict):
        checker.add(MANIFEST, WHOLE_FILE, f"top level must be an object, got {type(raw).__name__}")
        return None, checker.problems
    if isinstance(raw.get("session_id"), str) and re.search(SESSION_ID_RE, raw["session_id"]):
        checker.session = raw["session_id"]

    context = {"limits": limits}
    manifest = None
    try:
        manifest = SessionManifest.model_validate(raw, context=context)
    except ValidationError as exc:
        for error in exc.errors():
            checker.add(MANIFEST, _field(error["loc"]), _message(error))

    # File checks run on every section that is valid by itself, even when others are not.
    stage1 = _section(Stage1, raw.get("stage1"), context)
    grasp = _section(Grasp, raw.get("grasp"), context)
    color_size = _size(raw.get("color_camera"))
    thermal_size = _size(raw.get("thermal_camera"))
    mesh = raw.get("object_mesh")
    if isinstance(mesh, str) and re.search(MESH_PATH_RE, mesh):
        if (path := checker.existing(mesh, "object_mesh")) is not None:
            for message in mesh_problems(path, limits):
                checker.add(mesh, "object_mesh", message)
    if stage1:
        checker.image(stage1.depth, "stage1.depth", ImageKind.DEPTH, color_size, check_images)
        checker.image(stage1.color, "stage1.color", ImageKind.COLOR, color_size, check_images)
    if grasp:
        for kind in ("color", "depth", "keypoints"):
            if getattr(grasp, kind) is not None:
                checker.grasp_frames(grasp, kind, color_size, check_images)
    for j, view in _views(raw.get("scan"), limits):
        field = f"scan.views[{j}]"
        checker.image(view.thermal, f"{field}.thermal", ImageKind.THERMAL, thermal_size,
                      check_images)
        checker.image(view.depth, f"{field}.depth", ImageKind.DEPTH, color_size, check_images)
    return manifest, checker.problems


def validate_session(directory: Path, *, check_images: bool = True,
                     limits: SessionLimits = DEFAULT_LIMITS) -> list[Problem]:
    """Every problem of the session at ``directory``; empty when it meets the contract.

    ``check_images`` False skips decoding images (existence, paths, JSON still checked).
    Problems of :attr:`Severity.FRAME` do not stop :func:`load_session`. Never raises for a
    malformed session (see the module docstring).
    """
    return _validate(directory, check_images, limits)[1]


def load_session(directory: Path, *, check_images: bool = True,
                 limits: SessionLimits = DEFAULT_LIMITS) -> Session:
    """The validated session at ``directory``; raises :class:`SessionInvalid` with every
    problem of :attr:`Severity.ERROR` (frame-level ones are left to ``detect_keypoints``)."""
    manifest, problems = _validate(directory, check_images, limits)
    errors = [p for p in problems if p.severity is Severity.ERROR]
    if errors or manifest is None:
        raise SessionInvalid(errors)
    return Session(root=Path(directory).resolve(), manifest=manifest)
