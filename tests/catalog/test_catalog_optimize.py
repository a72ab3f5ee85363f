"""Compaction (`graspcap catalog optimize`): after many small appends the newest version reads
from fewer files with the same rows, and every older version and tag reads what it read."""

from __future__ import annotations

import pyarrow.compute as pc

import graspcap.catalog as gc
from graspcap.catalog.delta import delta_version, log_entries, table_files
from graspcap.catalog.optimize import optimize_catalog
from graspcap.cli import main
from tests.catalog_factory import make_build, snapshot

N = 12
IDS = [f"p{i:02d}-{('mug', 'drill', 'bowl')[i % 3]}-use-00" for i in range(N)]


def _sorted(table):
    keys = [k for k in ("session_id", "frame", "build_id") if k in table.column_names]
    return table.sort_by([(k, "ascending") for k in keys])


def test_optimize_compacts_the_newest_version_and_keeps_time_travel(tmp_path, capsys):
    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    for i, sid in enumerate(IDS):  # one small build per session: one file per table each
        assert cat.commit(make_build([sid], seed=i, build_id=f"b{i}")) == i + 1
    cat.tag(5, "paper")
    before = {v: snapshot(cat, v) for v in range(1, N + 1)}
    versions = cat.versions()
    files = {v: {n: cat.files(n, v) for n in ("sessions", "frames", "builds")}
             for v in range(1, N + 1)}
    assert len(files[N]["frames"]) == N

    assert main(["catalog", "optimize", "--catalog", str(root)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"compacted version {N} into version {N + 1}: {3 * N} -> 3 table "
                          "file(s) (sessions 12 -> 1, frames 12 -> 1, builds 12 -> 1)")
    cat = gc.open(root)
    assert cat.published_version() == N + 1 and cat.states()[N + 1] == "published"
    assert cat.versions()["build_id"].to_pylist()[-1].startswith("optimize-")
    for name in ("sessions", "frames", "builds"):
        assert len(cat.files(name)) == 1, name
        assert _sorted(cat.table(name)).equals(_sorted(before[N][name])), name
    assert cat.diff(N, N + 1) == {"added": [], "removed": [], "changed": {}}
    # the versions table (one file per row) is compacted too, its rows unchanged
    assert len(table_files(cat.layout, "versions", delta_version(cat.layout, "versions"))) == 1
    assert cat.versions().slice(0, N).equals(versions)
    # every older version and the tag read the same rows from their own files
    fresh = gc.open(root)
    for v in range(1, N + 1):
        for name, table in snapshot(fresh, v).items():
            assert table.equals(before[v][name]), (v, name)
            assert fresh.files(name, v) == files[v][name], (v, name)
    assert fresh.table("frames", "paper").equals(before[5]["frames"])
    # a checkpoint of every table, and the log entries before it are all kept
    for name in ("sessions", "frames", "builds", "versions"):
        commits, checkpoints = log_entries(cat.layout, name)
        assert checkpoints and commits == list(range(commits[-1] + 1)), name
    assert cat.problems() == []

    # the next build commits on top; vacuum keeps what the kept versions need
    assert cat.commit(make_build([IDS[0]], seed=99, build_id="after")) == N + 2
    report = cat.vacuum(2)
    assert report.kept_versions == [5, N + 1, N + 2]
    again = gc.open(root)
    assert again.table("frames", "paper").equals(before[5]["frames"])
    frames = again.table("frames", N + 1)
    assert _sorted(frames).equals(_sorted(before[N]["frames"]))
    assert pc.count_distinct(again.table("frames")["session_id"]).as_py() == N
    # nothing more to compact right after a compaction of the newest version
    assert optimize_catalog(again).text().startswith("compacted version")  # the new build
    assert optimize_catalog(gc.open(root)).version is None
