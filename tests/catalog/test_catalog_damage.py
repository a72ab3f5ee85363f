"""A catalog damaged on purpose loses nothing and never reads wrong: lost and garbage Delta
log entries, lost versions rows and their repair, two creators at once. Each case asserts what
readers see, what a writer says, and that no committed version changes (disk full, damaged
files, the command line and the work area: ``test_catalog_damage_files.py``).
"""

from __future__ import annotations

import json
import multiprocessing

import pytest
from deltalake import DeltaTable

import graspcap.catalog as gc
import graspcap.catalog.commit as commit_mod
from graspcap.catalog.errors import CatalogDamaged
from tests.catalog_factory import (
    DAMAGE_IDS,
    DATA_TABLES,
    assert_reads_back,
    commit_three,
    delta_logs,
    log_entry,
    make_build,
    snapshot,
)

# --- 1. recovery never discards what a reader could have seen ------------------------------

def test_lost_last_versions_entry_stops_writers_and_drops_nothing(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    snapshots = {v: snapshot(cat, v) for v in (1, 2, 3)}
    entry = log_entry(root, "versions", 3)
    saved = entry.read_bytes()
    entry.unlink()
    pins = delta_logs(root)

    fresh = gc.open(root)  # readers: version 3 is gone from the list, 1 and 2 read as written
    assert fresh.latest_version() == 2
    assert_reads_back(root, {v: snapshots[v] for v in (1, 2)})

    with pytest.raises(CatalogDamaged) as err:  # the record of version 3 says it was published
        fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert err.value.problems == [
        f"{root / 'published.json'}: version 3 was published, but the versions table ends at "
        "version 2 (its rows or log entries after that were lost)"]
    assert "`graspcap catalog repair --catalog CATALOG` puts their rows back" in str(err.value)
    assert delta_logs(root) == pins  # nothing rolled back, nothing written

    (root / "published.json").unlink()  # without the record: the versions row's own file
    with pytest.raises(CatalogDamaged) as err:
        fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    [problem] = err.value.problems
    assert problem.startswith(str(root / "tables" / "versions") + "/")
    assert problem.endswith(f".parquet: holds the versions row of version(s) [3], which no log "
                            f"entry lists (its log entry {entry} was lost, or a writer died "
                            "while appending it)")
    assert delta_logs(root) == pins

    entry.write_bytes(saved)  # repaired: version 3 is back and the next build is version 4
    assert gc.open(root).commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5")) == 4
    assert_reads_back(root, snapshots)


@pytest.mark.parametrize("damage", ["last entry lost", "middle entry lost", "entry garbled"])
def test_repair_puts_lost_versions_rows_back_from_their_files(tmp_path, damage):
    from graspcap.catalog.repair import main

    root = tmp_path / "cat"
    cat = commit_three(root)
    snapshots = {v: snapshot(cat, v) for v in (1, 2, 3)}
    n = 3 if damage == "last entry lost" else 2
    if damage == "entry garbled":
        log_entry(root, "versions", n).write_bytes(b"\xff\xfe")
    else:
        log_entry(root, "versions", n).unlink()
    with pytest.raises(CatalogDamaged):
        gc.open(root).commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))

    from graspcap.cli import main as graspcap_cli  # `graspcap catalog repair`, as a user types

    assert graspcap_cli(["catalog", "repair", "--catalog", str(root)]) == 0
    assert (root / "tables" / "versions" / "_delta_log" /
            f"{n:020d}.json.damaged").exists() == (damage == "entry garbled")
    fresh = gc.open(root)
    assert fresh.versions()["version"].to_pylist() == [1, 2, 3]
    assert fresh.problems() == []
    assert_reads_back(root, snapshots)
    assert fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5")) == 4
    assert_reads_back(root, snapshots)
    assert main([str(root)]) == 0  # nothing left to do


def test_repair_leaves_out_a_row_whose_tables_do_not_match(tmp_path, capsys):
    from graspcap.catalog.repair import main

    root = tmp_path / "cat"
    commit_three(root)
    log_entry(root, "versions", 3).unlink()
    log_entry(root, "frames", 3).write_text('{"commitInfo": {"operation": "WRITE"}}\n')
    assert main([str(root)]) == 2
    assert capsys.readouterr().err == (
        "left out version 3: table 'frames' at Delta version 3 has 9 rows, the row says 12\n")
    assert gc.open(root).latest_version() == 2


