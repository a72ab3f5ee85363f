"""A corpus of malformed and unusual capture sessions, each with the exact outcome it must get.

Every :class:`Kind` mutates a good session written by the independent writer
(``tests/session_factory.py``, see :func:`prepare`) and states its outcome:

- :class:`Invalid`: validation rejects the session, naming the file and the field;
- :class:`Fails`: the session is valid, and a stage fails it with that reason;
- :class:`Builds`: the session builds, with a note (and, for a problem inside one grasp
  frame, a frame-level problem naming that frame's file and field).

It holds every row of issue 15's table, the malformed kinds
``tests/tasks/session/test_validate.py`` already checks (imported from there, not copied) and
the kinds of the validator's limits. ``tests/tasks/session/test_reliability_validate.py`` runs
every kind through ``validate_session`` and ``graspcap validate``. The stage-level outcomes
(:class:`Fails`, the notes of :class:`Builds`) are the ones the issue asks for; those with
``verified=False`` are data for the build's own tests (other modules make them true): only their
validity is checked here; ``verified=True`` ones are built and checked by
``tests/tasks/test_stage_messages.py``, ``tests/flows/test_build_isolation.py`` or
``tests/flows/test_build_meshes.py`` (on sessions the stages get through), and
``tests/flows/test_reliability_build.py`` builds the whole corpus with good sessions in one
build.
"""

from __future__ import annotations

import json
import os
import re
import socket
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tests.session_factory import COLOR_H, COLOR_W, THERMAL_H, THERMAL_W, box_ply, write_session
from tests.tasks.session.test_validate import (
    _DELETE,
    CASES,
    FRAME_LEVEL,
    _keypoints,
    _manifest,
    _png,
)


@dataclass(frozen=True)
class Invalid:
    """Validation rejects the session with an error naming ``file`` (relative to the session)
    and a field starting with ``field``; its message matches the regex ``message``."""

    file: str
    field: str
    message: str = ""


@dataclass(frozen=True)
class Fails:
    """The session is valid; stage ``stage`` fails it with a reason containing
    ``message_contains``."""

    stage: str
    message_contains: str
    verified: bool = False
    """Whether a test in this repository builds the kind and checks the reason already."""


@dataclass(frozen=True)
class Builds:
    """The session is valid and builds, with a note containing ``note_contains``. When
    ``frame_file`` is given, validation reports a frame-level problem (that frame becomes a
    missing detection) naming that file and a field starting with ``frame_field``."""

    note_contains: str = ""
    frame_file: str | None = None
    frame_field: str | None = None
    verified: bool = False


Outcome = Invalid | Fails | Builds


@dataclass(frozen=True)
class Kind:
    """One kind of malformed or unusual session."""

    name: str
    mutate: Callable[[Path], None]
    """Changes a good session directory (written by :func:`prepare`) into this kind."""
    outcome: Outcome
    issue_row: bool = False
    """A row of issue 15's table."""
    hangs: bool = False
    """Hung, or exhausted memory, before the validator bounded it (run in a subprocess)."""

    @property
    def slug(self) -> str:
        return re.sub(r"[^a-z0-9]+", "-", self.name.lower()).strip("-")[:60]


DUPLICATE_ID = "good-session-0"
"""The id of the first good session in a build of the corpus; the duplicate-id kind takes it."""


def prepare(directory: Path, kind: Kind) -> Path:
    """A good session at ``directory`` (id ``kind-<slug>``) changed into ``kind``."""
    write_session(directory, session_id=f"kind-{kind.slug}")
    kind.mutate(directory)
    return directory


# --- helpers ---------------------------------------------------------------------------------

def _replace_with_dir(rel: str) -> Callable[[Path], None]:
    def mutate(d: Path) -> None:
        (d / rel).unlink()
        (d / rel).mkdir()
    return mutate


def _replace_with_fifo(rel: str) -> Callable[[Path], None]:
    def mutate(d: Path) -> None:
        (d / rel).unlink()
        os.mkfifo(d / rel)
    return mutate


