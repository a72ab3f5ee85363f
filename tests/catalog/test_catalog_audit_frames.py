"""The audit reads ``frames`` in proportion to what changed (``audit.frames_facts``): the same
verdicts and measurements as reading every row's key, on clean and on broken versions."""

from __future__ import annotations

import dataclasses

import numpy as np
import pyarrow as pa
import pytest
from deltalake import DeltaTable, write_deltalake

import graspcap.catalog as gc
from graspcap.catalog.audit import AuditGates, audit_version
from graspcap.catalog.delta import delta_version, table_versions_of
from graspcap.catalog.validate import to_table
from tests.catalog_factory import frame_rows, make_build

IDS = [f"p0{i}-{o}-use-00" for i, o in enumerate(["mug", "drill", "bowl", "mug", "drill"], 1)]
STRICT = AuditGates(tolerated_sessions=0)


def _pins(cat, version):
    return table_versions_of(next(r for r in cat.versions().to_pylist()
                                  if r["version"] == version))


def _frames(session_id: str, seed: int, count: int = 3) -> pa.Table:
    """``count`` frames rows as a commit writes them (frames 5, 6, ...)."""
    return to_table("frames", frame_rows(session_id, np.random.default_rng(seed), count))


def _same(cat, removed=()):
    """The newest Delta versions audited against published version 1 both ways: equal."""
    pins = {n: delta_version(cat.layout, n) for n in ("sessions", "frames", "builds")}
    both = [audit_version(cat.layout, pins, (1, _pins(cat, 1)), STRICT, removed,
                          incremental=inc) for inc in (True, False)]
    fast, full = both
    assert fast.measured.pop("frames_read")["how"] == "incremental"
    assert full.measured.pop("frames_read")["how"] == "full"
    assert fast == full
    return fast


@pytest.fixture
def cat(tmp_path):
    """Version 1: five sessions, audited and published; version 2: one session rewritten."""
    cat = gc.open(tmp_path / "cat", create=True)
    assert cat.commit(make_build(IDS, seed=1, build_id="b1"), STRICT) == 1
    assert cat.commit(make_build(IDS[:1], seed=2, build_id="b2"), STRICT) == 2
    return cat


def test_a_clean_version_reads_the_changed_files_only(cat):
    audit = cat.audit(2)
    # the rewritten session's file (it held all five: one commit) is read; nothing is kept
    assert audit["passed"] and audit["measured"]["frames_read"] == {
        "how": "incremental", "keys": 15, "session_ids": 0}
    assert audit["measured"]["frames"] == audit["measured"]["published_frames"] == 15
    assert _same(cat).passed
    first = cat.audit(1)  # no published version to compare with: every key read
    assert first["measured"]["frames_read"] == {"how": "full", "keys": 15, "session_ids": 0}
    assert first["measured"]["duplicate_frame_keys"] == 0


def test_duplicate_keys_orphans_and_empty_sessions_are_found_as_by_a_full_read(cat):
    frames = str(cat.layout.table("frames"))
    # a broken writer appends a session's rows again (its old rows are in kept files)
    write_deltalake(frames, _frames(IDS[2], 7), mode="append")
    dup = _same(cat)
    assert dup.reasons == ["rows: 3 (session_id, frame) key(s) appear more than once in frames"]
    # rows of a session the sessions table lacks, and an ok session's rows deleted
    write_deltalake(frames, _frames("p09-bowl-use-00", 8), mode="append")
    DeltaTable(frames).delete(f"session_id = '{IDS[4]}'")
    broken = _same(cat)
    assert broken.measured["sessions_without_frames"] == [IDS[4]]
    assert any("not in sessions: p09-bowl-use-00" in r for r in broken.reasons)
    assert broken.measured["frames"] == 15 - 3 + 3 + 3  # from the Delta log's counts


def test_removed_sessions_and_unaudited_versions(cat, tmp_path):
    assert cat.remove([IDS[3]], "withdrawn") == 3
    pins = _pins(cat, 3)
    for removed in ((), (IDS[3],)):
        fast, full = (audit_version(cat.layout, pins, (1, _pins(cat, 1)), STRICT, removed,
                                    incremental=inc) for inc in (True, False))
        assert fast.measured.pop("frames_read")["how"] == "incremental"
        full.measured.pop("frames_read")
        assert fast == full
    assert fast.passed and fast.measured["published_frames"] == 12
    # a published version committed without an audit: nothing is known of its keys
    other = gc.open(tmp_path / "other", create=True)
    other.commit(make_build(IDS, seed=1, build_id="b1"))
    other.commit(make_build(IDS[:1], seed=3, build_id="b2"), STRICT)
    assert other.audit(2)["measured"]["frames_read"]["how"] == "full"
    assert other.audit(2)["passed"]


def test_a_rewritten_session_with_new_frames(cat):
    build = make_build(IDS[1:2], seed=5, build_id="b3", frames=6)
    assert cat.commit(dataclasses.replace(build), STRICT) == 3
    assert cat.audit(3)["measured"]["frames"] == 18 and cat.audit(3)["passed"]
