"""What a build holds in memory per session until its one commit (issue 21: peak RSS flat in N).

    .venv/bin/python bench/build_memory.py --demo DIR
    .venv/bin/python bench/build_memory.py --commit 50 200 800 [--hand-vertices 5000]
    OMP_NUM_THREADS=1 .venv/bin/python bench/build_memory.py --timeline 60 --out DIR

``--demo DIR``: the output folder of ``graspcap demo --out DIR`` (its ``sessions/`` and
``catalog/``, whose work area holds every stage result): ``flows.assemble.assemble`` of its
sessions into a new catalog, all stages cached, once to warm the process's caches (the work
area's loaded results, imports) and once under ``tracemalloc``: the memory the ``Assembled``
holds afterwards (what waits for the commit), per session.

``--commit N ...``: per N, ``Catalog.commit`` of N sessions (``tests/catalog_factory.make_build``
rows, 2 frames each) whose arrays are made on every read, as the build's work-area spill reads
them (a hand mesh of ``--hand-vertices`` vertices and faces, the contact map of the object's
mesh): the peak of ``tracemalloc`` during the commit, in MB and in sessions' worth of arrays.
Flat in N when the commit reads each session's arrays as it writes them.

``--timeline N``: a cold ``graspcap build --preset fast`` of the first N sessions of
``bench/scale.py``'s pool (``graspcap synth --profile easy --frames 16``, seeds ``[10000, i]``,
made once under ``DIR/pool``) in a fresh process whose VmRSS is read every 2 s, and in which a
thread counts every object the garbage collector tracks and the bytes the live NumPy arrays own
every 25 s; then the same sessions committed again from the cold build's work area into a new
catalog (every stage cached: what assembling, the commit, compaction and the report hold), the
peak of that build (VmHWM). Prints per minute of the cold build: sessions done, VmRSS median and
maximum, and the objects counted.
"""

from __future__ import annotations

import argparse
import gc as pygc
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import graspcap.catalog as gc  # noqa: E402
from tests.catalog_factory import GeneratedArrays, make_build  # noqa: E402


def assembled_per_session(demo: Path) -> None:
    from graspcap.flows.assemble import assemble
    from graspcap.flows.build import configs_digest, resolve_configs
    from graspcap.flows.cached import session_id_of
    from graspcap.flows.session import settle_session
    from graspcap.flows.workarea import WorkArea

    work = WorkArea(demo / "catalog" / "work")
    configs = resolve_configs("default", None)
    dirs = sorted(p for p in (demo / "sessions").iterdir() if (p / "session.json").exists())
    outcomes, sessions = {}, []
    for d in dirs:
        settled = settle_session(d, configs, work)
        refs = {k: s.ref for k, s in settled.items() if s.state == "Cached"}
        if len(refs) < len(settled):
            sys.exit(f"{d}: not every stage is cached for this code; run graspcap demo again")
        outcomes[str(d)] = (refs, [], list(refs), [], None, None, ())
        sessions.append((d, session_id_of(d)))
    with tempfile.TemporaryDirectory() as tmp:
        cat = gc.open(Path(tmp) / "catalog", create=True)
        build = gc.BuildInfo("bench", "bench", configs_digest(configs))
        assemble(cat, work, build, None, sessions, {}, outcomes)  # caches warm
        pygc.collect()
        tracemalloc.start()
        done = assemble(cat, work, build, None, sessions, {}, outcomes)
        pygc.collect()
        held, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    frames = done.frames.num_rows
    print(f"{len(sessions)} sessions, {frames} frames rows: the Assembled holds {held / 1e6:.3f} "
          f"MB, {held / len(sessions) / 1e6:.3f} MB a session (peak while assembling "
          f"{peak / 1e6:.1f} MB)")


def commit_peak(n: int, vertices: int) -> None:
    ids = [f"p{i:04d}-mug-use-00" for i in range(n)]
    build = make_build(ids, seed=n, frames=2)
    arrays = GeneratedArrays({r["session_id"]: r["object_id"] for r in build.sessions},
                             vertices, faces=2 * vertices)
    one = arrays[ids[0]]
    one_mb = (one.hand_vertices.nbytes + one.hand_faces.nbytes + one.contact.nbytes) / 1e6
    with tempfile.TemporaryDirectory() as tmp:
        cat = gc.open(Path(tmp) / "catalog", create=True)
        pygc.collect()
        tracemalloc.start()
        cat.commit(gc.BuildCommit(build=build.build, sessions=build.sessions,
                                  frames=build.frames, session_arrays=arrays,
                                  object_meshes=build.object_meshes))
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    print(f"N = {n}: commit peak {peak / 1e6:.1f} MB = {peak / 1e6 / one_mb:.1f} sessions' arrays "
          f"({one_mb:.2f} MB a session, {n * one_mb:.0f} MB in all)")


