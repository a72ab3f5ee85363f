"""Dask speed-up of a cold build with 1, 2, 4 and 8 workers on the same sessions (issue 21).

    OMP_NUM_THREADS=1 .venv/bin/python bench/dask_scaling.py [--workers 1 2 4 8]
        [--sessions 16] [--frames 40] [--profile easy] [--preset fast] [--repeat 1]
        [--address tcp://HOST:PORT]

For a machine with at least as many cores as the largest worker count (a lab's workstation or
a cluster node with graspcap installed: the pipeline needs its compiled dependencies, gtsam,
open3d and pycolmap; docs/scale_out.md). On fewer cores the script still runs and says so:
workers beyond the cores only compete.

Writes ``--sessions`` synthetic sessions once (seeds [10000, i], skipping any the rig cannot
stage), then for each worker count W (in the order given; with ``--repeat`` > 1 the order
is reversed every other round) a cold ``graspcap build --dask local:W`` into a new catalog, in
a fresh process (bench/scale.py's ``run_build``: wall, CPU of the process tree, peak RSS per
process). ``--address`` builds on an existing scheduler instead, once, for comparison (start
its workers with ``--nthreads 1 --preload graspcap.flows.worker``).

Prints one markdown table: wall, the build's run phase (from its own record: the stages and the
cluster's start, without the process's imports and Prefect's start-up), CPU, the speed-ups
against 1 worker and the parallel efficiency (speed-up / W), medians over the rounds.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from scale import after_build, run_build  # noqa: E402 - bench/ is the script's folder


def sessions(root: Path, n: int, profile: str, frames: int) -> list[Path]:
    from graspcap.synth import config_for, generate_session
    from graspcap.tasks.core.errors import StageError

    cfg, made, i = config_for(profile, frames), [], 0
    while len(made) < n:
        try:
            made.append(generate_session(root, [10000, i], cfg))
        except StageError:
            pass
        i += 1
    return made


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--sessions", type=int, default=16)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--profile", default="easy")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--address", default=None, help="also build once on this scheduler")
    ap.add_argument("--out", type=Path, default=None, help="work folder (default: temporary)")
    args = ap.parse_args()
    cores = os.cpu_count() or 1
    if max(args.workers) > cores:
        print(f"NOTE: {cores} cores for up to {max(args.workers)} workers: the counts above "
              f"{cores} cannot show a speed-up here", flush=True)
    base = args.out or Path(tempfile.mkdtemp(prefix="graspcap-dask-scaling-"))
    root = base / "sessions"
    if not root.exists():
        sessions(root, args.sessions, args.profile, args.frames)
    runs: dict[str, list[dict]] = {}
    plan = [f"local:{w}" for w in args.workers]
    for r in range(args.repeat):
        order = plan if r % 2 == 0 else plan[::-1]
        for dask in order + ([args.address] if args.address and r == 0 else []):
            catalog = base / f"catalog-{len(runs.get(dask, []))}-{dask.replace(':', '_')[-24:]}"
            shutil.rmtree(catalog, ignore_errors=True)
            m = run_build([str(root), "--catalog", str(catalog), "--preset", args.preset,
                           "--dask", dask], base / "builds.log")
            after_build(catalog, m)
            m["run_s"] = json.loads((catalog / "work" / "builds.jsonl").read_text()
                                    .splitlines()[-1])["seconds"]["run"]
            workers = [mb for role, mb in m["other_rss_mb"] if role == "dask-worker"]
            m["worker_rss_mb"] = max(workers, default=0.0)
            runs.setdefault(dask, []).append(m)
            print(f"  {dask}: {m['wall_s']:.1f} s wall, run phase {m['run_s']:.1f} s, "
                  f"{m['cpu_s']:.1f} s CPU, {m['ran']} stages, {m['failed']} failed",
                  flush=True)
            shutil.rmtree(catalog, ignore_errors=True)
    one = runs.get(plan[0])
    print(f"\n{args.sessions} sessions x {args.frames} frames ({args.profile}, preset "
          f"{args.preset}), {cores} cores, medians of {args.repeat} round(s)\n")
    print("| workers | wall s | run phase s | CPU s | peak RSS a worker MB | speed-up (wall) "
          "| speed-up (run phase) | efficiency (run phase) |")
    print("|---|---|---|---|---|---|---|---|")
    w1 = statistics.median(m["wall_s"] for m in one) if one else None
    r1 = statistics.median(m["run_s"] for m in one) if one else None
    for dask, ms in runs.items():
        wall = statistics.median(m["wall_s"] for m in ms)
        run = statistics.median(m["run_s"] for m in ms)
        cpu = statistics.median(m["cpu_s"] for m in ms)
        rss = max(m["worker_rss_mb"] for m in ms)
        n = int(dask.split(":")[1]) if dask.startswith("local:") else None
        s_wall = f"{w1 / wall:.2f}" if w1 else ""
        s_run = f"{r1 / run:.2f}" if r1 else ""
        eff = f"{r1 / run / n:.2f}" if r1 and n else ""
        print(f"| {dask} | {wall:.1f} | {run:.1f} | {cpu:.1f} | {rss:.0f} | {s_wall} | {s_run} "
              f"| {eff} |")
    if args.out is None:
        shutil.rmtree(base, ignore_errors=True)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
