"""Checks and readers for the files of a capture session: images, the mesh, OpenPose JSON.

Each ``*_problems`` function returns a list of messages (empty when the file is fine) and
never raises for a bad file; ``graspcap.tasks.session.load_session`` attaches session, file and
field to them. Formats are those of ``session-format.md``.

Only regular files are read: :func:`not_regular` says why a path is not one (missing, a
directory, a FIFO, a device, a socket, a symlink loop) from one ``os.stat``, and
:func:`read_regular` opens with ``O_NONBLOCK`` and checks the open file again, so a FIFO put
in place after the check cannot hang a read. Sizes are bounded by
:class:`~graspcap.schemas.session.SessionLimits`, checked before anything is decoded.
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import stat
import struct
import zlib
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import numpy as np

from graspcap.schemas.session import DEFAULT_LIMITS, SessionLimits

# cv2, trimesh: imported where used, so that importing the stage table stays cheap

N_KEYPOINTS = 21
"""Hand keypoints in the OpenPose / MediaPipe layout."""

HAND_KEYS = {"right": "hand_right_keypoints_2d", "left": "hand_left_keypoints_2d"}
"""The OpenPose JSON key of each hand's 2D keypoints (21 x (x, y, confidence))."""


class ImageKind(StrEnum):
    """What an image must hold."""

    DEPTH = "depth"
    """uint16, one channel (millimetres)."""
    THERMAL = "thermal"
    """uint16, one channel (centi-kelvin)."""
    COLOR = "color"
    """8-bit, three channels (BGR)."""