_COUNTING = """
import gc, json, sys, threading, time
import numpy as np
def count(log, t0=time.time()):
    while True:
        time.sleep(25)
        objs = gc.get_objects()
        owned = sum(o.nbytes for o in objs if isinstance(o, np.ndarray) and o.base is None)
        with open(log, "a") as f:
            f.write(json.dumps([time.time() - t0, len(objs), owned]) + "\\n")
        del objs
threading.Thread(target=count, args=(sys.argv.pop(1),), daemon=True).start()
from graspcap.cli import main
sys.exit(main(sys.argv[1:]))
"""
"""The build's entry point with the object-counting thread (``--timeline``)."""


def _sampled_build(args: list[str], home: Path, objects_log: Path | None = None
                   ) -> tuple[list[tuple[float, float]], float]:
    """``graspcap build ARGS`` in a fresh process: its (seconds, VmRSS MB) every 2 s and its
    peak (VmHWM, MB, at the last sample) (with ``objects_log``: under the object-counting
    thread, which writes there)."""
    from scale import status_kb

    env = dict(os.environ, PREFECT_HOME=str(home))
    head = ["-c", _COUNTING, str(objects_log)] if objects_log else ["-m", "graspcap.cli"]
    log = home.parent / f"{home.name}.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, *head, "build", *args], env=env, stdout=out,
                                stderr=subprocess.STDOUT)
    t0, rows, peak_kb = time.perf_counter(), [], 0
    while proc.poll() is None:
        rss_kb, hwm_kb = status_kb(proc.pid, "VmRSS"), status_kb(proc.pid)
        if rss_kb is not None:
            rows.append((time.perf_counter() - t0, rss_kb / 1024))
        peak_kb = max(peak_kb, hwm_kb or 0)
        time.sleep(2)
    if proc.returncode not in (0, 1):
        sys.exit(f"build exited {proc.returncode}: see {log}")
    return rows, peak_kb / 1024


def timeline(n: int, out: Path) -> None:
    from scale import generate_pool

    sessions = generate_pool(out / "pool", n, "easy", 16, 10000)
    root = out / f"sessions-{n}"
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    for s in sessions:  # links are not followed by the build: the folders move instead
        s.rename(root / s.name)
    try:
        cold, recommit = out / "cold", out / "recommit"
        for d in (cold, recommit):
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir()
        objects = cold / "objects.jsonl"
        rss, cold_peak = _sampled_build(
            [str(root), "--catalog", str(cold / "catalog"), "--preset", "fast"],
            cold / "prefect", objects)
        shutil.copytree(cold / "catalog" / "work", recommit / "catalog" / "work")
        _, again_peak = _sampled_build(
            [str(root), "--catalog", str(recommit / "catalog"), "--preset", "fast"],
            recommit / "prefect")
    finally:
        for s in sessions:
            (root / s.name).rename(s)
        root.rmdir()
    log = (cold / "prefect.log").read_text()
    done = [(float(line.split("]")[0].strip("[ s")), int(line.split("(session ")[1].split("/")[0]))
            for line in log.splitlines() if line.startswith("[") and "(session " in line]
    counts = [json.loads(line) for line in objects.read_text().splitlines()] \
        if objects.exists() else []
    print(f"cold build of {n} sessions: peak VmHWM {cold_peak:.0f} MB")
    print("| minute | sessions done | VmRSS median MB | VmRSS max MB | objects tracked | "
          "NumPy arrays owned MB |\n|---|---|---|---|---|---|")
    for m in range(int(rss[-1][0] // 60) + 1):
        inside = [r for t, r in rss if m * 60 <= t < (m + 1) * 60]
        if not inside:
            continue
        by = [k for t, k in done if t < (m + 1) * 60]
        seen = [c for c in counts if m * 60 <= c[0] < (m + 1) * 60]
        print(f"| {m + 1} | {max(by, default=0)} | {statistics.median(inside):.0f} | "
              f"{max(inside):.0f} | {seen[-1][1] if seen else '-'} | "
              f"{f'{seen[-1][2] / 2**20:.0f}' if seen else '-'} |")
    print(f"the same sessions committed from the work area into a new catalog: peak VmHWM "
          f"{again_peak:.0f} MB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, help="a `graspcap demo --out` folder")
    ap.add_argument("--commit", type=int, nargs="*", default=[], help="session counts")
    ap.add_argument("--hand-vertices", type=int, default=5000)
    ap.add_argument("--timeline", type=int, default=0, metavar="N",
                    help="a cold build of N sessions, its memory over time")
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "build_memory")
    args = ap.parse_args()
    if args.demo is None and not args.commit and not args.timeline:
        ap.error("give --demo DIR, --commit N ... and/or --timeline N")
    if args.timeline:
        timeline(args.timeline, args.out)
    if args.demo is not None:
        assembled_per_session(args.demo)
    for n in args.commit:
        commit_peak(n, args.hand_vertices)


if __name__ == "__main__":
    main()
