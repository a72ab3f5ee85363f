"""The session loader: valid sessions load; every malformed one names its file and field."""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from graspcap.tasks.session.discover import discover_sessions
from graspcap.tasks.session.load_session import (
    Problem,
    Session,
    SessionInvalid,
    Severity,
    load_session,
    validate_session,
)
from tests.session_factory import COLOR_H, COLOR_W, THERMAL_H, THERMAL_W, write_session

NAN = float("nan")
ROT_SCALED = [[2.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.5], [0, 0, 0, 1.0]]


def _manifest(d: Path, **changes) -> None:
    """Rewrite session.json with nested ``changes`` ("a.b" keys); NaN is written as Python does."""
    path = d / "session.json"
    manifest = json.loads(path.read_text())
    for dotted, value in changes.items():
        *parents, leaf = dotted.split(".")
        node = manifest
        for key in parents:
            node = node[key]
        if value is _DELETE:
            del node[leaf]
        else:
            node[leaf] = value
    path.write_text(json.dumps(manifest))


_DELETE = object()


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _png(path: Path, image: np.ndarray) -> None:
    assert cv2.imwrite(str(path), image)


def _keypoints(d: Path, index: int, document: object | str) -> None:
    text = document if isinstance(document, str) else json.dumps(document)
    (d / f"grasp/keypoints/{index:06d}_keypoints.json").write_text(text)


def _symlink_out(d: Path) -> None:
    outside = d.parent / "outside.png"
    _png(outside, np.full((COLOR_H, COLOR_W), 500, np.uint16))
    (d / "stage1/depth.png").unlink()
    os.symlink(outside, d / "stage1/depth.png")


def _symlink_dir_out(d: Path) -> None:
    outside = d.parent / "elsewhere"
    shutil.move(d / "scan/thermal", outside)
    os.symlink(outside, d / "scan/thermal")


def _mesh(d: Path, text: str) -> None:
    (d / "object.ply").write_text(text)


EMPTY_PLY = ("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
             "property float z\nelement face 0\nproperty list uchar int vertex_indices\n"
             "end_header\n")

