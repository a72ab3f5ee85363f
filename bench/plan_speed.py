"""Wall time of ``graspcap build --plan`` on an unchanged catalog, in a fresh process.

    OMP_NUM_THREADS=1 .venv/bin/python bench/plan_speed.py [--sessions 8] [--frames 40]
        [--preset fast] [--repeat 3]

Writes ``--sessions`` synthetic sessions (seeds [11, i], easy; a seed the rig cannot stage is
skipped), builds them once (cold, untimed
beyond its own line), then runs ``graspcap build ROOT --catalog C --plan`` ``--repeat`` times,
each in a new Python process (imports, code digests of the 14 stages, every key: the cost a
person pays before a rebuild), and prints the wall times, their median per session, and the
plan's summary line (it must say "all cached").
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="graspcap-plan-bench-"))
    from graspcap.flows.runtime import configure

    configure(tmp / "prefect-work")
    from graspcap.synth import config_for, generate_session
    from graspcap.tasks.core.errors import StageError

    root, catalog = tmp / "sessions", tmp / "catalog"
    cfg, made, i = config_for("easy", args.frames), 0, 0
    while made < args.sessions:  # seeds the rig cannot stage are skipped
        try:
            generate_session(root, [11, i], cfg, None)
            made += 1
        except StageError:
            pass
        i += 1
    from graspcap.flows.build import build_dataset

    t = time.perf_counter()
    report = build_dataset([root], catalog, args.preset, build_id="cold")
    print(f"cold build of {args.sessions} sessions: {time.perf_counter() - t:.1f} s "
          f"({len(report.failed)} failed)")
    cmd = [sys.executable, "-m", "graspcap.cli", "build", str(root), "--catalog", str(catalog),
           "--preset", args.preset, "--plan"]
    walls, last = [], ""
    for _ in range(args.repeat):
        t = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        walls.append(time.perf_counter() - t)
        last = out.stdout.strip().splitlines()[-1]
    med = statistics.median(walls)
    print(f"plan in a fresh process, {args.sessions} unchanged sessions: median {med:.2f} s "
          f"(runs {', '.join(f'{w:.2f}' for w in walls)}), {med / args.sessions * 1000:.0f} ms "
          f"a session")
    print(f"plan summary: {last}")


if __name__ == "__main__":
    main()
