"""The training path with images (issue 20 item 4): frame items with decoded colour and depth,
their files and intrinsics from the session folder the build recorded; ``collate_fn`` over
items of different objects; the ContactPose-style ``Catalog.session`` view; a torch
``DataLoader`` with workers where torch is installed.

The image tests read the warm build of two synthetic sessions the flow tests share
(``tests/flow_fixtures.py``); the collate tests a factory catalog of three objects whose
meshes differ in vertex count (no images there)."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

import graspcap.catalog as gc
from graspcap.catalog.collate import SESSION_ARRAYS
from tests.catalog_factory import OBJECT_VERTICES, make_build

IDS = ["p01-mug-use-00", "p01-drill-handoff-00", "p02-bowl-use-00", "p02-mug-handoff-00"]
FRAMES = 20


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """A factory catalog: 4 sessions of 3 objects (mug 40, drill 60, bowl 30 vertices)."""
    cat = gc.open(tmp_path_factory.mktemp("mixed"), create=True)
    cat.commit(make_build(IDS, seed=3, frames=FRAMES))
    return cat


def _writable(value) -> bool:
    if isinstance(value, np.ndarray):
        return value.flags.writeable
    if isinstance(value, dict):
        return all(_writable(v) for v in value.values())
    if isinstance(value, list):
        return all(_writable(v) for v in value)
    return True


def _manifest(synth_root, session_id: str) -> dict:
    return json.loads((synth_root / session_id / "session.json").read_text())


def test_image_items_decode_the_recorded_session_files(warm, synth_root):
    catalog, _ = warm
    ds = gc.GraspDataset(catalog, images=True)
    items = [ds[0], ds[len(ds) - 1]]
    assert {it["session_id"] for it in items} == set(ds.session_ids)  # one of each session
    for item in items:
        sid, frame = item["session_id"], int(item["frame"])
        m = _manifest(synth_root, sid)
        folder = synth_root / sid
        color_file = folder / m["grasp"]["color"].format(index=frame)
        depth_file = folder / m["grasp"]["depth"].format(index=frame)
        assert item["color_path"] == str(color_file) and item["depth_path"] == str(depth_file)
        w, h = m["color_camera"]["width"], m["color_camera"]["height"]
        assert item["color"].shape == (h, w, 3) and item["color"].dtype == np.uint8
        assert item["depth"].shape == (h, w) and item["depth"].dtype == np.float32
        assert m["color_camera"]["dist"] == [0.0] * 5  # so the images are the files as is
        np.testing.assert_array_equal(item["color"], cv2.imread(str(color_file))[..., ::-1])
        raw = cv2.imread(str(depth_file), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(item["depth"],
                                      raw.astype(np.float32) * np.float32(m["depth_scale_m"]))
        assert 0.1 < float(np.median(item["depth"][item["depth"] > 0])) < 3.0  # metres
        np.testing.assert_array_equal(item["K"], np.array(m["color_camera"]["K"]))
        np.testing.assert_array_equal(item["image_size"], [w, h])
        assert _writable(item)
    item = ds[0]
    item["color"][:] = 0  # the item's own arrays: the next read is untouched
    item["T_c_o"][:] = 0
    assert ds[0]["color"].any() and ds[0]["T_c_o"][3, 3] == 1.0

    paths = gc.GraspDataset(catalog, images="paths")[0]
    assert paths["color_path"] == ds[0]["color_path"] and "color" not in paths
    np.testing.assert_array_equal(paths["K"], ds[0]["K"])
    batch = gc.collate_fn([ds[i] for i in (0, 1, len(ds) - 1)])
    assert batch["color"].shape == (3, 480, 640, 3) and batch["depth"].shape == (3, 480, 640)
    assert batch["K"].shape == (3, 3, 3) and batch["color_path"][2] == items[1]["color_path"]
    with pytest.raises(ValueError, match="images are per frame"):
        gc.GraspDataset(catalog, unit="sessions", images=True)
    with pytest.raises(ValueError, match=r"images='rgb'\): one of True, False, 'paths'"):
        gc.GraspDataset(catalog, images="rgb")


def test_session_view_is_contactpose_shaped(warm, synth_root):
    catalog, _ = warm
    cat = gc.open(catalog)
    frames = cat.table("frames", columns=["session_id", "frame", "T_c_o", "joints_c",
                                          "joints_2d_px", "reproj_err_px"]).to_pylist()
    sid = cat.table("sessions")["session_id"][0].as_py()
    rows = sorted((r for r in frames if r["session_id"] == sid), key=lambda r: r["frame"])
    view = cat.session(sid)
    assert view.frames == [r["frame"] for r in rows] and len(view.frames) > 20
    m = _manifest(synth_root, sid)
    K = np.array(m["color_camera"]["K"])
    np.testing.assert_array_equal(view.K, K)
    np.testing.assert_array_equal(view.image_size, [640, 480])
    vertices, _ = cat.object_mesh(session_id=sid)
    compared = 0
    for r in rows:
        f = r["frame"]
        T_c_o = np.array(r["T_c_o"]).reshape(4, 4)
        np.testing.assert_array_equal(view.object_pose(f), T_c_o)
        np.testing.assert_array_equal(view.hand_joints(f), np.array(r["joints_c"]).reshape(21, 3))
        # P projects object-frame points: the same pixels as K after T_c_o
        uvw = np.c_[vertices, np.ones(len(vertices))] @ view.P(f).T
        cam = vertices @ T_c_o[:3, :3].T + T_c_o[:3, 3]
        np.testing.assert_allclose(uvw[:, :2] / uvw[:, 2:], (cam @ K.T)[:, :2] / cam[:, 2:],
                                   rtol=0, atol=1e-9)
        # projected joints are what reproj_err_px measured against the detections
        err = np.array(r["reproj_err_px"], dtype=float)
        seen = np.isfinite(err)
        observed = np.array(r["joints_2d_px"]).reshape(21, 2)
        dist = np.linalg.norm(view.projected_hand_joints(f) - observed, axis=1)
        np.testing.assert_allclose(dist[seen], err[seen], rtol=0, atol=1e-6)
        compared += int(seen.sum())
    assert compared > 100
    color, depth = view.image_filenames(view.frames[0])
    assert color == synth_root / sid / m["grasp"]["color"].format(index=view.frames[0])
    assert depth.is_file()
    assert view.color(view.frames[0]).shape == (480, 640, 3)
    np.testing.assert_array_equal(view.hand_joints_o, cat.hand_joints(sid))
    with pytest.raises(KeyError, match=f"session '{sid}' has no catalog row for frame 0"):
        view.object_pose(0)  # before the steady frame
    with pytest.raises(KeyError, match="not in catalog version 1"):
        cat.session("nobody")
    same = gc.GraspDataset(catalog).session(sid)
    np.testing.assert_array_equal(same.P(view.frames[-1]), view.P(view.frames[-1]))


def test_images_without_a_session_folder_say_why(mixed, tmp_path):
    with pytest.raises(gc.CatalogError, match="recorded no session folder"):
        gc.GraspDataset(mixed, images=True)[0]
    gone = tmp_path / "gone"
    build = make_build(IDS[:1], seed=3, frames=2, build_id="moved")
    build = dataclasses.replace(build, build=dataclasses.replace(build.build, parameters={
        "report": {"sessions": [{"session_id": IDS[0], "session_dir": str(gone / IDS[0])}]}}))
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(build)
    want = (f"session '{IDS[0]}' \\(catalog version 1, build 'moved'\\): "
            f"{gone / IDS[0] / 'session.json'} is missing")
    with pytest.raises(gc.CatalogError, match=want):
        gc.GraspDataset(cat, images="paths", valid_only=False)[0]
    with pytest.raises(gc.CatalogError, match=want):
        view = cat.session(IDS[0])
        view.image_filenames(view.frames[0])


def test_collate_batches_items_of_different_objects(mixed):
    ds = gc.GraspDataset(mixed, valid_only=False)
    items = [ds[i] for i in range(len(ds))]
    assert len(items) == 4 * FRAMES
    assert {it["object_id"] for it in items} == {"mug", "drill", "bowl"}
    batch = gc.collate_fn(items)
    assert batch["T_c_o"].shape == (4 * FRAMES, 4, 4) and batch["frame"].shape == (4 * FRAMES,)
    np.testing.assert_array_equal(batch["T_c_o"][7], items[7]["T_c_o"])
    assert batch["object_id"] == [it["object_id"] for it in items]
    group = batch["sessions"]
    assert group["session_id"] == ds.session_ids  # once per session, not per frame
    assert [group["session_id"][i] for i in batch["session_index"]] == [
        it["session_id"] for it in items]
    n = [OBJECT_VERTICES[s.split("-")[1]] for s in group["session_id"]]
    assert group["object_vertices"].shape == (4, max(n), 3)
    assert group["contact"].shape == (4, max(n)) and group["contact"].dtype == np.float32
    np.testing.assert_array_equal(group["object_vertices_count"], n)
    np.testing.assert_array_equal(group["contact_count"], n)
    for s, sid in enumerate(group["session_id"]):
        arrays = ds.session_arrays(sid)
        assert group["mesh_id"][s] == arrays["mesh_id"]
        for k in SESSION_ARRAYS:
            count = group[f"{k}_count"][s]
            np.testing.assert_array_equal(group[k][s, :count], arrays[k])
            assert not group[k][s, count:].any()  # zero padding
        v, f = ds.mesh(arrays["mesh_id"])
        np.testing.assert_array_equal(v, arrays["object_vertices"])
    assert _writable(batch)
    # validity columns with nulls stay lists; bools without nulls are stacked
    assert isinstance(batch["object_reason"], list)
    with pytest.raises(ValueError, match="items of one dataset only"):
        gc.collate_fn([items[0], gc.GraspDataset(mixed, unit="sessions")[0]])


def test_torch_dataloader_with_workers(mixed):
    torch = pytest.importorskip(
        "torch", reason="torch is not installed (an optional extra: pip install torch, CPU "
        "wheel); collate_fn itself is tested without it")
    from torch.utils.data import DataLoader, default_convert

    ds = gc.GraspDataset(mixed.layout.root, valid_only=False)
    loader = DataLoader(ds, batch_size=64, num_workers=2, collate_fn=gc.collate_fn)
    batches = [default_convert(b) for b in loader]
    assert [len(b["session_index"]) for b in batches] == [64, len(ds) - 64]
    first = batches[0]
    assert isinstance(first["T_c_o"], torch.Tensor) and first["T_c_o"].shape == (64, 4, 4)
    assert first["sessions"]["object_vertices"].shape[-1] == 3
    assert len(first["sessions"]["session_id"]) == len(set(first["session_id"]))
    np.testing.assert_array_equal(first["T_c_o"][5].numpy(), ds[5]["T_c_o"])


def test_distorted_images_come_in_the_ideal_pinhole_image_of_K(synth_root, tmp_path):
    from graspcap.catalog.session_view import SessionSource
    from graspcap.tasks.core.camera import Camera

    sid = sorted(p.name for p in synth_root.iterdir() if (p / "session.json").is_file())[0]
    m = _manifest(synth_root, sid)
    m["color_camera"]["dist"] = [-0.12, 0.03, 0.0, 0.0, 0.0]
    root = tmp_path / sid
    frame = 10
    for kind in ("color", "depth"):  # only the files this test reads
        rel = m["grasp"][kind].format(index=frame)
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes((synth_root / sid / rel).read_bytes())
    (root / "session.json").write_text(json.dumps(m))
    source = SessionSource.find(sid, "b1", root, 1)
    color_file, depth_file = source.image_filenames(frame)
    raw_rgb = cv2.imread(str(color_file))[..., ::-1]
    raw_depth = cv2.imread(str(depth_file), cv2.IMREAD_UNCHANGED)
    camera = Camera(np.array(m["color_camera"]["K"]), np.array(m["color_camera"]["dist"]),
                    640, 480)
    color, depth = source.color(frame), source.depth(frame)
    assert color.shape == raw_rgb.shape and not np.array_equal(color, raw_rgb)
    np.testing.assert_array_equal(color, camera.undistort_image(np.ascontiguousarray(raw_rgb),
                                                                nearest=False))
    np.testing.assert_array_equal(depth, camera.undistort_image(raw_depth).astype(np.float32)
                                  * np.float32(m["depth_scale_m"]))
    np.testing.assert_array_equal(source.dist, m["color_camera"]["dist"])
    with pytest.raises(IndexError, match=f"session '{sid}': frame 40 outside the video's 0..39"):
        source.image_filenames(40)


def test_moved_session_folders_are_found_under_session_root(warm, synth_root, tmp_path):
    catalog, _ = warm
    moved = tmp_path / "moved"
    for folder in synth_root.iterdir():
        if (folder / "session.json").is_file():  # the manifest is all "paths" reads
            (moved / folder.name).mkdir(parents=True)
            (moved / folder.name / "session.json").write_bytes(
                (folder / "session.json").read_bytes())
    ds = gc.GraspDataset(catalog, images="paths", session_root=moved)
    item = ds[len(ds) - 1]
    sid, frame = item["session_id"], int(item["frame"])
    m = _manifest(synth_root, sid)
    assert item["color_path"] == str(moved / sid / m["grasp"]["color"].format(index=frame))
    view = gc.open(catalog).session(sid, session_root=moved)
    assert view.image_filenames(frame)[1] == moved / sid / m["grasp"]["depth"].format(index=frame)
    assert ds.session(sid).image_filenames(frame) == view.image_filenames(frame)
    with pytest.raises(gc.CatalogError, match=f"{tmp_path / 'empty' / sid / 'session.json'} is "
                       "missing; .* pass session_root="):
        gc.GraspDataset(catalog, images="paths",
                        session_root=tmp_path / "empty").session(sid).image_filenames(frame)