def _kind_of(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "is a directory, not a file"
    if stat.S_ISFIFO(mode):
        return "is a FIFO (named pipe), not a regular file; it is never opened"
    if stat.S_ISSOCK(mode):
        return "is a socket, not a regular file; it is never opened"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "is a device, not a regular file; it is never opened"
    return "is not a regular file; it is never opened"


def _os_error(exc: OSError) -> str:
    if exc.errno == errno.ENOENT:
        return "file does not exist"
    if exc.errno == errno.ELOOP:
        return "is a symlink loop (too many levels of symbolic links)"
    if exc.errno == errno.ENOTDIR:
        return "file does not exist (a component of its folder is a file)"
    if exc.errno == errno.ENAMETOOLONG:
        return "path is too long for the file system"
    return f"cannot read: {exc.strerror or exc}"


def not_regular(path: Path | str) -> str | None:
    """Why ``path`` (symlinks followed) is not a regular file to read, or None when it is."""
    try:
        st = os.stat(path)
    except OSError as exc:
        return _os_error(exc)
    except ValueError:  # an embedded NUL byte
        return "path holds a NUL character"
    return None if stat.S_ISREG(st.st_mode) else _kind_of(st.st_mode)


@dataclass(frozen=True)
class Unreadable:
    """A file that was not read, and why (see :func:`read_regular`)."""

    message: str


def read_regular(path: Path | str, max_bytes: int | None = None) -> bytes | Unreadable:
    """The bytes of the regular file at ``path``, or :class:`Unreadable` with why not.

    Opened with ``O_NONBLOCK`` and checked with ``fstat`` on the open file: a directory,
    FIFO, device or socket is refused before any read (a FIFO cannot block the open), and
    a file larger than ``max_bytes`` is refused from its size.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        if exc.errno == errno.EISDIR:
            return Unreadable("is a directory, not a file")
        return Unreadable(_os_error(exc))
    except ValueError:
        return Unreadable("path holds a NUL character")
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            return Unreadable(_kind_of(st.st_mode))
        if max_bytes is not None and st.st_size > max_bytes:
            return Unreadable(f"{st.st_size} bytes is more than the limit of {max_bytes}")
        with os.fdopen(fd, "rb", closefd=True) as handle:
            fd = -1
            return handle.read()
    except OSError as exc:
        return Unreadable(_os_error(exc))
    finally:
        if fd >= 0:
            os.close(fd)


_EXPECTED = {
    ImageKind.DEPTH: (np.uint16, 1, "uint16 single channel"),
    ImageKind.THERMAL: (np.uint16, 1, "uint16 single channel"),
    ImageKind.COLOR: (np.uint8, 3, "8-bit 3-channel"),
}


def _jpeg_problem(data: bytes) -> str | None:
    """libjpeg returns a grey-padded image for a truncated JPEG; catch that from the markers."""
    if not data.startswith(b"\xff\xd8"):
        return "not a JPEG (no start-of-image marker)"
    if b"\xff\xd9" not in data.rstrip(b"\x00")[-16:]:
        return "truncated JPEG (no end-of-image marker)"
    return None


_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
"""JPEG start-of-frame markers (the others in C0..CF are tables)."""


def _jpeg_header(data: bytes) -> tuple[int, int, int] | None:
    """(width, height, channels) from a baseline 8-bit JPEG's start-of-frame segment, or None
    (no such segment before the scan, or another precision: decode it fully instead)."""
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a segment
            pos += 2
            continue
        if marker == 0xDA:  # start of scan: no frame header before it
            return None
        length = struct.unpack(">H", data[pos + 2 : pos + 4])[0]
        if marker in _SOF:
            if pos + 10 > len(data) or data[pos + 4] != 8:
                return None
            height, width = struct.unpack(">HH", data[pos + 5 : pos + 9])
            return width, height, 1 if data[pos + 9] == 1 else 3
        pos += 2 + length
    return None


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}
"""Channels by PNG colour type (a palette image decodes to 3 channels)."""


def _png_header(data: bytes) -> tuple[int, int, np.dtype, int, int] | str:
    """(width, height, dtype, channels, interlace) of a PNG, or why the PNG is broken.

    Structural decode without unfiltering: every chunk's CRC, IHDR first, IEND last, and the
    zlib stream of the IDAT chunks complete with exactly the size the header implies. This
    catches truncated and corrupted files at about a third of the cost of a full decode.
    """
    pos, header, idat = 8, None, []
    while True:
        if pos + 8 > len(data):
            return "truncated PNG (no IEND chunk)"
        length, kind = struct.unpack(">I", data[pos : pos + 4])[0], data[pos + 4 : pos + 8]
        body = data[pos + 8 : pos + 8 + length]
        crc = data[pos + 8 + length : pos + 12 + length]
        if len(body) < length or len(crc) < 4:
            return f"truncated PNG (in chunk {kind!r})"
        if zlib.crc32(kind + body) != struct.unpack(">I", crc)[0]:
            return f"corrupt PNG (CRC mismatch in chunk {kind!r})"
        pos += 12 + length
        if header is None:
            if kind != b"IHDR" or length != 13:
                return "corrupt PNG (IHDR is not the first chunk)"
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    width, height, bit_depth, color_type, _, _, interlace = header
    channels = _PNG_CHANNELS.get(color_type)
    if channels is None or width == 0 or height == 0:
        return f"corrupt PNG (colour type {color_type}, size {width}x{height})"
    inflater = zlib.decompressobj()
    try:
        raw_size = len(inflater.decompress(b"".join(idat))) + len(inflater.flush())
    except zlib.error as exc:
        return f"corrupt PNG (image data: {exc})"
    samples = 1 if color_type == 3 else channels
    expected = height * (1 + (width * samples * bit_depth + 7) // 8)
    if not inflater.eof or (interlace == 0 and raw_size != expected):
        return f"corrupt PNG (image data holds {raw_size} bytes, expected {expected})"
    dtype = np.dtype(np.uint16 if bit_depth == 16 else np.uint8)
    return width, height, dtype, channels, interlace


def claimed_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` a PNG's IHDR or a JPEG's frame header claims, read without
    decoding anything; None for other formats or when the header is not there."""
    if data.startswith(PNG_SIGNATURE) and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if data.startswith(b"\xff\xd8"):
        header = _jpeg_header(data)
        return None if header is None else header[:2]
    return None


def size_problem(data: bytes, size: tuple[int, int] | None, max_pixels: int) -> str | None:
    """Why the image in ``data`` must not be decoded, from its header alone: more pixels
    than ``max_pixels``, or another size than the camera's ``size``; None otherwise."""
    claimed = claimed_size(data)
    if claimed is None:
        return None
    width, height = claimed
    if width * height > max_pixels:
        return (f"header claims {width}x{height} pixels, more than the limit of {max_pixels} "
                "(SessionLimits.max_image_pixels); not decoded")
    if size is not None and (width, height) != tuple(size) and width and height:
        return f"size {width}x{height}, expected {size[0]}x{size[1]} (width x height)"
    return None


def decode(data: bytes, flags: int) -> np.ndarray | None:
    """``cv2.imdecode`` of ``data``, None for an empty or undecodable buffer (never
    OpenCV's assertion error)."""
    import cv2

    if not data:
        return None
    try:
        return cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error:
        return None


def image_problems(
    path: Path, kind: ImageKind, size: tuple[int, int] | None, *, fast_png: bool = True,
    limits: SessionLimits = DEFAULT_LIMITS,
) -> list[str]:
    """Why the image at ``path`` is not a decodable ``kind`` image of ``size`` (width, height).

    ``size`` None skips the size check (the camera's size is itself invalid). With
    ``fast_png``, PNGs are checked structurally (see :func:`_png_header`) and 8-bit JPEGs
    take size and channels from their frame header and are decoded at 1/8 scale; other
    formats, and interlaced PNGs, are decoded with ``cv2.imdecode(..., IMREAD_UNCHANGED)``.
    """
    import cv2

    data = read_regular(path)
    if isinstance(data, Unreadable):
        return [data.message]
    if not data:
        return ["empty file (0 bytes)"]
    if path.suffix.lower() in (".jpg", ".jpeg") or data.startswith(b"\xff\xd8"):
        problem = _jpeg_problem(data)
        if problem:
            return [problem]
    if (problem := size_problem(data, None, limits.max_image_pixels)) is not None:
        return [problem]
    header = _png_header(data) if fast_png and data.startswith(PNG_SIGNATURE) else None
    if isinstance(header, str):
        return [header]
    jpeg = _jpeg_header(data) if fast_png and data.startswith(b"\xff\xd8") else None
    if header is not None and header[4] == 0:
        width, height, dtype, channels, _ = header
    elif jpeg is not None:
        # the size and channels from the frame header; the whole entropy-coded scan is still
        # decoded (at 1/8 scale, which skips most of the inverse DCT) to know that it decodes
        if decode(data, cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
            return ["does not decode as an image (corrupt or unsupported)"]
        (width, height, channels), dtype = jpeg, np.dtype(np.uint8)
    else:
        image = decode(data, cv2.IMREAD_UNCHANGED)
        if image is None:
            return ["does not decode as an image (corrupt or unsupported)"]
        height, width = image.shape[:2]
        dtype, channels = image.dtype, 1 if image.ndim == 2 else image.shape[2]
    problems = []
    want_dtype, want_channels, text = _EXPECTED[kind]
    if dtype != want_dtype or channels != want_channels:
        plural = "s" if channels != 1 else ""
        problems.append(f"{kind} image must be {text}, got {dtype} with {channels} channel{plural}")
    if size is not None and (width, height) != tuple(size):
        problems.append(f"size {width}x{height}, expected {size[0]}x{size[1]} (width x height)")
    return problems


_PLY_ELEMENT = re.compile(rb"^element\s+(vertex|face)\s+(\d+)\s*$", re.M)


def _claimed_mesh_size(data: bytes, suffix: str) -> tuple[int, int] | None:
    """``(vertices, faces)`` a mesh file says it holds, found without parsing it (PLY
    header, binary STL triangle count, OBJ ``v``/``f`` lines), or None when unknown."""
    if data.startswith(b"ply"):
        end = data.find(b"end_header")
        counts = dict(_PLY_ELEMENT.findall(data[: end if end > 0 else 4096]))
        if b"vertex" in counts or b"face" in counts:
            return int(counts.get(b"vertex", 0)), int(counts.get(b"face", 0))
        return None
    if suffix == ".stl" and not data[:5].lower() == b"solid" and len(data) >= 84:
        (triangles,) = struct.unpack("<I", data[80:84])
        return 3 * triangles, triangles
    if suffix == ".stl":
        triangles = data.count(b"facet")
        return 3 * triangles, triangles
    if suffix == ".obj":
        return data.count(b"\nv ") + data.startswith(b"v "), data.count(b"\nf ")
    return None


def mesh_problems(path: Path, limits: SessionLimits = DEFAULT_LIMITS) -> list[str]:
    """Why the mesh at ``path`` is not a non-empty, finite triangle mesh within the limits
    whose faces index its vertices. Sizes are checked from the file before trimesh parses it;
    a loader error is reported with what it means for the file."""
    import trimesh

    data = read_regular(path, limits.max_mesh_bytes)
    if isinstance(data, Unreadable):
        return [data.message + (" (SessionLimits.max_mesh_bytes)" * ("limit" in data.message))]
    claimed = _claimed_mesh_size(data, path.suffix.lower())
    if claimed is not None:
        problems = _mesh_size_problems(*claimed, limits)
        if problems:
            return problems
    try:
        mesh = trimesh.load(trimesh.util.wrap_as_stream(data), file_type=path.suffix[1:].lower(),
                            force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for a bad file
        text = str(exc).strip() or type(exc).__name__
        return [f"does not load as a {path.suffix[1:].upper()} mesh (corrupt or not a mesh "
                f"file; the loader said: {text[:200]})"]
    vertices = np.asarray(getattr(mesh, "vertices", np.empty((0, 3))))
    faces = np.asarray(getattr(mesh, "faces", np.empty((0, 3))))
    if len(vertices) == 0 or len(faces) == 0:
        return [f"empty mesh ({len(vertices)} vertices, {len(faces)} faces)"]
    problems = _mesh_size_problems(len(vertices), len(faces), limits)
    if problems:
        return problems
    if not np.all(np.isfinite(vertices)):
        return ["mesh has non-finite vertex coordinates"]
    if faces.min() < 0 or faces.max() >= len(vertices):
        bad = int(np.argmax((faces < 0).any(axis=1) | (faces >= len(vertices)).any(axis=1)))
        return [f"face {bad} indexes vertices {faces[bad].tolist()}, but the mesh has "
                f"{len(vertices)} vertices (indices 0..{len(vertices) - 1})"]
    return []


def _mesh_size_problems(vertices: int, faces: int, limits: SessionLimits) -> list[str]:
    out = []
    if faces > limits.max_mesh_faces:
        out.append(f"{faces} faces is more than the limit of {limits.max_mesh_faces} "
                   "(SessionLimits.max_mesh_faces); decimate the mesh or raise the limit")
    if vertices > limits.max_mesh_vertices:
        out.append(f"{vertices} vertices is more than the limit of {limits.max_mesh_vertices} "
                   "(SessionLimits.max_mesh_vertices); decimate the mesh or raise the limit")
    return out


@dataclass(frozen=True)
class JsonSyntaxError:
    """A JSON file that does not parse; ``message`` holds line and column."""

    message: str


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


def json_depth_exceeds(text: str, max_depth: int) -> bool:
    """Whether arrays and objects in JSON ``text`` nest deeper than ``max_depth`` (strings
    skipped). Cheap for ordinary files: fewer brackets than the limit cannot nest deeper."""
    if text.count("[") + text.count("{") <= max_depth:
        return False
    bare = _JSON_STRING.sub("", text).encode("utf-8", "replace")
    codes = np.frombuffer(bare, np.uint8)
    step = (np.isin(codes, (ord("["), ord("{"))).astype(np.int32)
            - np.isin(codes, (ord("]"), ord("}"))))
    return bool(len(step)) and int(np.cumsum(step).max()) > max_depth


def load_json(path: Path, max_bytes: int | None = DEFAULT_LIMITS.max_keypoint_bytes,
              max_depth: int = DEFAULT_LIMITS.max_json_depth) -> object | JsonSyntaxError:
    """The parsed JSON at ``path``, or a :class:`JsonSyntaxError` saying why not (line and
    column of a syntax error; not a regular file; larger than ``max_bytes``; nested deeper
    than ``max_depth``). Never raises for a bad file."""
    data = read_regular(path, max_bytes)
    if isinstance(data, Unreadable):
        return JsonSyntaxError(data.message)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        return JsonSyntaxError(f"not UTF-8 text (byte {exc.start}: {exc.reason})")
    if json_depth_exceeds(text, max_depth):
        return JsonSyntaxError(f"arrays and objects nest deeper than {max_depth} levels "
                               "(SessionLimits.max_json_depth); not parsed")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno} column {exc.colno}"
        return JsonSyntaxError(f"JSON syntax error at {where}: {exc.msg}")
    except (RecursionError, ValueError) as exc:  # a number too long to convert, ...
        return JsonSyntaxError(f"does not parse as JSON: {exc}"[:300])


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def openpose_problems(document: object) -> list[tuple[str, str]]:
    """``(field, message)`` for everything wrong in a parsed OpenPose keypoint JSON.

    A hand array is either empty (OpenPose ran without hand detection) or 21 x (x, y, c):
    63 finite numbers with confidences in [0, 1]. Other keys are OpenPose's own and ignored.
    """
    if not isinstance(document, dict):
        return [("(file)", f"top level must be an object, got {type(document).__name__}")]
    people = document.get("people")
    if not isinstance(people, list):
        return [("people", "missing or not a list")]
    problems = []
    for p, person in enumerate(people):
        if not isinstance(person, dict):
            problems.append((f"people[{p}]", "must be an object"))
            continue
        for key in HAND_KEYS.values():
            if key not in person:
                continue
            field, values = f"people[{p}].{key}", person[key]
            if not isinstance(values, list) or len(values) not in (0, 3 * N_KEYPOINTS):
                n = len(values) if isinstance(values, list) else type(values).__name__
                message = f"must hold {3 * N_KEYPOINTS} numbers (21 x, y, c), got {n}"
                problems.append((field, message))
                continue
            if not all(_is_number(v) and math.isfinite(v) for v in values):
                problems.append((field, "holds a value that is not a finite number"))
                continue
            conf = values[2::3]
            if conf and not (min(conf) >= 0 and max(conf) <= 1):
                message = f"confidence outside [0, 1] (min {min(conf)}, max {max(conf)})"
                problems.append((field, message))
    return problems


def openpose_hands(document: dict, hand: str) -> list[np.ndarray]:
    """One ``(21, 3) float64`` (x_px, y_px, confidence) array per person for ``hand``.

    A person without that hand's array (missing or empty) gets zeros: confidence 0 means
    not detected. ``document`` must have passed :func:`openpose_problems`.
    """
    out = []
    for person in document["people"]:
        values = person.get(HAND_KEYS[hand]) or [0.0] * (3 * N_KEYPOINTS)
        out.append(np.asarray(values, dtype=float).reshape(N_KEYPOINTS, 3))
    return out
