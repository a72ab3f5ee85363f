"""The versioned catalog: time travel, crash safety, concurrent writers, format, schema, vacuum."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pyarrow as pa
import pytest
from deltalake import DeltaTable

import graspcap.catalog as gc
from graspcap.catalog.commit import PAUSE_ENV, PAUSE_SIGNAL_ENV, writer_lock
from graspcap.catalog.validate import to_table
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION
from tests.catalog_factory import make_build
from tests.conftest import REPO
from tests.golden.make_golden import build as golden_build
from tests.golden.make_golden import expected as golden_expected

GOLDEN = REPO / "tests" / "golden"
IDS_1 = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-handoff-00"]
IDS_2 = ["p01-mug-use-00", "p04-mug-use-00"]  # one rewritten, one new
IDS_3 = ["p02-drill-use-00"]  # rewritten, and p03 removed


def _builds():
    return [make_build(IDS_1, seed=1, build_id="b1", failed=("p03-bowl-handoff-00",)),
            make_build(IDS_2, seed=2, build_id="b2"),
            make_build(IDS_3, seed=3, build_id="b3", remove=("p03-bowl-handoff-00",))]


def _expected_state(builds, upto):
    """{session_id: (session row dict, frames table, SessionArrays)} after builds[:upto]."""
    state = {}
    for b in builds[:upto]:
        for sid in b.remove:
            state.pop(sid, None)
        frames = to_table("frames", b.frames)
        for row in b.sessions:
            sel = frames.filter(pa.compute.equal(frames["session_id"], row["session_id"]))
            state[row["session_id"]] = (row, sel, b.session_arrays.get(row["session_id"]))
    return state


@pytest.fixture(scope="module")
def three_versions(tmp_path_factory):
    root = tmp_path_factory.mktemp("cat3")
    cat = gc.open(root, create=True)
    builds = _builds()
    assert [cat.commit(b) for b in builds] == [1, 2, 3]
    return cat, builds


def _snapshot(cat, version):
    return {name: cat.table(name, version) for name in ("sessions", "frames", "builds")}


def test_time_travel_reads_every_version_as_written(three_versions):
    cat, builds = three_versions
    assert cat.latest_version() == 3
    assert cat.versions()["build_id"].to_pylist() == ["b1", "b2", "b3"]
    for v in (1, 2, 3):
        state = _expected_state(builds, v)
        sessions = cat.table("sessions", v)
        assert sorted(sessions["session_id"].to_pylist()) == sorted(state)
        frames = cat.table("frames", v)
        assert frames.num_rows == sum(s[1].num_rows for s in state.values())
        for row in sessions.to_pylist():
            written, w_frames, arrays = state[row["session_id"]]
            assert row["status"] == written["status"] and row["build_id"] == written["build_id"]
            if written["status"] == "failed":
                assert row["T_adj"] is None and row["contact_digest"] is None
                continue
            np.testing.assert_array_equal(np.reshape(row["T_adj"], (4, 4)), written["T_adj"])
            np.testing.assert_array_equal(np.reshape(row["joints_w"], (21, 3)),
                                          written["joints_w"])
            got = frames.filter(pa.compute.equal(frames["session_id"], row["session_id"]))
            assert got.sort_by("frame").equals(w_frames.sort_by("frame"))
            values, observed = cat.contactmap(row["session_id"], v)
            assert values.dtype == np.float32 and observed.dtype == bool
            np.testing.assert_array_equal(values, arrays.contact)
            np.testing.assert_array_equal(observed, arrays.observed)
            verts, faces = cat.hand_mesh(row["session_id"], v)
            np.testing.assert_array_equal(verts, arrays.hand_vertices)
            np.testing.assert_array_equal(faces, arrays.hand_faces)
            np.testing.assert_array_equal(cat.hand_joints(row["session_id"], v), arrays.joints)
        assert cat.table("builds", v).num_rows == v
    obj = builds[0].object_meshes["drill"]
    verts, faces = cat.object_mesh("drill", 1)
    np.testing.assert_array_equal(verts, obj.vertices)
    np.testing.assert_array_equal(faces, obj.faces)


def test_tags_resolve_and_move(three_versions):
    cat, _ = three_versions
    cat.tag(1, "first")
    cat.tag(2, "paper")
    assert cat.table("sessions", "first").equals(cat.table("sessions", 1))
    with pytest.raises(gc.CatalogError, match="already points at version 2"):
        cat.tag(3, "paper")  # a tag moves only when asked to
    assert cat.resolve("paper") == 2
    assert cat.tag(3, "paper", force=True) is True
    assert cat.resolve("paper") == 3
    assert cat.versions()["tags"].to_pylist() == [["first"], [], ["paper"]]
    with pytest.raises(gc.VersionNotFound, match="no tag 'nope'"):
        cat.table("sessions", "nope")
    with pytest.raises(gc.VersionNotFound, match="no version 9"):
        cat.table("sessions", 9)


def test_builds_row_records_lineage(three_versions):
    cat, _ = three_versions
    rows = cat.table("builds", 3).sort_by("catalog_version").to_pylist()
    assert rows[0]["sessions_added"] == sorted(IDS_1)
    assert rows[0]["sessions_failed"][0]["session_id"] == "p03-bowl-handoff-00"
    assert rows[1]["sessions_added"] == ["p04-mug-use-00"]
    assert rows[1]["sessions_changed"] == ["p01-mug-use-00"]
    assert rows[2]["sessions_removed"] == ["p03-bowl-handoff-00"]


def test_diff_reports_added_removed_changed_columns(three_versions):
    cat, _ = three_versions
    d = cat.diff(1, 2)
    assert d["added"] == ["p04-mug-use-00"] and d["removed"] == []
    assert list(d["changed"]) == ["p01-mug-use-00"]
    assert {"T_adj", "contact_digest", "build_id"} <= set(d["changed"]["p01-mug-use-00"])
    assert {"session_id", "object_id", "code_version"}.isdisjoint(d["changed"]["p01-mug-use-00"])
    d = cat.diff(2, 3)
    assert d["removed"] == ["p03-bowl-handoff-00"] and d["added"] == []
    assert list(d["changed"]) == ["p02-drill-use-00"]
    assert cat.diff(3, 3) == {"added": [], "removed": [], "changed": {}}


_CHILD = textwrap.dedent("""
    import sys
    import graspcap.catalog as gc
    from tests.catalog_factory import make_build
    cat = gc.open(sys.argv[1], lock_timeout_s=float(sys.argv[3]))
    v = cat.commit(make_build(sys.argv[2].split(","), seed=int(sys.argv[4]), build_id=sys.argv[5]))
    print(v)