# (name, mutate(session_dir), file, field prefix, message pattern)
Case = tuple[str, Callable[[Path], None], str, str, str]
CASES: list[Case] = [
    ("missing frame", lambda d: (d / "grasp/depth/000001.png").unlink(),
     "grasp/depth/000001.png", "grasp.depth", "does not exist"),
    ("missing stage1 depth", lambda d: (d / "stage1/depth.png").unlink(),
     "stage1/depth.png", "stage1.depth", "does not exist"),
    ("corrupt PNG", lambda d: (d / "stage1/depth.png").write_bytes(b"\x89PNG\r\n\x1a\nxxxx"),
     "stage1/depth.png", "stage1.depth", "truncated PNG|does not decode"),
    ("truncated PNG", lambda d: _truncate(d / "scan/thermal/001.png"),
     "scan/thermal/001.png", "scan.views[1].thermal", "truncated PNG"),
    ("truncated JPEG", lambda d: _truncate(d / "grasp/color/000002.jpg"),
     "grasp/color/000002.jpg", "grasp.color", "truncated"),
    ("JPEG of garbage", lambda d: (d / "grasp/color/000000.jpg").write_bytes(b"GIF89a" * 40),
     "grasp/color/000000.jpg", "grasp.color", "JPEG"),
    ("wrong colour size", lambda d: _png(d / "stage1/color.png", np.zeros((30, 40, 3), np.uint8)),
     "stage1/color.png", "stage1.color", "size 40x30, expected 80x60"),
    ("thermal at colour size",
     lambda d: _png(d / "scan/thermal/000.png", np.zeros((COLOR_H, COLOR_W), np.uint16)),
     "scan/thermal/000.png", "scan.views[0].thermal", f"expected {THERMAL_W}x{THERMAL_H}"),
    ("8-bit depth",
     lambda d: _png(d / "grasp/depth/000003.png", np.zeros((COLOR_H, COLOR_W), np.uint8)),
     "grasp/depth/000003.png", "grasp.depth", "uint16 single channel, got uint8"),
    ("3-channel 16-bit scan depth",
     lambda d: _png(d / "scan/depth/001.png", np.zeros((COLOR_H, COLOR_W, 3), np.uint16)),
     "scan/depth/001.png", "scan.views[1].depth", "3 channels"),
    ("grey stage1 colour",
     lambda d: _png(d / "stage1/color.png", np.zeros((COLOR_H, COLOR_W), np.uint8)),
     "stage1/color.png", "stage1.color", "8-bit 3-channel"),
    ("non-rigid transform", lambda d: _manifest(d, **{"turntable.T_color_turntable": ROT_SCALED}),
     "session.json", "turntable.T_color_turntable", "not a rigid transform"),
    ("NaN in K", lambda d: _manifest(d, **{"color_camera.K": [[NAN, 0, 40], [0, 70, 30],
                                                              [0, 0, 1]]}),
     "session.json", "color_camera.K", "finite"),
    ("Infinity in T",
     lambda d: _manifest(d, **{"thermal_camera.T_color_thermal": [
         [1, 0, 0, float("inf")], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}),
     "session.json", "thermal_camera.T_color_thermal", "finite"),
    ("fx <= 0", lambda d: _manifest(d, **{"color_camera.K": [[0, 0, 40], [0, 70, 30], [0, 0, 1]]}),
     "session.json", "color_camera.K", "focal"),
    ("principal point outside",
     lambda d: _manifest(d, **{"thermal_camera.K": [[35, 0, 20], [0, 35, 99], [0, 0, 1]]}),
     "session.json", "thermal_camera.K", "principal point"),
    ("path with ..", lambda d: _manifest(d, **{"stage1.color": "../x.png"}),
     "session.json", "stage1.color", "relative path"),
    ("absolute path", lambda d: _manifest(d, **{"scan.views": [
        {"thermal": str(d / "scan/thermal/000.png"), "depth": "scan/depth/000.png",
         "angle_deg": 0}]}),
     "session.json", "scan.views[0].thermal", "relative path"),
    ("symlink leading out", _symlink_out, "stage1/depth.png", "stage1.depth", "leaves"),
    ("symlinked folder leading out", _symlink_dir_out,
     "scan/thermal/000.png", "scan.views[0].thermal", "leaves"),
    ("60 keypoint numbers",
     lambda d: _keypoints(d, 1, {"people": [{"hand_right_keypoints_2d": [0.5] * 60}]}),
     "grasp/keypoints/000001_keypoints.json", "people[0].hand_right_keypoints_2d", "got 60"),
    ("keypoint confidence > 1",
     lambda d: _keypoints(d, 2, {"people": [{"hand_left_keypoints_2d": [10, 10, 1.5] * 21}]}),
     "grasp/keypoints/000002_keypoints.json", "people[0].hand_left_keypoints_2d", r"\[0, 1\]"),
    ("keypoint NaN", lambda d: _keypoints(d, 0, '{"people": [{"hand_right_keypoints_2d": ['
                                          + ", ".join(["NaN"] * 63) + "]}]}"),
     "grasp/keypoints/000000_keypoints.json", "people[0].hand_right_keypoints_2d", "finite"),
    ("keypoint JSON syntax", lambda d: _keypoints(d, 3, '{"people": [\n  {"hand_right'),
     "grasp/keypoints/000003_keypoints.json", "grasp.keypoints", "line 2 column"),
    ("keypoints without people", lambda d: _keypoints(d, 0, {"version": 1.3}),
     "grasp/keypoints/000000_keypoints.json", "people", "missing"),
    ("count too small (extra files)", lambda d: _manifest(d, **{"grasp.count": 3}),
     "grasp/depth/000003.png", "grasp.count", "frame 3 exists but count is 3"),
    ("count too large (missing files)", lambda d: _manifest(d, **{"grasp.count": 6}),
     "grasp/depth/000004.png", "grasp.count", "frames 0..3 only"),
    ("unknown key", lambda d: _manifest(d, **{"stage1.mask": "m.png"}),
     "session.json", "stage1.mask", "unknown key"),
    ("missing required key", lambda d: _manifest(d, depth_scale_m=_DELETE),
     "session.json", "depth_scale_m", "required"),
    ("wrong format version", lambda d: _manifest(d, format="grasp-capture-session/0"),
     "session.json", "format", "grasp-capture-session/1"),
    ("steady_from out of range", lambda d: _manifest(d, **{"grasp.steady_from": 4}),
     "session.json", "grasp.steady_from", "below count 4"),
    ("neither colour nor keypoints",
     lambda d: _manifest(d, **{"grasp.color": _DELETE, "grasp.keypoints": None}),
     "session.json", "grasp", "color and grasp.keypoints"),
    ("unparseable session.json",
     lambda d: (d / "session.json").write_text('{\n  "format": "grasp-capture-session/1",,\n}'),
     "session.json", "(file)", "line 2 column"),
    ("missing session.json", lambda d: (d / "session.json").unlink(),
     "session.json", "(file)", "missing"),
    ("mesh missing", lambda d: (d / "object.ply").unlink(), "object.ply", "object_mesh", "exist"),
    ("mesh empty", lambda d: _mesh(d, EMPTY_PLY), "object.ply", "object_mesh", "empty mesh"),
    ("mesh garbage", lambda d: _mesh(d, "solid nothing here\n"), "object.ply", "object_mesh", ""),
]


FRAME_LEVEL = {"truncated JPEG", "JPEG of garbage", "60 keypoint numbers",
               "keypoint confidence > 1", "keypoint NaN", "keypoint JSON syntax",
               "keypoints without people"}
"""Problems inside one grasp frame's colour image or keypoint file: reported, but the session
loads (that frame becomes a missing detection in detect_keypoints)."""


@pytest.fixture
def session_dir(tmp_path: Path) -> Path:
    return write_session(tmp_path / "s")


def test_valid_session_has_no_problems_and_loads(session_dir):
    assert validate_session(session_dir) == []
    session = load_session(session_dir)
    assert isinstance(session, Session)
    assert session.session_id == "p01-box-use-01"
    assert session.root == session_dir.resolve()


@pytest.mark.parametrize(("name", "mutate", "file", "field", "pattern"), CASES,
                         ids=[c[0] for c in CASES])
def test_malformed_session_names_file_and_field(session_dir, name, mutate, file, field, pattern):
    mutate(session_dir)
    problems = validate_session(session_dir)
    hits = [p for p in problems if p.file == file and p.field.startswith(field)
            and re.search(pattern, p.message)]
    assert hits, "\n".join(map(str, problems))
    assert all(isinstance(p, Problem) for p in problems)
    text = str(hits[0])
    assert text.startswith("session ") and f"file {file}: field {hits[0].field}: " in text
    if name in FRAME_LEVEL:
        assert [p.severity for p in problems] == [Severity.FRAME] * len(problems)
        assert text.endswith("(frame skipped)")
        assert load_session(session_dir).session_id == "p01-box-use-01"
        return
    assert hits[0].severity is Severity.ERROR
    with pytest.raises(SessionInvalid) as raised:
        load_session(session_dir)
    assert raised.value.problems == [p for p in problems if p.severity is Severity.ERROR]
    assert file in str(raised.value)


def test_enough_distinct_cases():
    assert len({(c[2], c[3]) for c in CASES}) >= 15


def test_all_problems_of_a_session_are_reported_together(session_dir):
    _manifest(session_dir, operator="ann", **{
        "color_camera.K": [[NAN, 0, 40], [0, 70, 30], [0, 0, 1]], "grasp.steady_from": 99,
        "scan.views": [{"thermal": "scan/thermal/000.png", "depth": "/abs/d.png", "angle_deg": 0},
                       {"thermal": "scan/thermal/001.png", "depth": "scan/depth/001.png",
                        "angle_deg": 180}]})
    _png(session_dir / "grasp/depth/000002.png", np.zeros((COLOR_W, COLOR_H), np.uint16))
    (session_dir / "grasp/depth/000001.png").unlink()
    _truncate(session_dir / "grasp/color/000002.jpg")
    _keypoints(session_dir, 3, {"people": [{"hand_right_keypoints_2d": [1.0] * 60}]})
    (session_dir / "object.ply").unlink()
    _png(session_dir / "scan/thermal/001.png", np.zeros((5, 5), np.uint8))
    problems = validate_session(session_dir)
    located = {(p.file, p.field) for p in problems}
    assert {("session.json", "operator"), ("session.json", "color_camera.K[0][0]"),
            ("grasp/depth/000001.png", "grasp.depth"), ("grasp/color/000002.jpg", "grasp.color"),
            ("grasp/keypoints/000003_keypoints.json", "people[0].hand_right_keypoints_2d"),
            ("object.ply", "object_mesh"), ("scan/thermal/001.png", "scan.views[1].thermal"),
            ("session.json", "grasp.steady_from"), ("session.json", "scan.views[0].depth"),
            } <= located
    assert all(p.session == "p01-box-use-01" for p in problems)
    # Sections are checked on their own: a bad K, steady_from or view 0 hides nothing else.
    messages = {(p.file, p.message) for p in problems}
    assert ("scan/thermal/001.png", "size 5x5, expected 40x32 (width x height)") in messages
    assert ("grasp/depth/000002.png", "size 60x80, expected 80x60 (width x height)") in messages


def test_check_images_false_skips_decoding_but_not_existence(session_dir):
    _truncate(session_dir / "grasp/depth/000000.png")
    (session_dir / "grasp/color/000003.jpg").unlink()
    quick = validate_session(session_dir, check_images=False)
    assert [(p.file, p.field) for p in quick] == [("grasp/color/000003.jpg", "grasp.count")]
    full = validate_session(session_dir)
    assert ("grasp/depth/000000.png", "grasp.depth") in {(p.file, p.field) for p in full}


def test_many_missing_frames_are_summarised(tmp_path):
    d = write_session(tmp_path / "s", frames=30)
    for i in range(0, 30, 2):  # 15 holes, not a missing tail
        (d / f"grasp/depth/{i:06d}.png").unlink()
    problems = [p for p in validate_session(d, check_images=False) if p.field == "grasp.depth"]
    assert [p.file for p in problems] == [f"grasp/depth/{i:06d}.png" for i in range(0, 30, 2)]


def test_readers_convert_units(session_dir):
    session = load_session(session_dir)
    raw = cv2.imread(str(session_dir / "stage1/depth.png"), cv2.IMREAD_UNCHANGED)
    depth_m = session.read_depth_m("stage1/depth.png")
    assert depth_m.dtype == np.float32 and depth_m.shape == (COLOR_H, COLOR_W)
    np.testing.assert_allclose(depth_m, raw * 0.001, rtol=1e-6)
    thermal_k = session.read_thermal_k(session_dir / "scan/thermal/000.png")
    assert thermal_k.dtype == np.float32 and thermal_k.shape == (THERMAL_H, THERMAL_W)
    assert 295.0 <= thermal_k.min() and thermal_k.max() <= 310.0
    color = session.read_color(session.grasp_path("color", 1))
    assert color.dtype == np.uint8 and color.shape == (COLOR_H, COLOR_W, 3)
    hands = session.read_keypoints(2)
    document = json.loads((session_dir / "grasp/keypoints/000002_keypoints.json").read_text())
    assert len(hands) == 1 and hands[0].shape == (21, 3)
    right = document["people"][0]["hand_right_keypoints_2d"]
    np.testing.assert_array_equal(hands[0].ravel(), right)


def test_session_paths_stay_inside(session_dir, tmp_path):
    session = load_session(session_dir)
    assert session.path("./stage1/depth.png") == session_dir.resolve() / "stage1/depth.png"
    for bad in ("../s/stage1/depth.png", "grasp/../stage1/depth.png", "/etc/hostname"):
        with pytest.raises(SessionInvalid):
            session.path(bad)
    with pytest.raises(SessionInvalid):
        session.read_depth_m(tmp_path / "elsewhere.png")
    assert session.grasp_path("depth", 3) == session_dir.resolve() / "grasp/depth/000003.png"
    with pytest.raises(IndexError):
        session.grasp_path("depth", 4)


def test_input_files_by_role(session_dir):
    files = load_session(session_dir).input_files()
    counts = {role: len(paths) for role, paths in files.items()}
    assert counts == {"manifest": 1, "object_mesh": 1, "stage1": 2, "grasp_color": 4,
                      "grasp_depth": 4, "grasp_keypoints": 4, "scan_thermal": 2, "scan_depth": 2}
    assert all(p.is_file() for paths in files.values() for p in paths)


def test_keypoints_only_left_hand_session(tmp_path):
    d = write_session(tmp_path / "s", hand="left", grasp={"color": None})
    shutil.rmtree(d / "grasp/color")
    _keypoints(d, 0, {"people": []})
    _keypoints(d, 1, {"people": [{"hand_left_keypoints_2d": [20, 10, 0.5] * 21,
                                  "hand_right_keypoints_2d": []}, {"pose_keypoints_2d": []}]})
    session = load_session(d)
    assert session.grasp_path("color", 0) is None
    assert session.input_files()["grasp_color"] == []
    assert session.read_keypoints(0) == []
    first, second = session.read_keypoints(1)
    np.testing.assert_array_equal(first[:, 2], np.full(21, 0.5))
    np.testing.assert_array_equal(second, np.zeros((21, 3)))  # no left hand: not detected


def test_real_openpose_file_is_read(session_dir, shared_data):
    source = shared_data / "openpose_hand_json" / "COCO_val2014_000000000192_keypoints.json"
    shutil.copyfile(source, session_dir / "grasp/keypoints/000000_keypoints.json")
    assert validate_session(session_dir) == []
    document = json.loads(source.read_text())
    hands = load_session(session_dir).read_keypoints(0)
    assert len(hands) == len(document["people"]) >= 1
    expected = np.reshape(document["people"][0]["hand_right_keypoints_2d"], (21, 3))
    np.testing.assert_allclose(hands[0], expected)


def test_discover_sessions(tmp_path):
    root = tmp_path / "root"
    for name in ("b", "a", "group/c"):
        write_session(root / name, frames=1, views=1)
    (root / "not_a_session" / "deeper").mkdir(parents=True)
    (root / "not_a_session" / "notes.json").write_text("{}")
    found = discover_sessions([root])
    assert found == [root / "a", root / "b", root / "group/c"]
    assert discover_sessions([root / "a", root]) == found  # a session root, and duplicates
    assert discover_sessions([root / "not_a_session"]) == []
    assert discover_sessions([tmp_path / "absent"]) == []


def test_one_bad_path_gives_one_problem(session_dir):
    _manifest(session_dir, **{"scan.views": [{"thermal": "/abs/000.png", "depth": "d/../../x.png",
                                              "angle_deg": 0}]})
    problems = validate_session(session_dir)
    assert [(p.file, p.field) for p in problems] == [
        ("session.json", "scan.views[0].thermal"), ("session.json", "scan.views[0].depth")]


def test_long_lists_of_missing_frames_are_capped(tmp_path):
    d = write_session(tmp_path / "s", frames=30)
    for i in range(29):  # all but the last frame: holes, not a short count
        (d / f"grasp/color/{i:06d}.jpg").unlink()
    problems = [p for p in validate_session(d, check_images=False) if p.field == "grasp.color"]
    assert len(problems) == 21
    assert problems[-1].file == "grasp/color/{index:06d}.jpg"
    assert problems[-1].message == "9 more frames missing"


def test_stage_inputs_read_from_the_session(session_dir):
    """What the pipeline's glue hands the stages: intrinsics, turntable, the mesh, depth."""
    session = load_session(session_dir)
    np.testing.assert_array_equal(session.color_K,
                                  [[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]])
    assert session.color_K.dtype == float
    T = session.T_color_turntable
    assert T.shape == (4, 4) and T.dtype == float
    np.testing.assert_allclose(T[:3, 3], [0.0, 0.1, 0.6])
    assert session.mesh_name == "object_mesh object.ply"
    V, F = session.read_mesh()
    assert V.shape == (8, 3) and V.dtype == float and F.shape == (12, 3) and F.dtype == np.int64
    np.testing.assert_allclose(V[1], [-0.03, -0.03, 0.06])  # file order, not re-sorted
    read = session.grasp_depth_reader(cached_frames=2)
    np.testing.assert_array_equal(read(3), session.read_depth_m(session.grasp_path("depth", 3)))
    assert read(3) is read(3)  # kept
    read(0), read(1)
    assert read.cache_info().currsize == 2
