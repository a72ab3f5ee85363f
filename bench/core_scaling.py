"""What this machine's cores give: one CPU-bound job alone against N copies at once.

    .venv/bin/python bench/core_scaling.py [--copies 2] [--rounds 3] [--loops 20000000]

The job is a pure-Python loop (no memory traffic, no threads, no I/O), the most parallel
work there is. With N independent cores, N copies take as long as one, and the throughput
ratio (N x alone / together) is N. It bounds every multi-process speed-up on the machine,
the Dask 2 / 1 worker ratio of ``bench/build_overhead.py`` included. Rounds alternate alone
and together, medians reported.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

JOB = "s = 0\nfor i in range({loops}):\n    s += i * i % 7\n"


def _run(copies: int, loops: int) -> float:
    """Wall seconds until ``copies`` processes running the job all finish."""
    start = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-c", JOB.format(loops=loops)])
             for _ in range(copies)]
    for p in procs:
        if p.wait() != 0:
            raise RuntimeError("the job failed")
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--loops", type=int, default=20_000_000)
    args = parser.parse_args()
    alone, together = [], []
    for _ in range(args.rounds):
        alone.append(_run(1, args.loops))
        together.append(_run(args.copies, args.loops))
    ratios = [args.copies * a / t for a, t in zip(alone, together, strict=True)]
    print(f"\n{args.copies} copies of a {args.loops:,}-step pure-Python loop, "
          f"{args.rounds} rounds\n")
    print("| measure | median | min | max |")
    print("|---|---|---|---|")
    for name, v in (("alone (s)", alone), (f"{args.copies} at once (s)", together),
                    ("throughput ratio (ideal: copies)", ratios)):
        print(f"| {name} | {statistics.median(v):.2f} | {min(v):.2f} | {max(v):.2f} |")


if __name__ == "__main__":
    main()
