"""GraspDataset over a catalog version, and the one-liners users read the tables with."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pyarrow.parquet as pq
import pytest
from deltalake import DeltaTable

import graspcap.catalog as gc
from tests.catalog_factory import OBJECT_VERTICES, make_build

IDS = ["p01-mug-use-00", "p01-drill-handoff-00", "p02-mug-handoff-00", "p02-bowl-use-00",
       "p03-drill-use-00", "p03-mug-use-00"]
FRAMES = 4


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    cat = gc.open(tmp_path_factory.mktemp("ds"), create=True)
    build = make_build(IDS, seed=7, frames=FRAMES, failed=("p03-mug-use-00",))
    cat.commit(build)
    return cat, build


def test_frames_items_join_frame_row_with_session_arrays(catalog):
    cat, build = catalog
    ds = gc.GraspDataset(cat, valid_only=False)
    assert len(ds) == 5 * FRAMES  # the failed session has no frames and is filtered out
    item = ds[FRAMES + 1]
    sid = item["session_id"]
    assert sid == ds.session_ids[1]
    n = OBJECT_VERTICES[item["object_id"]]
    shapes = {"T_c_o": (4, 4), "T_w_p": (4, 4), "joints_c": (21, 3), "joints_2d_px": (21, 2),
              "keypoint_conf": (21,), "reproj_err_px": (21,), "joint_angles_rad": (20,),
              "contact": (n,), "contact_observed": (n,), "object_vertices": (n, 3),
              "hand_vertices": (25, 3), "hand_joints_o": (21, 3)}
    assert {k: item[k].shape for k in shapes} == shapes
    assert item["contact"].dtype == np.float32 and item["contact_observed"].dtype == bool
    i = list(build.frames["session_id"]).index(sid) + 1  # frames of a session are contiguous
    np.testing.assert_array_equal(item["T_c_o"], build.frames["T_c_o"][i])
    assert item["frame"] == build.frames["frame"][i]
    np.testing.assert_array_equal(item["contact"], build.session_arrays[sid].contact)
    np.testing.assert_array_equal(item["object_vertices"],
                                  build.object_meshes[item["object_id"]].vertices)
    assert ds[-1]["session_id"] == ds.session_ids[-1]
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_filters_and_session_unit(catalog):
    cat, _ = catalog
    assert len(gc.GraspDataset(cat, unit="sessions")) == 5
    assert len(gc.GraspDataset(cat, unit="sessions", status=("ok", "failed"))) == 6
    mugs = gc.GraspDataset(cat, objects=["mug"], valid_only=False)
    assert {mugs[i]["object_id"] for i in range(len(mugs))} == {"mug"}
    assert len(mugs) == 2 * FRAMES
    handoff = gc.GraspDataset(cat, unit="sessions", intents=["handoff"], participants=["p02"])
    assert handoff.session_ids == ["p02-mug-handoff-00"]
    assert "frame" not in handoff[0] and handoff[0]["T_adj"].shape == (4, 4)


def test_frame_items_only_from_valid_frames_unless_asked(catalog):
    cat, build = catalog
    flags = ("hand_used", "camera_solved", "object_supported")
    cols = {c: list(build.frames[c]) for c in ("session_id", "frame", *flags)}
    rows = list(zip(*cols.values(), strict=True))
    valid = {(s, f) for s, f, *v in rows if False not in v}
    # the factory's pattern: per session frame 1 is denied (interpolated, unused hand, depth
    # disagreeing); frame 2's object the depth cannot judge (null) is kept
    assert len(valid) == 5 * (FRAMES - 1)
    assert any(v[2] is None for s, f, *v in rows if (s, f) in valid)

    ds = gc.GraspDataset(cat)  # valid_only=True by default
    got = [(ds[i]["session_id"], ds[i]["frame"]) for i in range(len(ds))]
    assert len(got) == len(valid) and set(got) == valid
    for i in range(len(ds)):  # every item's columns are its own frame's
        item = ds[i]
        assert item["hand_used"] is not False and item["object_supported"] is not False
        j = [(s, f) for s, f, *_ in rows].index((item["session_id"], item["frame"]))
        np.testing.assert_array_equal(item["T_c_o"], build.frames["T_c_o"][j])
        assert item["object_reason"] == build.frames["object_reason"][j]
    everything = gc.GraspDataset(cat, valid_only=False)
    assert len(everything) == 5 * FRAMES
    denied = [everything[i] for i in range(len(everything))
              if (everything[i]["session_id"], everything[i]["frame"]) not in valid]
    assert {d["frame"] for d in denied} == {build.frames["frame"][1]}
    assert {d["camera_reason"] for d in denied} == {
        "interpolated from its neighbours: 2 keypoints detected"}
    assert all(d["object_reason"].startswith("depth disagrees") for d in denied)
    rest, held = ds.split_by("participant", ["p02"])  # subsets keep the filter
    assert len(rest) + len(held) == len(ds)
    assert pickle.loads(pickle.dumps(ds)).valid_only is True
    assert len(gc.GraspDataset(cat, unit="sessions")) == 5  # sessions are not filtered


@pytest.mark.parametrize("key, holdout", [("participant", ["p02"]),
                                          ("object_id", ["drill", "bowl"])])
def test_splits_are_disjoint_and_complete(catalog, key, holdout):
    cat, _ = catalog
    ds = gc.GraspDataset(cat)
    rest, held = ds.split_by(key, holdout)
    held_values = {held[i][key] for i in range(len(held))}
    rest_values = {rest[i][key] for i in range(len(rest))}
    assert held_values == set(holdout) and not held_values & rest_values
    assert len(rest) + len(held) == len(ds)
    assert set(rest.session_ids).isdisjoint(held.session_ids)


def test_pickles_for_dataloader_workers(catalog):
    cat, _ = catalog
    ds = gc.GraspDataset(cat.layout.root)
    ds[0]  # loaded state must not travel
    clone = pickle.loads(pickle.dumps(ds))
    assert clone._state is None and len(clone) == len(ds)
    a, b = ds[3], clone[3]
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_one_liners_pandas_and_pyarrow(catalog):
    cat, _ = catalog
    df = cat.to_pandas("frames", 1)
    assert len(df) == 5 * FRAMES and np.asarray(df["T_c_o"].iloc[0]).shape == (16,)
    pins = cat.versions().to_pylist()[0]["table_versions"]
    files = DeltaTable(str(cat.layout.table("frames")),
                       version=json.loads(pins)["frames"]).file_uris()
    assert pq.read_table(files).num_rows == 5 * FRAMES


@pytest.mark.parametrize("module", ["duckdb", "polars"])
def test_duckdb_and_polars_read_the_parquet(catalog, module):
    pytest.importorskip(module, reason=f"{module} is not installed in this environment")
    cat, _ = catalog
    frames = cat.table("frames", 1)
    if module == "polars":
        import polars as pl
        assert pl.from_arrow(frames).height == 5 * FRAMES
    else:
        import duckdb
        assert duckdb.sql("select count(*) from frames").fetchall()[0][0] == 5 * FRAMES


def test_hand_shape_round_trips_and_rebuilds_the_hand(catalog):
    """``sessions.hand_shape`` (format 7, bone lengths in metres) reads back as written, in
    dataset items and the session view; the hand rebuilt from the row has those bones."""
    from graspcap.catalog.session_view import SessionView
    from graspcap.tasks.hand.model import SKELETON, HandModel, HandSide
    from graspcap.tasks.hand.shape import bone_scale_from_lengths

    cat, build = catalog
    sid = "p02-bowl-use-00"
    want = next(r["hand_shape"] for r in build.sessions if r["session_id"] == sid)
    assert cat.table("sessions").schema.field("hand_shape").metadata[b"unit"] == b"m"
    item = next(i for i in gc.GraspDataset(cat, unit="sessions") if i["session_id"] == sid)
    np.testing.assert_array_equal(item["hand_shape"], want)
    view = SessionView(cat, sid)
    np.testing.assert_array_equal(view.hand_shape, want)
    row = next(r for r in build.sessions if r["session_id"] == sid)
    T_w_p = np.asarray(row["T_w_p"]).reshape(4, 4)
    bone_scale = bone_scale_from_lengths(np.asarray(want), row["hand_scale"])
    model = HandModel(HandSide.RIGHT)
    kp = model.keypoints(row["joint_angles_rad"], T_w_p, row["hand_scale"], bone_scale)
    lengths = [np.linalg.norm(kp[k] - kp[p]) for p, k in SKELETON]
    np.testing.assert_allclose(lengths, want, rtol=1e-12)
    assert SessionView(cat, "p03-mug-use-00").hand_shape is None  # failed: no hand
