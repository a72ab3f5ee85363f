"""Orchestration overhead of a dataset build (prints markdown; numbers in docs/architecture.md).

    .venv/bin/python bench/build_overhead.py [--sessions 8] [--frames 40] [--preset fast]

1. Prefect's start-up in a fresh process (first trivial flow run, embedded ephemeral API);
2. the bare baseline: ``tasks.pipeline.run_session`` for every session, sequentially;
3. a cold ``build_dataset`` with 1 and with 2 thread workers (ratio to the baseline);
4. a no-op rebuild (ratio to the cold build);
5. all-cached sessions as 8 subflows vs as tasks of one flow run (the structure decision);
6. Dask LocalCluster, 1 vs 2 single-threaded worker processes (speed-up).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="graspcap-bench-"))
    from graspcap.flows.runtime import configure

    configure(tmp / "prefect-work")
    from graspcap.synth import generate

    root = tmp / "sessions"
    generate(root, sessions=args.sessions, seed=11, difficulty="easy", frames=args.frames)
    rows: list[tuple[str, str, str]] = []

    t = time.perf_counter()
    from prefect import flow

    from graspcap.flows.runtime import build_settings

    @flow
    def trivial() -> int:
        return 1

    with build_settings():
        trivial()
    rows.append(("Prefect start-up (import + first flow run, new PREFECT_HOME)",
                 f"{time.perf_counter() - t:.1f} s", ""))

    from graspcap.flows.build import build_dataset
    from graspcap.tasks.errors import StageError
    from graspcap.tasks.load_session import discover_sessions
    from graspcap.tasks.pipeline import configs_for, run_session

    configs = configs_for(args.preset)
    t = time.perf_counter()
    bare_failed = 0
    for d in discover_sessions([root]):
        try:  # a failing stage stops its session in the build too: same work either way
            run_session(d, configs)
        except StageError:
            bare_failed += 1
    bare = time.perf_counter() - t
    rows.append((f"bare sequential run_session, {args.sessions} sessions", f"{bare:.1f} s",
                 f"{bare_failed} session(s) failed a stage"))

    cold = {}
    for workers in (1, 2):
        t = time.perf_counter()
        r = build_dataset([root], tmp / f"cat{workers}", args.preset, workers=workers)
        cold[workers] = time.perf_counter() - t
        rows.append((f"cold build, {workers} thread worker(s)", f"{cold[workers]:.1f} s",
                     f"{cold[workers] / bare:.2f} x bare (target <= 1.15)"))
    t = time.perf_counter()
    r = build_dataset([root], tmp / "cat2", args.preset)
    noop = time.perf_counter() - t
    assert r.failed or (r.catalog_version is None and r.executed == 0), r.summary()
    rows.append(("no-op rebuild", f"{noop:.2f} s",
                 f"{noop / cold[2]:.3f} x cold (target <= 0.05)"))

    from graspcap.catalog.workarea import WorkArea
    from graspcap.flows.session import session_flow, submit_session

    work = str(tmp / "cat2" / "work")
    dirs = [str(d) for d in discover_sessions([root])]

    @flow
    def as_subflows() -> None:
        for d in dirs:
            session_flow(d, work, args.preset, return_state=True)

    @flow
    def as_tasks() -> None:
        futures = [submit_session(d, configs, WorkArea(work), "bench") for d in dirs]
        for fs in futures:
            for f in fs.values():
                f.wait()

    with build_settings():
        for name, fn in (("subflow per session", as_subflows), ("one flow run", as_tasks)):
            t = time.perf_counter()
            fn()
            rows.append((f"all cached, {len(dirs)} sessions: {name}",
                         f"{time.perf_counter() - t:.2f} s", ""))

    if not args.no_dask:
        dask = {}
        for n in (1, 2):
            t = time.perf_counter()
            r = build_dataset([root], tmp / f"dask{n}", args.preset, dask=f"local:{n}")
            dask[n] = time.perf_counter() - t
            rows.append((f"cold build, Dask LocalCluster {n} worker(s)", f"{dask[n]:.1f} s", ""))
        rows.append(("Dask speed-up 2 vs 1 worker", f"{dask[1] / dask[2]:.2f} x",
                     "target >= 1.7"))

    print(f"\n{args.sessions} synthetic sessions, {args.frames} frames, preset "
          f"{args.preset!r}, load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    print("| measure | value | ratio |\n|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} |")


if __name__ == "__main__":
    main()
