"""Catalog formats: the golden catalogs of formats 1 to 6 fail to open naming `migrate`, and
migrate (old rows read the newer columns as null, format 6's reasons say "not recorded before
format 6", new commits fill them, format 7's `sessions.hand_shape` reads null on the old rows;
array groups get their format-5 manifests)."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from deltalake import DeltaTable

import graspcap.catalog as gc
from graspcap.catalog.delta import create_tables
from graspcap.catalog.layout import CatalogLayout, write_format_file
from graspcap.catalog.migrate import add_missing_columns, mark_not_recorded, migrate_catalog
from graspcap.schemas.tables import (
    CATALOG_FORMAT_VERSION,
    DELTA_TABLE_PROPERTIES,
    NOT_RECORDED,
    SESSIONS_SCHEMA,
    TABLE_SCHEMAS,
)
from tests.catalog_factory import make_build
from tests.conftest import REPO
from tests.golden.make_golden import (
    COLUMNS_ADDED,
    GOLDEN_FORMATS,
    SESSION,
    added_after,
    archive,
    build,
    expected,
    unpack,
    write_golden,
)

ARCHIVE = archive(1)


REASONS = ("camera_reason", "hand_reason", "object_reason")
"""Format 6's reason columns: the migration sets them on the rows before it."""


def _migrated(col: str, fmt: int) -> list:
    """The golden's two frames' ``col`` (a format-6 column) after the migration: flags null,
    reasons "not recorded before format 6", the camera's only where camera_solved is not True
    (the golden's is [True, False] from format 4 on); a format-6 golden keeps its own."""
    if fmt >= 6:
        return list(build().frames[col])
    if col not in REASONS:
        return [None, None]
    if col == "camera_reason" and fmt >= 4:
        return [None, NOT_RECORDED]
    return [NOT_RECORDED] * 2


def _properties(root) -> dict[str, dict[str, str]]:
    return {p.name: DeltaTable(str(p)).metadata().configuration
            for p in sorted((root / "tables").iterdir())}  # a golden lacks newer tables


def _listing(root) -> list:
    return sorted((str(p.relative_to(root)), p.stat().st_size) for p in root.rglob("*")
                  if p.is_file() and p.name != ".lock")


def _check_golden_content(cat: gc.Catalog, version) -> None:
    e = expected()
    values, observed = cat.contactmap(SESSION, version)
    np.testing.assert_array_equal(values, e["contact"])
    np.testing.assert_array_equal(observed, e["observed"])
    verts, faces = cat.object_mesh("cube", version)
    np.testing.assert_array_equal(verts, e["vertices"])
    np.testing.assert_array_equal(faces, e["faces"])
    row = cat.table("sessions", version).to_pylist()[0]
    np.testing.assert_array_equal(np.reshape(row["T_w_p"], (4, 4)), e["T"])
    np.testing.assert_array_equal(np.reshape(row["joints_w"], (21, 3)), e["joints"])
    assert cat.table("frames", version)["frame"].to_pylist() == [3, 4]
    assert cat.table("builds", version)["build_id"].to_pylist() == ["golden-1"]


def test_current_format_tables_keep_their_delta_logs(tmp_path):
    gc.open(tmp_path / "cat", create=True)
    stamp = json.loads((tmp_path / "cat" / "catalog.json").read_text())
    assert stamp["format_version"] == CATALOG_FORMAT_VERSION == 7
    for name, config in _properties(tmp_path / "cat").items():
        assert config == DELTA_TABLE_PROPERTIES, name


def test_golden_v1_fails_naming_migrate_then_migrated_copy_reads(tmp_path):
    src = unpack(ARCHIVE, tmp_path / "v1")
    assert json.loads((src / "catalog.json").read_text())["format_version"] == 1
    assert all(c == {} for c in _properties(src).values())  # really the old table properties
    with pytest.raises(gc.CatalogFormatError,
                       match=r"format 1.*graspcap catalog migrate .*--out NEW"):
        gc.open(src)
    before = _listing(src)

    report = migrate_catalog(src, tmp_path / "v2")
    assert (report.from_format, report.to_format, report.new_version) == (1, 7, 2)
    assert _listing(src) == before  # source untouched (the copy is taken under its lock)
    with pytest.raises(gc.CatalogFormatError, match="migrate"):
        gc.open(src)

    cat = gc.open(tmp_path / "v2")
    assert cat.versions()["version"].to_pylist() == [1, 2]
    assert cat.versions()["format_version"].to_pylist() == [1, 7]
    assert cat.versions()["build_id"].to_pylist() == ["golden-1", "migrate-1-to-7"]
    assert cat.resolve("golden") == 1
    for version in ("golden", 2, None):
        _check_golden_content(cat, version)
    assert cat.diff(1, 2) == {"added": [], "removed": [], "changed": {}}
    assert all(c == DELTA_TABLE_PROPERTIES for c in _properties(tmp_path / "v2").values())

    # the next build commits on top, and its recovery step keeps the migrated properties
    assert cat.commit(make_build(["p05-mug-use-00"], seed=5, build_id="after")) == 3
    assert sorted(cat.table("sessions", 3)["session_id"].to_pylist()) == [
        SESSION, "p05-mug-use-00"]
    assert all(c == DELTA_TABLE_PROPERTIES for c in _properties(tmp_path / "v2").values())
    _check_golden_content(cat, 1)