def _replace_with_socket(rel: str) -> Callable[[Path], None]:
    def mutate(d: Path) -> None:
        path = d / rel
        path.unlink()
        here = os.getcwd()
        os.chdir(path.parent)  # a relative name: AF_UNIX paths are limited to ~108 bytes
        try:
            with socket.socket(socket.AF_UNIX) as sock:
                sock.bind(path.name)
        finally:
            os.chdir(here)
    return mutate


def _write(rel: str, data: bytes | str) -> Callable[[Path], None]:
    def mutate(d: Path) -> None:
        if isinstance(data, str):
            (d / rel).write_text(data)
        else:
            (d / rel).write_bytes(data)
    return mutate


def _sparse(rel: str, size: int, head: bytes = b"") -> Callable[[Path], None]:
    """The file at ``rel`` made ``size`` bytes long without writing them (a sparse file)."""
    def mutate(d: Path) -> None:
        (d / rel).write_bytes(head)
        os.truncate(d / rel, size)
    return mutate


def _set(**changes) -> Callable[[Path], None]:
    """Rewrite session.json with dotted-key changes (``tests/test_validate._manifest``)."""
    return lambda d: _manifest(d, **changes)


def _png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png_claiming(width: int, height: int) -> bytes:
    """A small, well-formed-looking 16-bit grey PNG whose header claims ``width x height``."""
    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
            + _png_chunk(b"IDAT", zlib.compress(b"\0" * 4096)) + _png_chunk(b"IEND", b""))


def _png_with_stream(d: Path, rel: str, stream: bytes) -> None:
    """A depth PNG of the right size whose IDAT holds ``stream`` (with a valid CRC)."""
    ihdr = struct.pack(">IIBBBBB", COLOR_W, COLOR_H, 16, 0, 0, 0, 0)
    (d / rel).write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr)
                          + _png_chunk(b"IDAT", stream) + _png_chunk(b"IEND", b""))


def _good_depth_stream() -> bytes:
    rows = b"".join(b"\0" + np.full(COLOR_W, 600, ">u2").tobytes() for _ in range(COLOR_H))
    return zlib.compress(rows)


def _deep_json(levels: int, key: str) -> str:
    return '{"' + key + '": ' + "[" * levels + "]" * levels + "}"


