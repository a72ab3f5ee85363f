"""Checks and readers for the files of a capture session: images, the mesh, OpenPose JSON.

Each ``*_problems`` function returns a list of messages (empty when the file is fine) and
never raises for a bad file; ``graspcap.tasks.session.load_session`` attaches session, file and
field to them. Formats are those of ``session-format.md``.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path

import cv2
import numpy as np
import trimesh

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


def image_problems(
    path: Path, kind: ImageKind, size: tuple[int, int] | None, *, fast_png: bool = True
) -> list[str]:
    """Why the image at ``path`` is not a decodable ``kind`` image of ``size`` (width, height).

    ``size`` None skips the size check (the camera's size is itself invalid). With
    ``fast_png``, PNGs are checked structurally (see :func:`_png_header`) and 8-bit JPEGs
    take size and channels from their frame header and are decoded at 1/8 scale; other
    formats, and interlaced PNGs, are decoded with ``cv2.imdecode(..., IMREAD_UNCHANGED)``.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        return [f"cannot read: {exc.strerror or exc}"]
    if path.suffix.lower() in (".jpg", ".jpeg") or data.startswith(b"\xff\xd8"):
        problem = _jpeg_problem(data)
        if problem:
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
        buffer = np.frombuffer(data, np.uint8)
        if cv2.imdecode(buffer, cv2.IMREAD_REDUCED_GRAYSCALE_8) is None:
            return ["does not decode as an image (corrupt or unsupported)"]
        (width, height, channels), dtype = jpeg, np.dtype(np.uint8)
    else:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
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


def mesh_problems(path: Path) -> list[str]:
    """Why the mesh at ``path`` does not load with trimesh as a non-empty, finite triangle mesh."""
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for a bad file
        return [f"does not load as a mesh: {type(exc).__name__}: {exc}"]
    vertices = np.asarray(getattr(mesh, "vertices", np.empty((0, 3))))
    faces = np.asarray(getattr(mesh, "faces", np.empty((0, 3))))
    if len(vertices) == 0 or len(faces) == 0:
        return [f"empty mesh ({len(vertices)} vertices, {len(faces)} faces)"]
    if not np.all(np.isfinite(vertices)):
        return ["mesh has non-finite vertex coordinates"]
    return []


@dataclass(frozen=True)
class JsonSyntaxError:
    """A JSON file that does not parse; ``message`` holds line and column."""

    message: str


def load_json(path: Path) -> object | JsonSyntaxError:
    """The parsed JSON at ``path``, or a :class:`JsonSyntaxError` with line and column."""
    try:
        text = path.read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        return JsonSyntaxError(f"cannot read as UTF-8 text: {exc}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        where = f"line {exc.lineno} column {exc.colno}"
        return JsonSyntaxError(f"JSON syntax error at {where}: {exc.msg}")


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