""")


def _spawn(root, ids, seed, build_id, env=None, timeout_s=60.0):
    return subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(root), ",".join(ids), str(timeout_s), str(seed),
         build_id], cwd=REPO, env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})},
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("point", ["after_arrays", "after_sessions", "after_frames",
                                   "after_builds"])
def test_killed_writer_leaves_previous_version_and_next_commit_recovers(tmp_path, point):
    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    builds = _builds()
    cat.commit(builds[0])
    before = _snapshot(cat, 1)
    pins = {n: DeltaTable(str(root / "tables" / n)).version() for n in before}
    signal_file = tmp_path / "paused"
    child = _spawn(root, IDS_2, 2, "b2", {PAUSE_ENV: point, PAUSE_SIGNAL_ENV: str(signal_file)})
    deadline = time.monotonic() + 60
    while not signal_file.exists():
        assert child.poll() is None, child.communicate()[1]
        assert time.monotonic() < deadline, "child never reached the pause point"
        time.sleep(0.05)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    assert child.returncode == -signal.SIGKILL
    ahead = {n: DeltaTable(str(root / "tables" / n)).version() - pins[n] for n in pins}
    n_ahead = ["after_arrays", "after_sessions", "after_frames", "after_builds"].index(point)
    assert sum(ahead.values()) == n_ahead  # the orphaned table commits exist ...

    fresh = gc.open(root)  # ... and no reader sees them
    assert fresh.latest_version() == 1
    for name, table in _snapshot(fresh, 1).items():
        assert table.equals(before[name]), name
    values, _ = fresh.contactmap("p01-mug-use-00", 1)
    np.testing.assert_array_equal(values, builds[0].session_arrays["p01-mug-use-00"].contact)

    assert fresh.commit(builds[1]) == 2  # the next writer rolls them back, then commits
    state = _expected_state(builds, 2)
    assert sorted(fresh.table("sessions", 2)["session_id"].to_pylist()) == sorted(state)
    assert fresh.table("frames", 2).num_rows == sum(s[1].num_rows for s in state.values())
    assert fresh.table("builds", 2)["build_id"].to_pylist().count("b2") == 1
    for name, table in _snapshot(fresh, 1).items():
        assert table.equals(before[name]), name


def test_two_writers_at_once_commit_serially(tmp_path):
    root = tmp_path / "cat"
    gc.open(root, create=True)
    a = _spawn(root, ["p01-mug-use-00", "p02-mug-use-00"], 11, "wa")
    b = _spawn(root, ["p03-drill-use-00", "p01-mug-use-00"], 12, "wb")
    outs = [p.communicate(timeout=120) for p in (a, b)]
    assert [p.returncode for p in (a, b)] == [0, 0], [o[1][-2000:] for o in outs]
    assert sorted(int(o[0]) for o in outs) == [1, 2]
    cat = gc.open(root)
    versions = cat.versions().to_pylist()
    assert [r["version"] for r in versions] == [1, 2]
    last = versions[-1]["build_id"]
    sessions = cat.table("sessions", 2)
    assert sorted(sessions["session_id"].to_pylist()) == [
        "p01-mug-use-00", "p02-mug-use-00", "p03-drill-use-00"]
    p01 = sessions.filter(pa.compute.equal(sessions["session_id"], "p01-mug-use-00"))
    assert p01["build_id"][0].as_py() == last  # the later commit wins the shared session
    assert cat.table("frames", 2).num_rows == 9
    assert sorted(cat.table("builds", 2)["build_id"].to_pylist()) == ["wa", "wb"]


def test_second_writer_times_out_with_a_clear_message(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True, lock_timeout_s=0.3)
    with writer_lock(cat.layout, 1.0):
        with pytest.raises(gc.CatalogLockTimeout, match=r"another writer \(pid \d+"):
            cat.commit(make_build(IDS_2, seed=0))
    assert cat.latest_version() is None
    assert cat.commit(make_build(IDS_2, seed=0)) == 1


def test_unmigratable_older_format_names_the_rebuild(tmp_path):
    with pytest.raises(gc.CatalogFormatError, match=r"format 0.*no graspcap.*graspcap build"):
        gc.open(GOLDEN / "catalog_v0")
    with pytest.raises(gc.CatalogFormatError, match="not a graspcap catalog"):
        gc.open(tmp_path / "nothing")


def test_newer_format_says_upgrade_and_golden_build_reads_back(tmp_path):
    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    cat.commit(golden_build())
    e = golden_expected()
    values, observed = cat.contactmap("p01-cube-use-00")
    np.testing.assert_array_equal(values, e["contact"])
    np.testing.assert_array_equal(observed, e["observed"])
    row = cat.table("sessions").to_pylist()[0]
    np.testing.assert_array_equal(np.reshape(row["T_w_p"], (4, 4)), e["T"])
    stamp = json.loads((root / "catalog.json").read_text())
    assert stamp["format_version"] == CATALOG_FORMAT_VERSION
    stamp["format_version"] = CATALOG_FORMAT_VERSION + 1
    (root / "catalog.json").write_text(json.dumps(stamp))
    with pytest.raises(gc.CatalogFormatError,
                       match=rf"format {CATALOG_FORMAT_VERSION + 1}.*upgrade graspcap"):
        gc.open(root)


def test_vacuum_keeps_what_kept_versions_need(tmp_path):
    root = tmp_path / "cat"
    cat = src = gc.open(root, create=True)
    builds = _builds()
    for b in builds:
        cat.commit(b)
    before = {v: _snapshot(cat, v) for v in (2, 3)}
    groups_before = set((root / "arrays").glob("??/*.zarr"))
    v1_only = src.table("sessions", 1).filter(
        pa.compute.equal(src.table("sessions", 1)["session_id"], "p01-mug-use-00"))
    v1_digest = v1_only["contact_digest"][0].as_py()
    report = cat.vacuum(keep=2)
    assert report.kept_versions == [2, 3] and report.dropped_versions == [1]
    assert report.removed_files > 0 and report.removed_arrays > 0 and report.freed_bytes > 0
    assert not (root / "arrays" / v1_digest[:2] / f"{v1_digest}.zarr").exists()
    assert len(set((root / "arrays").glob("??/*.zarr"))) == len(groups_before) - \
        report.removed_arrays
    fresh = gc.open(root)
    for v in (2, 3):
        for name, table in _snapshot(fresh, v).items():
            assert table.equals(before[v][name]), (v, name)
        for sid in fresh.table("sessions", v)["session_id"].to_pylist():
            if sid in builds[0].session_arrays or v > 1:
                state = _expected_state(builds, v)[sid]
                if state[2] is not None:
                    np.testing.assert_array_equal(fresh.contactmap(sid, v)[0], state[2].contact)
    with pytest.raises(gc.CatalogError, match="vacuum"):
        fresh.table("sessions", 1)
    assert fresh.commit(make_build(["p09-bowl-use-00"], seed=9, build_id="b4")) == 4
    fresh.tag(2, "paper")  # a tag keeps its version
    report = fresh.vacuum(keep=1)
    assert report.kept_versions == [2, 4]
    assert fresh.table("frames", "paper").equals(before[2]["frames"])


CONTRACT = {
    "sessions": {
        **dict.fromkeys(["session_id", "participant", "object_id", "intent", "hand", "status",
                         "error", "input_digest", "code_version", "build_id"], pa.string()),
        "steady_from": pa.int64(),
        "keypoint_backend": pa.string(), "keypoint_frames_detected": pa.int32(),
        **dict.fromkeys(["T_w_o_stage1", "T_adj", "T_w_p", "T_turntable_o_scan"],
                        pa.list_(pa.float64(), 16)),
        "hand_scale": pa.float64(), "joint_angles_rad": pa.list_(pa.float64(), 20),
        "joints_w": pa.list_(pa.float64(), 63), "joints_fit_w": pa.list_(pa.float64(), 63),
        **dict.fromkeys(["qa_reproj_rmse_px", "qa_inlier_ratio", "qa_crosscheck_mm",
                         "qa_registration_rmse_mm", "qa_fit_residual_mm",
                         "qa_penetration_max_mm", "qa_penetration_mean_mm",
                         "qa_contact_agreement", "qa_contact_coverage",
                         "qa_window_outlier_share", "qa_crosscheck_camera_deg",
                         "qa_rgbd_discrepancy_mm", "qa_fit_contact_agreement"], pa.float64()),
        **dict.fromkeys(["qa_flags", "qa_notes"], pa.list_(pa.string())),
    },
    "frames": {
        "session_id": pa.string(), "frame": pa.int64(),
        **dict.fromkeys(["T_w_c", "T_c_o", "T_c_p"], pa.list_(pa.float64(), 16)),
        "camera_solved": pa.bool_(),
        "joints_2d_px": pa.list_(pa.float64(), 42), "keypoint_conf": pa.list_(pa.float64(), 21),
        "joints_c": pa.list_(pa.float64(), 63), "reproj_err_px": pa.list_(pa.float64(), 21),
    },
}


def test_contract_columns_have_the_documented_types(three_versions):
    cat, _ = three_versions
    for name, columns in CONTRACT.items():
        schema = cat.table(name, 1).schema
        for col, type_ in columns.items():
            assert schema.field(col).type == type_, (name, col)
    units = cat.table("sessions", 1).schema.field("qa_crosscheck_mm").metadata
    assert units[b"unit"] == b"mm"
    sessions = cat.table("sessions", 1)
    for col in ("keypoint_backend", "keypoint_frames_detected"):  # null on the failed row
        assert sessions.schema.field(col).nullable and b"doc" in sessions.schema.field(
            col).metadata
        by_status = dict(zip(sessions["status"].to_pylist(), sessions[col].to_pylist(),
                             strict=True))
        assert by_status["failed"] is None and by_status["ok"] is not None, col
    assert set(sessions["keypoint_backend"].drop_null().to_pylist()) == {"openpose_json"}
    # QA's reasons and notes: lists of strings (null on the failed row), pandas reads lists
    df = sessions.to_pandas()
    assert df.qa_flags.dtype == object and df.qa_notes.dtype == object
    mugs = 0
    for sid, status, flags, notes in zip(df.session_id, df.status, df.qa_flags, df.qa_notes,
                                         strict=True):
        if status == "failed":
            assert flags is None and notes is None, sid
            continue
        assert list(flags) == [], sid
        want = ["estimate_adjustment: ambiguous (the pose nearest stage 1 kept)"] * (
            "-mug-" in sid)
        assert list(notes) == want, sid
        mugs += "-mug-" in sid
    assert mugs and (df.status == "failed").any()


@pytest.mark.parametrize("mutate, column, message", [
    (lambda r: r.pop("T_adj"), "T_adj", "missing here"),
    (lambda r: r.update(extra_col=1.0), "extra_col", "unexpected"),
    (lambda r: r.update(T_adj=np.eye(3)), "T_adj", "expected 16 values"),
    (lambda r: r.update(steady_from="soon"), "steady_from", "is not int64"),
    (lambda r: r.update(status="great"), "status", "not one of"),
    (lambda r: r.update(status="failed"), "error", "needs an error"),
    (lambda r: r.update(error="oops"), "error", "null unless"),
    (lambda r: r.update(joints_w=None), "joints_w", "did not fail"),
])
def test_bad_session_batch_names_table_column_session(mutate, column, message):
    build = make_build(IDS_2, seed=5)
    for row in build.sessions:
        row.update(contact_digest="c", hand_mesh_digest="h", object_mesh_digest="o")
    mutate(build.sessions[1])
    with pytest.raises(gc.CatalogSchemaError, match=message) as info:
        to_table("sessions", build.sessions)
    text = str(info.value)
    assert "'sessions'" in text and f"'{column}'" in text and "p04-mug-use-00" in text


def test_wrong_arrow_type_and_bad_arrays_are_rejected(tmp_path):
    build = make_build(IDS_2, seed=5)
    frames = to_table("frames", build.frames)
    bad = frames.set_column(frames.schema.get_field_index("T_c_o"), "T_c_o",
                            frames["T_c_o"].cast(pa.list_(pa.float64())))
    with pytest.raises(gc.CatalogSchemaError, match=r"'frames', column 'T_c_o', session "
                                                    r"'p01-mug-use-00'.*expected type"):
        to_table("frames", bad)
    arrays = build.session_arrays["p04-mug-use-00"]
    short = gc.SessionArrays(arrays.contact[:-1], arrays.observed, arrays.hand_vertices,
                             arrays.hand_faces, arrays.joints)
    build = gc.BuildCommit(build.build, build.sessions, build.frames,
                           {**build.session_arrays, "p04-mug-use-00": short},
                           build.object_meshes)
    cat = gc.open(tmp_path / "cat", create=True)
    with pytest.raises(gc.CatalogSchemaError, match="p04-mug-use-00"):
        cat.commit(build)
    assert cat.latest_version() is None