def test_table_commits_made_for_a_later_version_are_evidence(tmp_path):
    # versions 2 and 3 lost with every trace but the data tables' own commit metadata
    root = tmp_path / "cat"
    cat = commit_three(root)
    v1 = snapshot(cat, 1)
    for n in (2, 3):
        log_entry(root, "versions", n).unlink()
    listed = set(json.loads(line)["add"]["path"] for n in (0, 1)
                 for line in log_entry(root, "versions", n).read_text().splitlines()
                 if line.startswith('{"add"'))
    for path in (root / "tables" / "versions").glob("*.parquet"):
        if path.name not in listed:
            path.unlink()
    (root / "published.json").unlink()
    pins = delta_logs(root)
    with pytest.raises(CatalogDamaged) as err:
        gc.open(root).commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert (f"{log_entry(root, 'sessions', 3)}: table 'sessions': Delta version 3 was made for "
            "catalog version 3, so version 2 was published, but the versions table ends "
            "at 1") in err.value.problems
    assert (f"{root / 'tables' / 'builds'}: build 'b3' was committed as version 3, so "
            "version 2 was published, but the versions table ends at 1") in err.value.problems
    assert delta_logs(root) == pins
    assert_reads_back(root, {1: v1})


def test_a_tag_of_a_lost_version_is_evidence(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    cat.tag(3, "paper")
    entry = log_entry(root, "versions", 3)
    [row_file] = [json.loads(line)["add"]["path"] for line in entry.read_text().splitlines()
                  if line.startswith('{"add"')]
    entry.unlink()
    (root / "tables" / "versions" / row_file).unlink()
    (root / "published.json").unlink()
    logs = delta_logs(root)
    with pytest.raises(CatalogDamaged) as err:  # else: the tables rolled back to version 2
        gc.open(root).commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert err.value.problems == [f"{root / 'tables' / 'tags'}: tag 'paper' points at version "
                                  "3 but the versions table ends at version 2"]
    assert delta_logs(root) == logs


def test_gap_in_the_versions_log_keeps_readers_and_stops_writers(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    snapshots = {v: snapshot(cat, v) for v in (1, 3)}
    log_entry(root, "versions", 2).unlink()

    fresh = gc.open(root)
    assert fresh.versions()["version"].to_pylist() == [1, 3]
    assert fresh.latest_version() == 3
    assert_reads_back(root, snapshots)
    with pytest.raises(gc.VersionNotFound, match="has no version 2"):
        fresh.table("sessions", 2)

    pins = delta_logs(root)
    with pytest.raises(CatalogDamaged) as err:
        fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert err.value.problems == [
        f"{root / 'tables' / 'versions' / '_delta_log'}: table 'versions' lacks log entry "
        "00000000000000000002.json (its log runs 0-3 with a gap: Delta version 2 is lost)"]
    assert delta_logs(root) == pins


def test_garbage_versions_entry_keeps_readers_and_stops_writers(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    snapshots = {v: snapshot(cat, v) for v in (1, 3)}
    log_entry(root, "versions", 2).write_bytes(b"\xff\xd8 not json")
    fresh = gc.open(root)
    assert fresh.versions()["version"].to_pylist() == [1, 3]
    assert_reads_back(root, snapshots)
    logs = delta_logs(root)
    with pytest.raises(CatalogDamaged) as err:
        fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert err.value.problems == [
        f"{log_entry(root, 'versions', 2)}: table 'versions': the log entry for Delta version 2 "
        "is unreadable: not UTF-8 text (byte 0)"]
    with pytest.raises(CatalogDamaged):
        fresh.tag(3, "paper")
    assert delta_logs(root) == logs
    assert fresh.problems() == err.value.problems


def test_lost_data_table_entry_is_named_and_other_versions_read(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    v1 = snapshot(cat, 1)
    log_entry(root, "frames", 3).unlink()  # the tail entry: version 3's frames

    fresh = gc.open(root)
    assert_reads_back(root, {1: v1})
    with pytest.raises(CatalogDamaged) as err:
        fresh.table("frames", 3)
    assert err.value.problems == [
        f"{log_entry(root, 'frames', 3)}: table 'frames' at Delta version 3 is needed but the "
        "log ends at Delta version 2 (Delta version 3 is lost)"]
    with pytest.raises(CatalogDamaged) as err:
        fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert err.value.problems == [
        f"{root / 'tables' / 'frames' / '_delta_log'}: version 3 pins table 'frames' at Delta "
        "version 3 but its log ends at 2 (Delta version 3 is lost)"]


@pytest.mark.parametrize("garbage", [b"\x00\xff\xfe binary", b'{"add": {"path": "trunc',
                                     b"[1, 2, 3]\n"])
def test_garbage_log_entry_is_named_without_a_backtrace(tmp_path, garbage):
    root = tmp_path / "cat"
    cat = commit_three(root)
    v1 = snapshot(cat, 1)
    log_entry(root, "sessions", 2).write_bytes(garbage)

    fresh = gc.open(root)
    assert_reads_back(root, {1: v1})  # version 1 is pinned before the bad entry
    for call in (lambda: fresh.table("sessions", 3),
                 lambda: fresh.commit(make_build(["p05-drill-use-00"], seed=5))):
        with pytest.raises(CatalogDamaged) as err:
            call()
        [problem] = err.value.problems
        assert problem.startswith(f"{log_entry(root, 'sessions', 2)}: table 'sessions': the log "
                                  "entry for Delta version 2 is unreadable: ")
        assert "backtrace" not in str(err.value) and "0: <unknown>" not in str(err.value)


def test_a_log_entry_rewritten_as_valid_json_never_reads_wrong(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    v1 = snapshot(cat, 1)
    log_entry(root, "frames", 3).write_text('{"commitInfo": {"operation": "WRITE"}}\n')
    fresh = gc.open(root)  # deltalake reads version 3 without its added file: 3 rows short
    with pytest.raises(CatalogDamaged) as err:
        fresh.table("frames", 3)
    assert err.value.problems == [
        f"{root / 'tables' / 'frames'}: table 'frames' at version 3 has 9 rows, but version 3 "
        "was committed with 12: a Delta log entry or a data file of it was altered"]
    logs = delta_logs(root)
    with pytest.raises(CatalogDamaged) as err:
        fresh.commit(make_build(["p05-drill-use-00"], seed=5, build_id="b5"))
    assert err.value.problems == [
        f"{root / 'tables' / 'frames'}: table 'frames' at version 3 has 9 rows, but version 3 "
        "was committed with 12: a Delta log entry of it was altered"]
    assert delta_logs(root) == logs
    assert_reads_back(root, {1: v1})


def test_killed_writer_orphans_are_still_rolled_back(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    before = snapshot(cat, 3)
    commit = make_build(["p05-drill-use-00"], seed=5, build_id="b5")
    real = commit_mod.write_deltalake

    def die_before_versions(uri, *args, **kwargs):
        if uri.endswith("/versions"):
            raise KeyboardInterrupt  # the writer stops between its builds and versions commits
        return real(uri, *args, **kwargs)

    commit_mod.write_deltalake = die_before_versions
    try:
        with pytest.raises(KeyboardInterrupt):
            cat.commit(commit)
    finally:
        commit_mod.write_deltalake = real
    assert DeltaTable(str(root / "tables" / "builds")).version() == 4  # the orphan commits
    fresh = gc.open(root)
    assert fresh.commit(commit) == 4  # made for version 4 = last + 1: rolled back, then redone
    assert fresh.table("builds", 4)["build_id"].to_pylist().count("b5") == 1
    assert_reads_back(root, {3: before})


# --- 2. two creators at once ---------------------------------------------------------------

def _create(root: str, barrier) -> None:
    barrier.wait()
    gc.open(root, create=True)


def test_two_processes_creating_a_catalog_at_once_both_succeed(tmp_path):
    root = tmp_path / "new" / "cat"
    ctx = multiprocessing.get_context("spawn")
    barrier = ctx.Barrier(2)
    procs = [ctx.Process(target=_create, args=(str(root), barrier)) for _ in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(120)
    assert [p.exitcode for p in procs] == [0, 0]
    for name in (*DATA_TABLES, "versions", "tags"):
        log = root / "tables" / name / "_delta_log"
        creates = [f.name for f in sorted(log.glob("*.json"))
                   if '"operation":"CREATE TABLE"' in f.read_text()]
        assert creates == ["00000000000000000000.json"], name
    cat = gc.open(root)
    assert cat.latest_version() is None
    assert cat.commit(make_build(DAMAGE_IDS[0], seed=1)) == 1


