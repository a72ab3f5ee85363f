"""Cost of the array reads' manifest check and of ``verify_group``, per group of a real size.

    .venv/bin/python bench/array_integrity_bench.py [--repeat 200] [--dir /tmp/graspcap-bench]

Writes one group of each kind the size of a real session (a 10,137-vertex object mesh with
twice as many faces and its contact map, a 778-vertex hand mesh), then reports the median
wall time of ``read_group`` with the manifest check, without it (patched out), and of
``verify_group`` (manifest, decode, digest), with each group's size on disk; reads with and
without the check alternate
(docs/catalog.md, "Integrity").
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import time
from pathlib import Path

import numpy as np

import graspcap.catalog.arrays as arrays
from graspcap.catalog.layout import CatalogLayout

OBJECT_VERTICES, HAND_VERTICES, HAND_FACES = 10137, 778, 1538


def _groups(rng: np.random.Generator) -> dict[str, dict[str, np.ndarray]]:
    n = OBJECT_VERTICES
    return {
        "contact": {"values": rng.uniform(0, 1, n).astype(np.float32),
                    "observed": rng.uniform(size=n) > 0.3},
        "hand_mesh": {"vertices": rng.normal(size=(HAND_VERTICES, 3)).astype(np.float32),
                      "faces": rng.integers(0, HAND_VERTICES, (HAND_FACES, 3)).astype(np.int32),
                      "joints": rng.normal(size=(21, 3))},
        "object_mesh": {"vertices": rng.normal(size=(n, 3)).astype(np.float32),
                        "faces": rng.integers(0, n, (2 * n, 3)).astype(np.int32)},
    }


def _median_ms(func, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        func()
        times.append(time.perf_counter() - t)
    return statistics.median(times) * 1e3


def _read_ms(layout: CatalogLayout, digest: str, repeat: int) -> tuple[float, float]:
    """Median read times with and without the manifest check, alternated (a shared machine's
    load changes under a benchmark; alternating gives both sides the same)."""
    checked = arrays.check_files
    with_check, without = [], []
    for i in range(2 * repeat):
        arrays.check_files = checked if i % 2 == 0 else (lambda *a, **k: None)
        t = time.perf_counter()
        arrays.read_group(layout, digest)
        (with_check if i % 2 == 0 else without).append(time.perf_counter() - t)
    arrays.check_files = checked
    return statistics.median(with_check) * 1e3, statistics.median(without) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=200)
    parser.add_argument("--dir", type=Path, default=Path("/tmp/graspcap-bench-integrity"))
    args = parser.parse_args()
    layout = CatalogLayout(args.dir.resolve())
    shutil.rmtree(layout.root, ignore_errors=True)
    layout.root.mkdir(parents=True)
    checked = arrays.check_files
    try:
        for kind, group in _groups(np.random.default_rng(0)).items():
            group = arrays.check_arrays(kind, group, owner="bench")
            digest = arrays.array_digest(kind, group)
            arrays.write_group(layout, kind, group, digest)
            size = sum(p.stat().st_size for p in layout.array_group(digest).rglob("*")
                       if p.is_file())
            with_check, without = _read_ms(layout, digest, args.repeat)
            verify = _median_ms(lambda d=digest: arrays.verify_group(layout, d),
                                max(1, args.repeat // 4))
            print(f"{kind:<12} {size / 1e3:7.1f} kB  read {without:.3f} ms  read + manifest "
                  f"{with_check:.3f} ms (+{with_check - without:.3f})  verify {verify:.3f} ms")
    finally:
        arrays.check_files = checked
        shutil.rmtree(layout.root, ignore_errors=True)


if __name__ == "__main__":
    main()
