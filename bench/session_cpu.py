"""CPU seconds per stage of a whole session, run bare (issue 19's CPU row).

Each session runs every stage (``graspcap.tasks.pipeline.STAGES``, in order, as ``run_session``
does) in a fresh Python process; the child measures each stage's process CPU time
(``time.process_time``: user + system of all the process's threads) and wall time, and prints
them as one JSON line. The parent prints a table per stage (median over sessions), the total
per session and the median total per profile (the session directory's parent name).

The script uses only names the pipeline has had since before issue 19 (``STAGES``,
``run_stage``, ``configs_for``, ``AID_STAGES``), so the same file measures an older checkout:
run it with that checkout's interpreter (``/work/wt/base/.venv/bin/python
bench/session_cpu.py ...``) and it imports that checkout's ``graspcap``.

Usage::

    # once: sessions made by the current generator
    python bench/session_cpu.py generate --root /tmp/s12/cpu --frames 120 \\
        --profile realistic=9400 --profile wild=9700 --sessions 3
    # per code version, the same sessions; --json keeps the rows for a later comparison
    OMP_NUM_THREADS=1 nice -n 10 python bench/session_cpu.py run /tmp/s12/cpu/*/* --json cur.json
    python bench/session_cpu.py compare base.json cur.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _one(session_dir: str) -> dict:
    """Every stage of one session in this process: per-stage CPU and wall seconds, or the
    failing stage and its reason."""
    from graspcap.tasks.pipeline import AID_STAGES, STAGES, configs_for, run_stage

    configs = configs_for()
    results: dict = {}
    cpu_s: dict[str, float] = {}
    wall_s: dict[str, float] = {}
    failed = None
    for name, stage in STAGES.items():
        c0, w0 = time.process_time(), time.perf_counter()
        try:
            results[name] = run_stage(stage, session_dir, configs[name], results)
        except Exception as exc:  # noqa: BLE001 - reported, not handled
            if name not in AID_STAGES:
                failed = f"{name}: {type(exc).__name__}: {str(exc)[:160]}"
        cpu_s[name] = time.process_time() - c0
        wall_s[name] = time.perf_counter() - w0
        if failed:
            break
    return {"session": session_dir, "profile": Path(session_dir).parent.name,
            "cpu_s": cpu_s, "wall_s": wall_s, "failed": failed}


def _run(dirs: list[str]) -> list[dict]:
    rows = []
    for d in dirs:
        p = subprocess.run([sys.executable, __file__, "one", d], capture_output=True, text=True,
                           check=False)
        lines = [x for x in p.stdout.splitlines() if x.startswith("{")]
        row = (json.loads(lines[-1]) if lines else
               {"session": d, "profile": Path(d).parent.name, "cpu_s": {}, "wall_s": {},
                "failed": f"process: rc {p.returncode}: {p.stderr.strip()[-300:]}"})
        total = sum(row["cpu_s"].values())
        print(f"{Path(d).parent.name}/{Path(d).name}: CPU {total:.1f} s"
              + (f"  FAILED {row['failed']}" if row["failed"] else ""), flush=True)
        rows.append(row)
    return rows


def _table(rows: list[dict]) -> None:
    stages = list(dict.fromkeys(s for r in rows for s in r["cpu_s"]))
    for prof in sorted({r["profile"] for r in rows}):
        ok = [r for r in rows if r["profile"] == prof and not r["failed"]]
        print(f"\n## {prof}: {len(ok)} of {sum(r['profile'] == prof for r in rows)} ran through")
        if not ok:
            continue
        print("| stage | median CPU s |")
        for s in stages:
            print(f"| {s} | {statistics.median(r['cpu_s'].get(s, 0.0) for r in ok):.2f} |")
        tot = [sum(r["cpu_s"].values()) for r in ok]
        print(f"| **total** | {statistics.median(tot):.2f} |")
        print("per session: " + ", ".join(f"{Path(r['session']).name} {t:.1f}"
                                          for r, t in zip(ok, tot, strict=True)))


def _compare(base: list[dict], cur: list[dict]) -> None:
    for prof in sorted({r["profile"] for r in cur}):
        names = {r["session"] for r in base if r["profile"] == prof and not r["failed"]} & {
            r["session"] for r in cur if r["profile"] == prof and not r["failed"]}
        if not names:
            print(f"{prof}: no session ran through with both")
            continue

        def med(rows: list[dict], names: set[str] = names) -> float:
            return statistics.median(sum(r["cpu_s"].values()) for r in rows
                                     if r["session"] in names)

        stages = list(dict.fromkeys(s for r in cur for s in r["cpu_s"]))
        print(f"\n## {prof}: {len(names)} sessions both ran through")
        print("| stage | base CPU s | current CPU s |")
        for s in stages:
            b = statistics.median(r["cpu_s"].get(s, 0.0) for r in base if r["session"] in names)
            c = statistics.median(r["cpu_s"].get(s, 0.0) for r in cur if r["session"] in names)
            print(f"| {s} | {b:.2f} | {c:.2f} |")
        print(f"| **total (median of totals)** | {med(base):.2f} | {med(cur):.2f} |")
        print(f"current / base: {med(cur) / med(base):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="make sessions with this checkout's generator")
    g.add_argument("--root", type=Path, required=True)
    g.add_argument("--frames", type=int, default=120)
    g.add_argument("--sessions", type=int, default=3)
    g.add_argument("--profile", action="append", required=True, help="NAME=SEED")
    o = sub.add_parser("one")
    o.add_argument("session")
    r = sub.add_parser("run", help="each session in a fresh process")
    r.add_argument("sessions", nargs="+")
    r.add_argument("--json", type=Path)
    c = sub.add_parser("compare")
    c.add_argument("base", type=Path)
    c.add_argument("current", type=Path)
    a = ap.parse_args()
    if a.cmd == "generate":
        from graspcap.synth import config_for, generate_session

        for spec in a.profile:
            prof, seed = spec.split("=")
            for i in range(a.sessions):
                d = generate_session(a.root / prof, [int(seed), i],
                                     config_for(prof, a.frames), None)
                print(d, flush=True)
    elif a.cmd == "one":
        print(json.dumps(_one(a.session)))
    elif a.cmd == "run":
        rows = _run(a.sessions)
        if a.json:
            a.json.write_text(json.dumps(rows, indent=1))
        _table(rows)
    else:
        _compare(json.loads(a.base.read_text()), json.loads(a.current.read_text()))


if __name__ == "__main__":
    main()
