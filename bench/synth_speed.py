"""Time the synthetic rig: N realistic sessions of F frames, single process and with workers.

    .venv/bin/python bench/synth_speed.py [--sessions 4] [--frames 120] [--workers 1 2]

Prints a markdown table (wall time in total and per session) for docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from graspcap.synth import generate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()

    print("| sessions x frames | workers | wall time (s) | per session (s) |")
    print("|---|---|---|---|")
    for workers in args.workers:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            dirs = generate(
                Path(tmp), sessions=args.sessions, seed=args.seed, difficulty="realistic",
                frames=args.frames, workers=workers,
            )
            wall = time.perf_counter() - t0
        print(f"| {len(dirs)} x {args.frames} | {workers} | {wall:.1f} | {wall / len(dirs):.1f} |")


if __name__ == "__main__":
    main()
