"""Reading ``frames`` after many small incremental builds, before and after ``catalog optimize``.

    .venv/bin/python bench/compaction.py [--builds 50] [--sessions-per-build 2] [--frames 60]

Commits ``--builds`` versions of a few sessions each (``tests/catalog_factory.make_build``: fake
rows, no pipeline), then times reading the newest version's ``frames`` (a fresh ``Catalog``
each time, median of 15, the catalogs taking turns): after the builds, after
``optimize_catalog``, and the same rows committed at once into a new catalog (freshly
written). Also the Delta files per table.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import graspcap.catalog as gc  # noqa: E402
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--builds", type=int, default=50)
    ap.add_argument("--sessions-per-build", type=int, default=2)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
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
