"""Reading ``frames`` after many small incremental builds, before and after ``catalog optimize``;
and what a one-session commit rewrites against the catalog's size.

    .venv/bin/python bench/compaction.py [--builds 50] [--sessions-per-build 2] [--frames 60]
    .venv/bin/python bench/compaction.py --one-session 100 300 1000 [--frames 60]

Commits ``--builds`` versions of a few sessions each (``tests/catalog_factory.make_build``: fake
rows, no pipeline), then times reading the newest version's ``frames`` (a fresh ``Catalog``
each time, median of 15, the catalogs taking turns): after the builds, after
``optimize_catalog``, and the same rows committed at once into a new catalog (freshly
written). Also the Delta files per table.

``--one-session N ...`` (issue 21: the rewrite behind "one changed session published in 60 s"):
per N, a new catalog with N sessions committed at once (the cold build), then a build that
changes one session, a build of 10 new sessions (new takes of existing participants, so their
ids sort among the old ones), ``optimize_catalog``, and one more one-session change. For each
commit: wall time and the ``frames`` Parquet files and bytes its Delta commits add and remove
(from the add/remove actions of the log entries between the two versions' pins); then the time
to read the newest ``frames``. ``--frames-file-mb M`` tries another target file size.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.compute as pc

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import graspcap.catalog as gc  # noqa: E402
from graspcap.catalog import commit, optimize  # noqa: E402
from graspcap.catalog.optimize import optimize_catalog  # noqa: E402
from tests.catalog_factory import make_build  # noqa: E402


def _read_s(roots: list[Path], repeat: int = 15) -> list[tuple[float, float]]:
    """Per catalog of ``roots``, median seconds of (a fresh ``Catalog``'s ``table("frames")``:
    resolving the published version, listing its files, reading them; reading them again
    with the files listed). The catalogs take turns in each repetition, so a load that drifts
    (a shared machine) weighs on each alike."""
    full: list[list[float]] = [[] for _ in roots]
    read: list[list[float]] = [[] for _ in roots]
    for _ in range(repeat):
        for i, root in enumerate(roots):
            cat = gc.open(root)
            t0 = time.perf_counter()
            cat.table("frames")
            full[i].append(time.perf_counter() - t0)
            v = cat.published_version()
            t1 = time.perf_counter()
            cat.table("frames", v)  # pins and file list cached
            read[i].append(time.perf_counter() - t1)
    return [(statistics.median(f), statistics.median(r)) for f, r in zip(full, read,
                                                                           strict=True)]


def frames_actions(root: Path, first: int, last: int) -> dict[str, int]:
    """Files and bytes the ``frames`` Delta versions ``first``..``last`` add and remove."""
    out = {"added": 0, "added_bytes": 0, "removed": 0, "removed_bytes": 0}
    for v in range(first, last + 1):
        entry = root / "tables" / "frames" / "_delta_log" / f"{v:020d}.json"
        for line in entry.read_text().splitlines():
            action = json.loads(line)
            for kind, key in (("add", "added"), ("remove", "removed")):
                if kind in action:
                    out[key] += 1
                    out[f"{key}_bytes"] += int(action[kind].get("size") or 0)
    return out


def _frames_pin(cat: gc.Catalog, version: int | None) -> int:
    if version is None:
        return 0  # an empty catalog: its tables are at Delta version 0
    row = cat.versions().filter(pc.equal(cat.versions()["version"], version)).to_pylist()[0]
    return int(json.loads(row["table_versions"])["frames"])


def _timed_commit(root: Path, build) -> tuple[float, dict[str, int]]:
    cat = gc.open(root)
    before = _frames_pin(cat, cat.latest_version())
    t0 = time.perf_counter()
    version = cat.commit(build)
    wall = time.perf_counter() - t0
    return wall, frames_actions(root, before + 1, _frames_pin(gc.open(root), version))


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def one_session(sizes: list[int], frames: int) -> None:
    """The ``--one-session`` measurement (module docstring), a markdown row per commit."""
    objects = ("mug", "drill", "bowl")
    print("| N | commit | wall s | frames files added / removed | bytes added / removed | "
          "frames files, total bytes after |")
    print("|---|---|---|---|---|---|")
    for n in sizes:
        ids = [f"p{i:04d}-{objects[i % 3]}-use-00" for i in range(n)]
        new = [f"p{i:04d}-{objects[i % 3]}-use-01" for i in range(3, n, max(1, n // 10))][:10]
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp) / "catalog"
            gc.open(root, create=True)
            steps = [("cold", make_build(ids, seed=n, build_id="cold", frames=frames)),
                     ("one session changed", make_build([ids[n // 2]], seed=n + 1,
                                                        build_id="one", frames=frames)),
                     ("10 new sessions", make_build(new, seed=n + 2, build_id="new",
                                                    frames=frames)),
                     ("optimize", None),
                     ("one session changed", make_build([ids[n // 3]], seed=n + 3,
                                                        build_id="two", frames=frames))]
            for what, build in steps:
                if build is None:
                    t0 = time.perf_counter()
                    report = optimize_catalog(gc.open(root))
                    wall = time.perf_counter() - t0
                    cat = gc.open(root)
                    pins = [_frames_pin(cat, v) for v in (report.compacted_version,
                                                          cat.latest_version())]
                    acts = frames_actions(root, pins[0] + 1, pins[1])
                else:
                    wall, acts = _timed_commit(root, build)
                files = gc.open(root).files("frames")
                total = sum(Path(f).stat().st_size for f in files)
                print(f"| {n} | {what} | {wall:.2f} | {acts['added']} / {acts['removed']} | "
                      f"{_mb(acts['added_bytes'])} / {_mb(acts['removed_bytes'])} | "
                      f"{len(files)}, {_mb(total)} |", flush=True)
            reads = []
            for _ in range(5):
                t0 = time.perf_counter()
                gc.open(root).table("frames")
                reads.append(time.perf_counter() - t0)
            print(f"| {n} | read the newest `frames` (`gc.open(...).table`, median of 5) | "
                  f"{statistics.median(reads):.2f} | | | |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--builds", type=int, default=50)
    ap.add_argument("--sessions-per-build", type=int, default=2)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--one-session", type=int, nargs="+", metavar="N",
                    help="measure one-session commits on catalogs of N sessions instead")
    ap.add_argument("--frames-file-mb", type=float, default=None,
                    help="with --one-session: the frames target file size (MiB) to try "
                         "instead of catalog.commit.FRAMES_FILE_BYTES")
    args = ap.parse_args()
    if args.frames_file_mb is not None:
        commit.FRAMES_FILE_BYTES = int(args.frames_file_mb * 2**20)
        optimize.TARGET_BYTES["frames"] = commit.FRAMES_FILE_BYTES
    if args.one_session:
        print(f"frames target file size {commit.FRAMES_FILE_BYTES / 2**20:g} MiB")
        one_session(args.one_session, args.frames)
        return
    objects = ("mug", "drill", "bowl")
    ids = [[f"p{b:03d}-{objects[(b + k) % 3]}-use-{k:02d}" for k in
            range(args.sessions_per_build)] for b in range(args.builds)]
    with tempfile.TemporaryDirectory() as tmp:
        root, fresh = Path(tmp) / "incremental", Path(tmp) / "fresh"
        cat = gc.open(root, create=True)
        t0 = time.perf_counter()
        for b, some in enumerate(ids):
            cat.commit(make_build(some, seed=b, build_id=f"b{b}", frames=args.frames))
        commit_s = time.perf_counter() - t0
        gc.open(root).table("frames")  # warm up pyarrow's and deltalake's first calls
        files = len(gc.open(root).files("frames"))
        rows = gc.open(root).table("frames").num_rows
        unoptimized = Path(tmp) / "unoptimized"
        shutil.copytree(root, unoptimized, ignore=shutil.ignore_patterns(".lock"))
        t0 = time.perf_counter()
        report = optimize_catalog(gc.open(root))
        optimize_s = time.perf_counter() - t0
        every = [sid for some in ids for sid in some]
        one = gc.open(fresh, create=True)
        one.commit(make_build(every, seed=0, build_id="fresh", frames=args.frames))
        before, after, written = _read_s([unoptimized, root, fresh])
        print(f"{args.builds} builds of {args.sessions_per_build} sessions x {args.frames} "
              f"frames: {rows} frames rows; commits {commit_s:.1f} s")
        print(f"frames files: {files} after the builds, {report.by_table['frames'][1]} after "
              f"optimize ({optimize_s:.2f} s: {report.text()})")
        for i, what in enumerate(("open + resolve + list + read", "read (files listed)")):
            print(f"frames, {what} (median of 15, interleaved): {before[i] * 1e3:.1f} ms "
                  "after the builds, "
                  f"{after[i] * 1e3:.1f} ms after optimize, {written[i] * 1e3:.1f} ms freshly "
                  f"written (ratios {before[i] / written[i]:.2f} and "
                  f"{after[i] / written[i]:.2f})")


if __name__ == "__main__":
    main()