def test_migrate_in_place_is_idempotent_and_refuses_what_it_cannot(tmp_path):
    src = unpack(ARCHIVE, tmp_path / "v1")
    assert migrate_catalog(src).new_version == 2
    again = migrate_catalog(src)
    assert (again.from_format, again.new_version) == (7, None)
    frames = DeltaTable(str(src / "tables" / "frames"))  # a rerun after a crash: no commit
    assert mark_not_recorded(frames) is False
    assert DeltaTable(str(src / "tables" / "frames")).version() == frames.version()
    _check_golden_content(gc.open(src), 2)
    with pytest.raises(gc.CatalogError, match="exists"):
        migrate_catalog(src, tmp_path / "v1")
    with pytest.raises(gc.CatalogFormatError, match="no migration leads from it"):
        migrate_catalog(REPO / "tests" / "golden" / "catalog_v0", tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_empty_format_1_catalog_migrates_to_an_empty_current_one(tmp_path):
    layout = CatalogLayout((tmp_path / "empty").resolve())
    layout.root.mkdir()
    create_tables(layout, properties=None)
    write_format_file(layout, 1)
    assert migrate_catalog(layout.root).new_version is None
    cat = gc.open(layout.root)
    assert cat.latest_version() is None
    assert all(c == DELTA_TABLE_PROPERTIES for c in _properties(layout.root).values())
    assert cat.commit(make_build(["p01-bowl-use-00"], seed=1)) == 1


def _delta_columns(root, name="sessions") -> list[str]:
    return [f.name for f in DeltaTable(str(root / "tables" / name)).schema().fields]


@pytest.mark.parametrize("fmt", GOLDEN_FORMATS)
def test_migrate_adds_the_newer_columns_and_old_versions_read_them_as_null(tmp_path, fmt):
    src = unpack(archive(fmt), tmp_path / f"v{fmt}")
    assert json.loads((src / "catalog.json").read_text())["format_version"] == fmt
    added = added_after(fmt)  # {table: columns the formats after fmt added}
    if fmt < 4:  # format 5 added no column
        assert "camera_solved" in added["frames"]
        assert {"qa_flags", "qa_notes"} <= set(added["sessions"])
    for name, cols in added.items():
        assert not set(cols) & set(_delta_columns(src, name)), name  # the golden lacks them
    for name, cols in COLUMNS_ADDED.get(fmt, {}).items():
        assert set(cols) <= set(_delta_columns(src, name)), name
    with pytest.raises(gc.CatalogFormatError, match=rf"format {fmt}.*graspcap catalog migrate"):
        gc.open(src)
    report = migrate_catalog(src)
    assert (report.from_format, report.to_format, report.new_version) == (fmt, 7, 2)
    upgraded = 3 if fmt < 5 else 0  # given their format-5 manifests
    assert (report.arrays_upgraded, report.damaged_arrays) == (upgraded, {})
    for name, cols in added.items():
        assert _delta_columns(src, name)[-len(cols):] == list(cols), name
    for name in TABLE_SCHEMAS:  # format 7's publications table is created
        assert sorted(_delta_columns(src, name)) == sorted(TABLE_SCHEMAS[name].names), name
    cat = gc.open(src)
    assert cat.states() == {1: "published", 2: "published"}  # versions before format 7
    assert cat.audit(1) is None and cat.audit(2) is None
    added = {n: c for n, c in added.items() if n in ("sessions", "frames")}  # per session
    assert cat.versions()["build_id"].to_pylist() == ["golden-1", f"migrate-{fmt}-to-7"]
    for version in (1, "golden", 2):  # pinned before, and made by, the migration
        for name, cols in added.items():
            old = cat.table(name, version)
            assert old.schema == TABLE_SCHEMAS[name]  # conformed on read (field docs included)
            for col in cols:
                if version == 2 and col in REASONS:  # the migration wrote them
                    assert old[col].to_pylist() == _migrated(col, fmt), col
                else:
                    assert old[col].null_count == old.num_rows > 0, (name, col)
        old = cat.table("sessions", version)
        assert old["session_id"].to_pylist() == [SESSION]
        assert old["qa_contact_coverage"].to_pylist() == [0.5]  # the old QA values stay
        if fmt >= 2:
            assert old["keypoint_backend"].to_pylist() == ["openpose_json"]
        if fmt >= 3:
            assert old["qa_window_outlier_share"].to_pylist() == [0.5]
    assert cat.diff(1, 2) == {"added": [], "removed": [], "changed": {}}

    # the next build validates against the migrated tables; its version mixes files written
    # before the migration (the golden rows) and after (the new rows), in either read order
    build = make_build(["p05-mug-use-00", "p06-bowl-use-00"], seed=5, build_id="after")
    assert cat.commit(build) == 3
    rows = {r["session_id"]: r for r in cat.table("sessions", 3).to_pylist()}
    for col in added.get("sessions", ()):
        assert rows[SESSION][col] is None, col
        for r in build.sessions:
            assert rows[r["session_id"]][col] == r[col] is not None, col
    # list<string> columns: the Delta table has them as arrays of strings, the rows as lists
    delta_types = {f.name: str(f.type) for f in DeltaTable(str(src / "tables" /
                                                               "sessions")).schema().fields}
    for col in ("qa_flags", "qa_notes"):
        assert "string" in delta_types[col] and "array" in delta_types[col].lower(), delta_types
        assert cat.table("sessions", 3).schema.field(col).type == pa.list_(pa.string())
    assert rows["p05-mug-use-00"]["qa_notes"] == [
        "estimate_adjustment: ambiguous (the pose nearest stage 1 kept)"]
    assert rows["p06-bowl-use-00"]["qa_notes"] == [] == rows["p06-bowl-use-00"]["qa_flags"]
    frames = cat.table("frames", 3).sort_by([("session_id", "ascending"), ("frame", "ascending")])
    golden = frames.filter(pc.equal(frames["session_id"], SESSION))
    new = frames.filter(pc.not_equal(frames["session_id"], SESSION))
    assert golden["camera_solved"].to_pylist() == ([None, None] if fmt < 4 else [True, False])
    want = np.asarray(build.frames["camera_solved"])  # sessions sorted, as the build's
    assert new["camera_solved"].to_pylist() == want.tolist()
    assert want.any() and not want.all()  # both True and False written
    for col in COLUMNS_ADDED[6]["frames"]:
        assert golden[col].to_pylist() == _migrated(col, fmt), col
        assert new[col].to_pylist() == list(build.frames[col]), col
    assert {True, False, None} == set(new["object_supported"].to_pylist())
    for name, cols in added.items():
        files = cat.files(name, 3)
        assert len(files) == 2, name
        for order in (files, files[::-1]):
            some = gc.Catalog(cat.layout)
            some._files[(name, 3)] = order  # the read must not depend on the file order
            got = some.table(name, 3, columns=["session_id", *cols])
            old = got.filter(pc.equal(got["session_id"], SESSION))
            assert old.num_rows > 0, name
            for c in cols:
                want_old = _migrated(c, fmt) if c in REASONS else [None] * old.num_rows
                assert old[c].to_pylist() == want_old, (name, c, order)
    assert cat.table("frames", 1)["camera_solved"].to_pylist() == (
        [None, None] if fmt < 4 else [True, False])
    _check_golden_content(cat, 1)


@pytest.mark.parametrize("fmt", GOLDEN_FORMATS)
def test_golden_script_still_writes_that_formats_columns(tmp_path, fmt):
    golden = unpack(archive(fmt), tmp_path / "golden")
    write_golden(tmp_path / "fresh", fmt)
    tables = sorted(p.name for p in (golden / "tables").iterdir())
    assert sorted(p.name for p in (tmp_path / "fresh" / "tables").iterdir()) == tables
    for name in tables:
        assert _delta_columns(tmp_path / "fresh", name) == _delta_columns(golden, name), name
    assert _properties(tmp_path / "fresh") == _properties(golden)
    for name, cols in added_after(fmt).items():
        assert set(cols) <= set(TABLE_SCHEMAS[name].names), name  # the swap was undone


def test_only_nullable_columns_can_be_added_to_existing_rows(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(make_build(["p01-bowl-use-00"], seed=1))
    dt = DeltaTable(str(tmp_path / "cat" / "tables" / "sessions"))
    assert add_missing_columns(dt, SESSIONS_SCHEMA) == []
    strict = SESSIONS_SCHEMA.append(pa.field("must_have", pa.string(), nullable=False))
    with pytest.raises(gc.CatalogFormatError, match="must_have"):
        add_missing_columns(dt, strict)
    assert "must_have" not in _delta_columns(tmp_path / "cat")