def _big_mesh(d: Path, faces: int = 2_000_000) -> None:
    """A real binary PLY of ``faces`` triangles over 8 vertices (26 MB)."""
    vertices = np.array([(x, y, z) for x in (-0.03, 0.03) for y in (-0.03, 0.03)
                         for z in (0.0, 0.06)], "<f4")
    face = np.zeros(faces, dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"] = 3
    face["v"] = np.random.default_rng(0).integers(0, 8, (faces, 3))
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex 8\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {faces}\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    (d / "object.ply").write_bytes(head + vertices.tobytes() + face.tobytes())


def _mesh_index_past_end(d: Path) -> None:
    text = box_ply()
    assert "3 1 7 3\n" in text
    (d / "object.ply").write_text(text.replace("3 1 7 3\n", "3 1 7 99\n"))


def _mesh_nan_vertex(d: Path) -> None:
    lines = box_ply().splitlines()
    first = lines.index("end_header") + 1
    lines[first] = "nan 0 0"
    (d / "object.ply").write_text("\n".join(lines) + "\n")


def _mesh_other_vertices(d: Path) -> None:
    """The same object_id as the good sessions ('box') with another mesh: 9 vertices."""
    text = box_ply().replace("element vertex 8", "element vertex 9")
    head, body = text.split("end_header\n")
    (d / "object.ply").write_text(head + "end_header\n0 0 0.1\n" + body)


def _symlink_loop(d: Path) -> None:
    (d / "stage1/depth.png").unlink()
    os.symlink("depth.png", d / "stage1/depth.png")


def _keypoints_all(d: Path, document: dict) -> None:
    for i in range(4):
        _keypoints(d, i, document)


def _hand(x: float, y: float, c: float = 0.9) -> list[float]:
    return [x, y, c] * 21


def _one_view(d: Path) -> None:
    manifest = json.loads((d / "session.json").read_text())
    manifest["scan"]["views"] = manifest["scan"]["views"][:1]
    (d / "session.json").write_text(json.dumps(manifest))


def _views(n: int) -> list[dict]:
    return [{"thermal": "scan/thermal/000.png", "depth": "scan/depth/000.png",
             "angle_deg": 360.0 * j / n} for j in range(n)]


def _obj_mesh(d: Path) -> None:
    lines = box_ply().splitlines()
    start = lines.index("end_header") + 1
    vertices, faces = lines[start:start + 8], lines[start + 8:]
    text = "".join(f"v {v}\n" for v in vertices) + "".join(
        "f " + " ".join(str(int(i) + 1) for i in f.split()[1:]) + "\n" for f in faces)
    (d / "object.ply").unlink()
    (d / "object.obj").write_text(text)
    _manifest(d, object_mesh="object.obj")


def _left_hand(d: Path) -> None:
    _keypoints_all(d, {"people": [{"hand_left_keypoints_2d": _hand(40, 30)}]})
    _manifest(d, hand="left")


WIDE = [[3.0, 0, 40.0], [0, 3.0, 30.0], [0, 0, 1]]
ROW = "grasp/keypoints/000001_keypoints.json"

# --- the kinds -------------------------------------------------------------------------------

ISSUE_ROWS: list[Kind] = [
    Kind("same object_id, another mesh", _mesh_other_vertices,
         Builds(note_contains="labels 2 different object meshes", verified=True), issue_row=True),
    Kind("duplicate session_id across folders", _set(session_id=DUPLICATE_ID),
         Fails(stage="build", message_contains="is also the id of", verified=True), issue_row=True),
    Kind("session_id of 300 characters", _set(session_id="s" * 300),
         Invalid("session.json", "session_id", "not a session id"), issue_row=True),
    Kind("session_id with a newline", _set(session_id="p01\nmug"),
         Invalid("session.json", "session_id", "1-128 characters"), issue_row=True),
    Kind("session_id with a NUL", _set(session_id="p01\0mug"),
         Invalid("session.json", "session_id", "1-128 characters"), issue_row=True),
    Kind("object_mesh is a directory", _replace_with_dir("object.ply"),
         Invalid("object.ply", "object_mesh", "is a directory, not a file"), issue_row=True),
    Kind("depth frame is a directory", _replace_with_dir("grasp/depth/000001.png"),
         Invalid("grasp/depth/000001.png", "grasp.depth", "is a directory, not a file"),
         issue_row=True),
    Kind("session.json nested 100000 levels", _write("session.json", _deep_json(100_000, "a")),
         Invalid("session.json", "(file)", "nest deeper than 64"), issue_row=True),
    Kind("keypoint file is a directory", _replace_with_dir(ROW),
         Invalid(ROW, "grasp.keypoints", "is a directory, not a file"), issue_row=True),
    Kind("FIFO as a depth PNG", _replace_with_fifo("grasp/depth/000002.png"),
         Invalid("grasp/depth/000002.png", "grasp.depth", "FIFO"), issue_row=True, hangs=True),
    Kind("grasp.count of 10^12", _set(**{"grasp.count": 10**12}),
         Invalid("session.json", "grasp.count", "SessionLimits.max_frames"),
         issue_row=True, hangs=True),
    Kind("frame pattern of a gigabyte", _set(**{"grasp.depth": "grasp/{index:0999999999d}.png"}),
         Invalid("session.json", "grasp.depth", "SessionLimits.max_path_chars"),
         issue_row=True, hangs=True),
    Kind("2-million-face mesh", _big_mesh,
         Invalid("object.ply", "object_mesh", "2000000 faces .*max_mesh_faces"), issue_row=True),
    Kind("session_id climbing out", _set(session_id="../../../../tmp/escaped-session"),
         Invalid("session.json", "session_id", "not a session id"), issue_row=True),
    Kind("session_id with a slash", _set(session_id="a/b"),
         Invalid("session.json", "session_id", "not a session id"), issue_row=True),
    Kind("keypoint JSON nested deeply", _write(ROW, _deep_json(50_000, "people")),
         Builds(frame_file=ROW, frame_field="grasp.keypoints"), issue_row=True),
    Kind("symlink loop", _symlink_loop,
         Invalid("stage1/depth.png", "stage1.depth", "symlink loop"), issue_row=True),
    Kind("frame pattern {index.nope}", _set(**{"grasp.depth": "grasp/depth/{index.nope}.png"}),
         Invalid("session.json", "grasp.depth", r"\{index.nope\} is not allowed"),
         issue_row=True),
    Kind("frame pattern {index[0]}", _set(**{"grasp.color": "grasp/color/{index[0]}.jpg"}),
         Invalid("session.json", "grasp.color", r"\{index\[0\]\} is not allowed"),
         issue_row=True),
    Kind("empty depth file", _write("grasp/depth/000000.png", b""),
         Invalid("grasp/depth/000000.png", "grasp.depth", r"empty file \(0 bytes\)"),
         issue_row=True),
    Kind("all-zero thermal image",
         lambda d: _png(d / "scan/thermal/000.png", np.zeros((THERMAL_H, THERMAL_W), np.uint16)),
         Fails(stage="build_contactmap", message_contains="scan/thermal/000.png",
               verified=True),
         issue_row=True),
    Kind("mesh face index out of range", _mesh_index_past_end,
         Invalid("object.ply", "object_mesh",
                 r"face 11 indexes vertices \[1, 7, 99\], but the mesh has 8 vertices"),
         issue_row=True),
    Kind("root folder without session.json", lambda d: (d / "session.json").unlink(),
         Invalid("session.json", "(file)", "missing"), issue_row=True),
    Kind("keypoints only for the other hand",
         lambda d: _keypoints_all(d, {"people": [{"hand_left_keypoints_2d": _hand(40, 30),
                                                  "hand_right_keypoints_2d": []}]}),
         Fails(stage="detect_keypoints", message_contains="hand_left_keypoints_2d",
               verified=True),
         issue_row=True),
    Kind("keypoints at 1e8 px",
         lambda d: _keypoints_all(d, {"people": [{"hand_right_keypoints_2d": _hand(1e8, 1e8)}]}),
         Fails(stage="detect_keypoints", message_contains="outside the image"), issue_row=True),
    Kind("one corrupt keypoint file", _write(ROW, '{"people": [{"hand_right_keypoints_2d": [1,'),
         Builds(frame_file=ROW, frame_field="grasp.keypoints"), issue_row=True),
    Kind("fx of 1e300", _set(**{"color_camera.K": [[1e300, 0, 40.0], [0, 70.0, 30.0],
                                                   [0, 0, 1]]}),
         Invalid("session.json", "color_camera.K", "field of view"), issue_row=True),
    Kind("thermal focal length 100x", _set(**{"thermal_camera.K": [[3500.0, 0, 20.0],
                                                                   [0, 3500.0, 16.0],
                                                                   [0, 0, 1]]}),
         Invalid("session.json", "thermal_camera.K", "field of view"), issue_row=True),
    Kind("dist of 1e300", _set(**{"color_camera.dist": [1e300, 0, 0, 0, 0]}),
         Invalid("session.json", "color_camera.dist", "beyond"), issue_row=True),
    Kind("keypoint frame with two people",
         lambda d: _keypoints(d, 2, {"people": [{"hand_right_keypoints_2d": _hand(30, 20)},
                                                {"hand_right_keypoints_2d": _hand(50, 40)}]}),
         Builds(note_contains="had more than one right hand", verified=True), issue_row=True),
    Kind("one scan view", _one_view,
         Builds(note_contains="one thermal view only", verified=True), issue_row=True),
]
"""Every row of issue 15's table (two-input rows split into one kind per input)."""


LIMITS_AND_FILES: list[Kind] = [
    Kind("session_id empty", _set(session_id=""),
         Invalid("session.json", "session_id", "not a session id")),
    Kind("session_id starting with a dot", _set(session_id=".hidden"),
         Invalid("session.json", "session_id", "not starting with '.'")),
    Kind("session_id with a space", _set(session_id="p01 mug"),
         Invalid("session.json", "session_id", "not a session id")),
    Kind("session_id not a string", _set(session_id=17),
         Invalid("session.json", "session_id", "string")),
    Kind("keypoint JSON of 50 MB", _sparse(ROW, 50 * 2**20, b'{"people": []}'),
         Builds(frame_file=ROW, frame_field="grasp.keypoints")),
    Kind("session.json of 5 MB", _sparse("session.json", 5 * 2**20, b"{"),
         Invalid("session.json", "(file)", "more than the limit")),
    Kind("session.json is a FIFO", _replace_with_fifo("session.json"),
         Invalid("session.json", "(file)", "FIFO"), hangs=True),
    Kind("session.json is not UTF-8", _write("session.json", b'{"format": "\xff\xfe"}'),
         Invalid("session.json", "(file)", "not UTF-8")),
    Kind("session.json is a list", _write("session.json", "[1, 2]"),
         Invalid("session.json", "(file)", "top level must be an object")),
    Kind("session.json with a 5000-digit number", _write("session.json", "1" * 5000),
         Invalid("session.json", "(file)", "parse")),
    Kind("PNG header claims 60000 x 60000", _write("stage1/depth.png", _png_claiming(60000, 60000)),
         Invalid("stage1/depth.png", "stage1.depth", "header claims 60000x60000")),
    Kind("depth frame is a socket", _replace_with_socket("grasp/depth/000003.png"),
         Invalid("grasp/depth/000003.png", "grasp.depth", "socket")),
    Kind("scan thermal is a FIFO", _replace_with_fifo("scan/thermal/001.png"),
         Invalid("scan/thermal/001.png", "scan.views[1].thermal", "FIFO"), hangs=True),
    Kind("empty stage1 colour", _write("stage1/color.png", b""),
         Invalid("stage1/color.png", "stage1.color", "empty file")),
    Kind("empty colour frame", _write("grasp/color/000001.jpg", b""),
         Builds(frame_file="grasp/color/000001.jpg", frame_field="grasp.color")),
    Kind("PNG stream cut short, valid CRC",
         lambda d: _png_with_stream(d, "grasp/depth/000000.png", _good_depth_stream()[:-40]),
         Invalid("grasp/depth/000000.png", "grasp.depth", "corrupt PNG")),
    Kind("PNG stream of garbage, valid CRC",
         lambda d: _png_with_stream(d, "grasp/depth/000001.png", b"\x78\x9c" + b"\0\xff" * 20),
         Invalid("grasp/depth/000001.png", "grasp.depth", "corrupt PNG")),
    Kind("frame pattern with another field", _set(**{"grasp.depth": "grasp/{camera}/{index}.png"}),
         Invalid("session.json", "grasp.depth", r"\{camera\} is not allowed")),
    Kind("frame pattern with an unbalanced brace", _set(**{"grasp.depth": "grasp/{index:06d.png"}),
         Invalid("session.json", "grasp.depth", "not a format pattern")),
    Kind("frame pattern with a nested spec",
         _set(**{"grasp.keypoints": "k/{index:{index}}.json"}),
         Invalid("session.json", "grasp.keypoints", "not an integer format")),
    Kind("path with a trailing newline", _set(**{"stage1.depth": "stage1/depth.png\n"}),
         Invalid("session.json", "stage1.depth", "no control character")),
    Kind("frame pattern with a tab", _set(**{"grasp.depth": "grasp/depth/\t{index:06d}.png"}),
         Invalid("session.json", "grasp.depth", "relative path")),
    Kind("mesh path with a NUL", _set(object_mesh="object\0.ply"),
         Invalid("session.json", "object_mesh", "relative path")),
    Kind("frame pattern with a conversion", _set(**{"grasp.depth": "grasp/{index!r}.png"}),
         Invalid("session.json", "grasp.depth", "not allowed")),
    Kind("721 scan views", _set(**{"scan.views": _views(721)}),
         Invalid("session.json", "scan.views", "SessionLimits.max_scan_views")),
    Kind("camera of 60000 x 60000", _set(**{"color_camera.width": 60000,
                                            "color_camera.height": 60000}),
         Invalid("session.json", "color_camera.height", "max_image_pixels")),
    Kind("field of view over 170 degrees", _set(**{"color_camera.K": WIDE}),
         Invalid("session.json", "color_camera.K", "field of view")),
    Kind("fy ten times fx", _set(**{"color_camera.K": [[70.0, 0, 40.0], [0, 700.0, 30.0],
                                                       [0, 0, 1]]}),
         Invalid("session.json", "color_camera.K", "square")),
    Kind("depth scale of 5 m", _set(depth_scale_m=5.0),
         Invalid("session.json", "depth_scale_m", "outside")),
    Kind("thermal dist of 6 numbers", _set(**{"thermal_camera.dist": [0.0] * 6}),
         Invalid("session.json", "thermal_camera.dist", "6 coefficients")),
    Kind("reflection in T_color_turntable", _set(**{"turntable.T_color_turntable": [
        [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, -1.0, 0.5], [0, 0, 0, 1.0]]}),
         Invalid("session.json", "turntable.T_color_turntable", "reflection")),
    Kind("T_color_thermal last row", _set(**{"thermal_camera.T_color_thermal": [
        [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0.2, 0, 0, 1.0]]}),
         Invalid("session.json", "thermal_camera.T_color_thermal", "last row")),
    Kind("grasp.count of 0", _set(**{"grasp.count": 0}),
         Invalid("session.json", "grasp.count", "greater than or equal to 1")),
    Kind("width as a string", _set(**{"color_camera.width": "80"}),
         Invalid("session.json", "color_camera.width", "integer")),
    Kind("hand both", _set(hand="both"), Invalid("session.json", "hand", "right")),
    Kind("mesh as .glb", _set(object_mesh="object.glb"),
         Invalid("session.json", "object_mesh", r"\.ply, \.obj or \.stl")),
    Kind("no scan views", _set(**{"scan.views": []}),
         Invalid("session.json", "scan.views", "at least one view")),
    Kind("mesh with a NaN vertex", _mesh_nan_vertex,
         Invalid("object.ply", "object_mesh", "non-finite")),
    Kind("mesh is a FIFO", _replace_with_fifo("object.ply"),
         Invalid("object.ply", "object_mesh", "FIFO"), hangs=True),
    Kind("session.json is a directory", _replace_with_dir("session.json"),
         Invalid("session.json", "(file)", "is a directory")),
    Kind("left hand", _left_hand, Builds()),
    Kind("no keypoint files (the builder detects)", _set(**{"grasp.keypoints": _DELETE}),
         Builds()),
    Kind("OBJ mesh", _obj_mesh, Builds()),
    Kind("14 distortion coefficients", _set(**{"color_camera.dist": [0.01] * 14}), Builds()),
    Kind("real Kinect distortion", _set(**{"color_camera.dist": [0.1, -0.25, 0.001, -0.002,
                                                                 0.08]}), Builds()),
    Kind("session_id of 128 characters", _set(session_id="s" * 128), Builds()),
]
"""The validator's limits and file checks, and unusual kinds that are valid."""


EXISTING: list[Kind] = [
    Kind(name, mutate,
         Builds(frame_file=file, frame_field=field) if name in FRAME_LEVEL
         else Invalid(file, field, pattern))
    for name, mutate, file, field, pattern in CASES
    if name != "missing session.json"  # the same kind as the issue's folder without one
]
"""The kinds ``tests/tasks/session/test_validate.py`` checks (its cases, with their outcomes)."""


KINDS: list[Kind] = ISSUE_ROWS + LIMITS_AND_FILES + EXISTING
"""Every kind of the corpus."""

assert len({k.slug for k in KINDS}) == len(KINDS), "kind names must give distinct folders"
