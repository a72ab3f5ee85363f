"""Prefect's database after K builds, with and without retention (issue 21; docs/benchmarks.md).

    OMP_NUM_THREADS=1 .venv/bin/python bench/prefect_db.py --runs 40 --keep 10

Each mode runs in its own process with its own Prefect home (``flows.runtime.configure``, the
embedded defaults a build gets, heartbeats off as in a build) and Prefect's ephemeral API; a
"build" is a tiny flow run: ``--tasks`` task runs, three WARNING log lines (the level that
reaches the API by default) and a table artifact under one key, as a build's QA table; like
``flows/build.py`` it calls ``prune_flow_runs`` at its end, inside the flow run. Modes:
``none`` (no retention), ``runs`` (flow runs only: ``RunRetention(history=False)``, what the
retention did before) and ``all`` (flow runs, then events, event resources, logs and
artifacts). Prints, every ``--every`` runs and after the last (once the server has persisted
its events), the database file and its write-ahead log in MB and the rows of every table that
grows per run; writes them to ``--out`` as JSON.
"""

from __future__ import annotations

import argparse
import json
import sqlite3
import subprocess
import sys
import tempfile
import time
from contextlib import closing
from pathlib import Path

TABLES = ("flow_run", "flow_run_state", "task_run", "task_run_state", "events",
          "event_resources", "log", "artifact", "artifact_collection")


def measure(db: Path) -> dict:
    with closing(sqlite3.connect(db, timeout=60)) as con:
        rows = {t: con.execute(f"SELECT count(*) FROM {t}").fetchone()[0] for t in TABLES}
        free = con.execute("PRAGMA freelist_count").fetchone()[0]
        page = con.execute("PRAGMA page_size").fetchone()[0]
    wal = db.with_name(db.name + "-wal")
    return {"db_mb": round(db.stat().st_size / 1e6, 3),
            "wal_mb": round(wal.stat().st_size / 1e6, 3) if wal.exists() else 0.0,
            "free_mb": round(free * page / 1e6, 3), "rows": rows}


def child(mode: str, runs: int, keep: int, tasks: int, every: int, home: Path) -> list[dict]:
    from graspcap.flows.runtime import build_settings, configure

    configure(home)
    from prefect import flow, get_run_logger, task
    from prefect.artifacts import create_table_artifact

    from graspcap.flows.retention import RunRetention, prune_flow_runs

    retention = None if mode == "none" else RunRetention(
        max_runs=keep, max_age_days=None, history=mode == "all")

    @task
    def stage(i: int) -> int:
        return i + 1

    @flow(name="graspcap-db-bench", persist_result=False)
    def build(n: int) -> list[int]:
        logger = get_run_logger()
        for k in range(3):
            logger.warning("build %d line %d", n, k)
        out = [stage(i) for i in range(tasks)]
        create_table_artifact([{"session": f"s{i}", "status": "ok"} for i in range(tasks)],
                              key="graspcap-db-bench-qa")
        if retention is not None:
            prune_flow_runs(retention)
        return out

    db = home / "prefect" / "prefect.db"
    points = []
    t0 = time.perf_counter()
    for n in range(1, runs + 1):
        with build_settings():
            build(n)
        if n % every == 0 and n < runs:
            points.append({"runs": n, "seconds": round(time.perf_counter() - t0, 1),
                           **measure(db)})
            print(json.dumps(points[-1]), flush=True)
    time.sleep(8)  # the server persists events every 5 s
    with build_settings():  # a last pass, as the next build's would (the last run's events)
        if retention is not None:
            prune_flow_runs(retention)
    points.append({"runs": runs, "seconds": round(time.perf_counter() - t0, 1), **measure(db)})
    print(json.dumps(points[-1]), flush=True)
    return points


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--keep", type=int, default=10)
    ap.add_argument("--tasks", type=int, default=20)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--modes", nargs="+", default=["none", "runs", "all"])
    ap.add_argument("--out", type=Path, default=Path("prefect_db.json"))
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        mode, home = args.child.split(":", 1)
        pts = child(mode, args.runs, args.keep, args.tasks, args.every, Path(home))
        Path(home, "points.json").write_text(json.dumps(pts))
        return
    results = {}
    for mode in args.modes:
        with tempfile.TemporaryDirectory(prefix=f"prefect-db-{mode}-") as home:
            print(f"== {mode}: {args.runs} runs of {args.tasks} tasks, keep {args.keep}",
                  flush=True)
            subprocess.run([sys.executable, __file__, "--runs", str(args.runs), "--keep",
                            str(args.keep), "--tasks", str(args.tasks), "--every",
                            str(args.every), "--child", f"{mode}:{home}"], check=True)
            results[mode] = json.loads(Path(home, "points.json").read_text())
    args.out.write_text(json.dumps({"args": {k: v for k, v in vars(args).items()
                                             if k not in ("child", "out")},
                                    "results": results}, indent=1, default=str))
    last = {m: r[-1] for m, r in results.items()}
    print(f"\nafter {args.runs} runs (keep {args.keep}):")
    print("mode  db MB  wal MB  free MB  " + "  ".join(TABLES))
    for m, p in last.items():
        print(f"{m:5} {p['db_mb']:6.2f} {p['wal_mb']:7.2f} {p['free_mb']:7.2f}  "
              + "  ".join(str(p["rows"][t]) for t in TABLES))


if __name__ == "__main__":
    main()
