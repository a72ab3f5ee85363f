"""How a build's costs grow with the number of sessions N (issue 21; docs/benchmarks.md).

Full run (a lab's machine; the issue's sizes; hours of CPU):

    OMP_NUM_THREADS=1 .venv/bin/python bench/scale.py --sizes 100 300 1000 --incremental 50

Short run (``make bench``; a few minutes):

    OMP_NUM_THREADS=1 .venv/bin/python bench/scale.py --short

Sessions: ``graspcap synth`` sessions of the ``--profile`` (default easy: the profile every
stage gets through, so the builds measure the pipeline's work and not early stops) with
``--frames`` grasp frames (default 16: the shortest video the fast preset builds through
here; 3 of 3 sessions, 10 s of CPU a session), seeds ``[--seed, i]``, generated once into
``<out>/pool`` and reused by every size; built with ``--preset`` (default ``fast``).

For each size N (ascending), every build a ``graspcap build`` in a fresh process:

1. cold: the first N sessions into a new catalog. With ``--grow`` (default) the catalog of the
   previous size, copied right after its cold build, gains the sessions N_prev..N (the
   stage work of a cold build is per session; the cold cost of N is reported as the previous
   cold cost plus this build's, marked "grown");
2. unchanged rebuild;
3. one file of one session changed (one pixel of one grasp depth image, +1 mm): the stages
   that read it re-run and the session's rows make a version; also ``--plan`` of that change;
4. ``--arrivals`` (10) new sessions added;
5. ``--incremental`` (50) builds in a row, each after one session's label (``participant``)
   changed (``--change label``: no stage runs, the session's rows are rewritten, a version
   per build: the small-file growth of the tables at the least CPU) or one depth pixel
   (``--change depth``: 3-4 stages run per build);
6. in a fresh process: the time to read ``frames`` of the latest version (a new ``Catalog``
   each read, so the Delta log replay is counted) against the same rows written freshly as
   one Parquet file (alternated, medians), and to open one random session's arrays (contact
   map, hand mesh, object mesh; first read, then the median of warm reads).

Per build: wall time, CPU seconds (the build process and every descendant it reaped: the
Prefect server, Dask workers), peak RSS of the build process and of each other process of
the tree (``VmHWM``, read every 0.2 s), the Prefect database, the catalog (without the work
area) and the work area sizes, the number of Parquet files of ``frames``. The changed files
are restored after each size, so the next size's grown build finds their results cached.

Prints a line per build and one table of each cost against N with the growth exponent (log-log
slope between the smallest and largest N) and a linear extrapolation to ``--extrapolate``
(default 1000) sessions when the largest N measured is below it; writes every number to
``<out>/scale-<sizes>.json``. ``bench/scale.py --table A.json B.json`` prints that table for
the sizes of several runs together (a run continued with ``--grow-from``).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

PROBE = "--read-probe"


def status_kb(pid: int, field: str = "VmHWM") -> int | None:
    """A memory figure of a live process from ``/proc/PID/status``, kB: by default its peak
    resident set size (``VmHWM``), ``VmRSS`` for the current one."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def _role(cmdline: list[str]) -> str:
    cmd = " ".join(cmdline)
    if "uvicorn" in cmd or ("prefect" in cmd and "server" in cmd):
        return "prefect-api"
    if "spawn_main" in cmd or "forkserver" in cmd or "dask_worker" in cmd:
        return "dask-worker"
    return (cmdline[-1] if cmdline else "?")[-40:]


def run_build(args: list[str], log: Path) -> dict:
    """One ``graspcap build ARGS`` in a fresh process: wall, CPU, peak RSS per process."""
    import psutil

    cmd = [sys.executable, "-m", "graspcap.cli", "build", *args]
    peaks: dict[int, tuple[str, int]] = {}
    t0 = time.perf_counter()
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    done = threading.Event()

    def sample() -> None:
        root = psutil.Process(proc.pid)
        while not done.is_set():
            try:
                tree = [root, *root.children(recursive=True)]
            except psutil.Error:
                tree = []
            for p in tree:
                kb = status_kb(p.pid)
                if kb is None:
                    continue
                if p.pid not in peaks:
                    try:
                        role = "build" if p.pid == proc.pid else _role(p.cmdline())
                    except psutil.Error:
                        continue
                    peaks[p.pid] = (role, kb)
                peaks[p.pid] = (peaks[p.pid][0], max(kb, peaks[p.pid][1]))
            done.wait(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    done.set()
    sampler.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    # 1: some session failed (reported); 4: committed, but the audit staged it (its costs are
    # a build's all the same: the next build writes on top of it); else broken
    if proc.returncode not in (0, 1, 4):
        raise RuntimeError(f"build exited {proc.returncode}: see {log}")
    build_mb = max(usage.ru_maxrss, peaks.get(proc.pid, ("build", 0))[1]) / 1024
    others = sorted((role, kb / 1024) for pid, (role, kb) in peaks.items() if pid != proc.pid)
    return {"wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "exit": proc.returncode,
            "build_rss_mb": build_mb, "other_rss_mb": others}


def _size_mb(path: Path, skip: str | None = None) -> float:
    total = 0
    for cur, dirs, files in os.walk(path):
        if skip and Path(cur) == path and skip in dirs:
            dirs.remove(skip)
        for f in files:
            try:
                total += os.lstat(os.path.join(cur, f)).st_size
            except OSError:
                pass
    return total / 1e6


def _last_record(catalog: Path) -> dict:
    lines = (catalog / "work" / "builds.jsonl").read_text().splitlines()
    return json.loads(lines[-1])


def after_build(catalog: Path, m: dict) -> dict:
    """Sizes and the build's own record, added to the measurement ``m``."""
    rec = _last_record(catalog)
    prefect = catalog / "work" / "prefect"
    m.update({
        "version": rec.get("catalog_version"),
        "ran": sum(len(s.get("ran", ())) for s in rec["sessions"]),
        "sessions": len(rec["sessions"]) + (rec.get("unlisted") or {}).get("sessions", 0),
        "failed": len(rec["summary"]["failed"]),
        "flow_s": rec["seconds"].get("total"),
        "prefect_db_mb": sum(p.stat().st_size for p in prefect.glob("*.db*")) / 1e6
        if prefect.exists() else 0.0,
        "catalog_mb": _size_mb(catalog, skip="work"),
        "work_mb": _size_mb(catalog / "work"),
        "frames_files": len(list((catalog / "tables" / "frames").glob("*.parquet"))),
    })
    return m


def change_depth_pixel(session: Path) -> tuple[Path, bytes]:
    """+1 on the first non-zero pixel of the session's first grasp depth image; (file, the
    bytes it had)."""
    import cv2

    path = sorted((session / "grasp" / "depth").iterdir())[0]
    before = path.read_bytes()
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    ys, xs = img.nonzero()[:2]
    img[ys[0], xs[0]] += 1
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")
    return path, before


def change_label(session: Path, i: int) -> tuple[Path, bytes]:
    """A new ``participant`` label in the session's manifest; (file, the bytes it had)."""
    path = session / "session.json"
    before = path.read_bytes()
    doc = json.loads(before)
    doc["participant"] = f"bench-p{i}"
    path.write_text(json.dumps(doc, indent=2))
    return path, before


def read_probe(catalog: str, seed: int, repeat: int) -> dict:
    """(In a fresh process) reading ``frames`` of the latest version against the same rows
    as one fresh Parquet file, and one random session's arrays."""
    import pyarrow.parquet as pq

    import graspcap.catalog as gc

    t = time.perf_counter()
    cat = gc.open(catalog)
    version = cat.latest_version()
    frames = cat.table("frames", version)
    first = time.perf_counter() - t
    fresh = Path(tempfile.mkdtemp(prefix="graspcap-scale-fresh-")) / "frames.parquet"
    pq.write_table(frames, fresh)
    cat_s, plain_s = [], []
    for _ in range(repeat):  # alternated: the machine's load hits both sides alike
        t = time.perf_counter()
        rows = gc.open(catalog).table("frames", version).num_rows
        cat_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        pq.read_table(fresh)
        plain_s.append(time.perf_counter() - t)
    delta = _delta_layer(cat, version, repeat)
    shutil.rmtree(fresh.parent)
    ok = [r["session_id"] for r in cat.table("sessions", version).to_pylist()
          if r["contact_digest"] and r["hand_mesh_digest"] and r["object_mesh_digest"]]
    sid = random.Random(seed).choice(sorted(ok))
    arrays_s = []
    for _ in range(repeat + 1):
        t = time.perf_counter()
        cat.contactmap(sid, version)
        cat.hand_mesh(sid, version)
        cat.object_mesh(session_id=sid, version=version)
        arrays_s.append(time.perf_counter() - t)
    return {**_frames_log(Path(cat.layout.table("frames"))), **delta,
            "frames_rows": rows, "frames_first_s": first,
            "frames_s": statistics.median(cat_s), "frames_fresh_s": statistics.median(plain_s),
            "frames_ratio": statistics.median(cat_s) / statistics.median(plain_s),
            "frames_parquet_files": len(cat.files("frames", version)),
            "session": sid, "arrays_first_ms": arrays_s[0] * 1000,
            "arrays_ms": statistics.median(arrays_s[1:]) * 1000}


def _delta_layer(cat, version: int, repeat: int) -> dict:
    """The ``frames`` read at the Delta layer (open the table at its pinned Delta version, list
    its files, read them) against the same rows written as a new Delta table in one commit
    (what a compacted or freshly built table holds): the files and the log replay, without the
    catalog's ``versions`` lookup, which both sides of a catalog read pay."""
    try:
        import pyarrow.parquet as pq
        from deltalake import DeltaTable, write_deltalake

        uri = str(cat.layout.table("frames"))
        pinned = cat._pinned(version)["frames"]
        raw = pq.read_table(DeltaTable(uri, version=pinned).file_uris())
        fresh = Path(tempfile.mkdtemp(prefix="graspcap-scale-delta-"))
        write_deltalake(str(fresh), raw)
        mine, theirs = [], []
        for _ in range(repeat):
            t = time.perf_counter()
            pq.read_table(DeltaTable(uri, version=pinned).file_uris())
            mine.append(time.perf_counter() - t)
            t = time.perf_counter()
            pq.read_table(DeltaTable(str(fresh)).file_uris())
            theirs.append(time.perf_counter() - t)
        shutil.rmtree(fresh)
        return {"frames_delta_s": statistics.median(mine),
                "frames_delta_fresh_s": statistics.median(theirs),
                "frames_delta_ratio": statistics.median(mine) / statistics.median(theirs),
                "frames_delta_log_entries": pinned + 1}
    except Exception as exc:  # noqa: BLE001 - a bench's extra figure never stops the run
        return {"frames_delta_error": f"{type(exc).__name__}: {exc}"}


def _frames_log(table: Path) -> dict:
    """Bytes and rows each commit of the ``frames`` Delta table added (its log's ``add``
    actions): what a build that changes one session writes."""
    added = []
    try:
        for entry in sorted((table / "_delta_log").glob("*.json")):
            size = rows = 0
            for line in entry.read_text().splitlines():
                action = json.loads(line) if line.strip() else {}
                if "add" in action:
                    size += action["add"].get("size", 0)
                    stats = action["add"].get("stats")
                    rows += json.loads(stats).get("numRecords", 0) if stats else 0
            added.append((size, rows))
    except (OSError, ValueError) as exc:
        return {"frames_log_error": str(exc)}
    later = added[2:]  # after the table's creation and the cold build's commit
    return {"frames_commits": len(added), "frames_commit_rows": [a[1] for a in added],
            "frames_commit_bytes": [a[0] for a in added],
            "frames_cold_commit_mb": added[1][0] / 1e6 if len(added) > 1 else None,
            "frames_later_commit_mb_median":
                statistics.median(a[0] for a in later) / 1e6 if later else None,
            "frames_later_commit_rows_median":
                statistics.median(a[1] for a in later) if later else None}


def generate_pool(pool: Path, n: int, profile: str, frames: int, seed: int) -> list[Path]:
    """``n`` sessions under ``pool`` (kept between runs: only missing ones are made); seeds
    the rig cannot stage are skipped."""
    from graspcap.synth import config_for, generate_session
    from graspcap.tasks.core.errors import StageError

    pool.mkdir(parents=True, exist_ok=True)
    index = pool / "index.json"
    made = json.loads(index.read_text()) if index.exists() else {
        "profile": profile, "frames": frames, "seed": seed, "sessions": [], "next": 0}
    if (made["profile"], made["frames"], made["seed"]) != (profile, frames, seed):
        raise SystemExit(f"{pool} holds sessions of another profile/frames/seed; use --out")
    cfg = config_for(profile, frames)
    t = time.perf_counter()
    while len(made["sessions"]) < n:
        i = made["next"]
        made["next"] += 1
        try:
            d = generate_session(pool / "sessions", [seed, i], cfg)
            made["sessions"].append(str(d))
        except StageError:
            continue
        index.write_text(json.dumps(made))
    if time.perf_counter() - t > 1:
        print(f"  synthesized up to {n} sessions in {time.perf_counter() - t:.0f} s", flush=True)
    return [Path(s) for s in made["sessions"][:n]]


def measure_size(n: int, sessions: list[Path], base: Path, previous: Path | None,
                 previous_cold: float | None, args, incremental: int) -> dict:
    """Every step of the module docstring for the first ``n`` of ``sessions``."""
    catalog = base / f"catalog-{n}"
    snapshot = base / f"cold-{n}"
    log = base / f"builds-{n}.log"
    shutil.rmtree(catalog, ignore_errors=True)
    grown = previous is not None
    if grown:
        shutil.copytree(previous, catalog, symlinks=True)
    flags = ["--catalog", str(catalog), "--preset", args.preset,
             *(["--dask", args.dask] if args.dask else [])]
    roots = [str(s) for s in sessions[:n]]
    out: dict = {"n": n, "grown_from": previous.name if grown else None}

    def build(name: str, extra_roots: list[str] = (), plan: bool = False) -> dict:
        m = run_build([*roots, *extra_roots, *flags, *(["--plan"] if plan else [])], log)
        if not plan:
            after_build(catalog, m)
        out[name] = m
        print(f"  N={n} {name}: {m['wall_s']:.1f} s wall, {m['cpu_s']:.1f} s CPU, "
              f"build RSS {m['build_rss_mb']:.0f} MB"
              + ("" if plan else f", ran {m['ran']}, version {m['version']}, "
                 f"failed {m['failed']}"), flush=True)
        return m

    cold = build("cold")
    out["cold_total_s"] = cold["wall_s"] + (previous_cold or 0.0) if grown else cold["wall_s"]
    out["cold_total_cpu_s"] = cold["cpu_s"]
    if args.grow:
        shutil.rmtree(snapshot, ignore_errors=True)
        shutil.copytree(catalog, snapshot, symlinks=True)
    build("unchanged")
    rng = random.Random(args.seed * 1000 + n)
    restore: dict[Path, bytes] = {}
    try:
        victim = Path(rng.choice(roots))
        path, before = change_depth_pixel(victim)
        restore.setdefault(path, before)
        build("plan_one_changed", plan=True)
        build("one_changed")
        build("arrivals", [str(s) for s in sessions[n:n + args.arrivals]])
        roots += [str(s) for s in sessions[n:n + args.arrivals]]
        walls = []
        for k in range(incremental):
            victim = Path(rng.choice(roots))
            if args.change == "label":
                path, before = change_label(victim, k)
            else:
                path, before = change_depth_pixel(victim)
            restore.setdefault(path, before)
            m = run_build([*roots, *flags], log)
            after_build(catalog, m)
            walls.append(m)
        if walls:
            out["incremental"] = {
                "builds": len(walls),
                "wall_s_median": statistics.median(w["wall_s"] for w in walls),
                "wall_s_max": max(w["wall_s"] for w in walls),
                "wall_s_last": walls[-1]["wall_s"],
                "cpu_s_median": statistics.median(w["cpu_s"] for w in walls),
                "build_rss_mb_max": max(w["build_rss_mb"] for w in walls),
                "last": walls[-1]}
            print(f"  N={n} {len(walls)} incremental builds: median "
                  f"{out['incremental']['wall_s_median']:.1f} s, last "
                  f"{walls[-1]['wall_s']:.1f} s, frames files {walls[-1]['frames_files']}",
                  flush=True)
    finally:
        for path, before in restore.items():
            path.write_bytes(before)
    probe = subprocess.run([sys.executable, __file__, PROBE, str(catalog), "--seed",
                            str(args.seed), "--repeat", str(args.read_repeat)],
                           capture_output=True, text=True, check=True)
    out["reads"] = json.loads(probe.stdout.strip().splitlines()[-1])
    r = out["reads"]
    print(f"  N={n} reads: frames {r['frames_rows']} rows {r['frames_s']:.3f} s vs fresh "
          f"{r['frames_fresh_s']:.3f} s (ratio {r['frames_ratio']:.2f}, "
          f"{r['frames_parquet_files']} files), arrays {r['arrays_ms']:.1f} ms "
          f"(first {r['arrays_first_ms']:.1f} ms)", flush=True)
    if not args.keep:
        shutil.rmtree(catalog, ignore_errors=True)
    return out


ROWS = [  # (label, how to get it from a size's result)
    ("cold build wall, s", lambda r: r["cold_total_s"]),
    ("cold build CPU, s", lambda r: r["cold_cpu_total_s"]),
    ("unchanged rebuild wall, s", lambda r: r["unchanged"]["wall_s"]),
    ("unchanged rebuild: the build flow's own seconds", lambda r: r["unchanged"]["flow_s"]),
    ("unchanged / cold", lambda r: r["unchanged"]["wall_s"] / r["cold_total_s"]),
    ("unchanged rebuild CPU, s", lambda r: r["unchanged"]["cpu_s"]),
    ("plan of one changed file, s", lambda r: r["plan_one_changed"]["wall_s"]),
    ("one changed file: build wall, s", lambda r: r["one_changed"]["wall_s"]),
    ("one changed file: build CPU, s", lambda r: r["one_changed"]["cpu_s"]),
    ("one changed file: the build flow's own seconds", lambda r: r["one_changed"]["flow_s"]),
    ("arrivals (--arrivals new sessions): build wall, s", lambda r: r["arrivals"]["wall_s"]),
    ("incremental build wall, median, s", lambda r: r["incremental"]["wall_s_median"]),
    ("incremental build wall, last, s", lambda r: r["incremental"]["wall_s_last"]),
    ("peak RSS build process (cold), MB", lambda r: r["cold"]["build_rss_mb"]),
    ("peak RSS build process (unchanged), MB", lambda r: r["unchanged"]["build_rss_mb"]),
    ("peak RSS build process (incremental, max), MB",
     lambda r: r["incremental"]["build_rss_mb_max"]),
    ("peak RSS other processes (cold), MB",
     lambda r: max((mb for _, mb in r["cold"]["other_rss_mb"]), default=0.0)),
    ("Prefect database after all builds, MB", lambda r: r["incremental"]["last"]["prefect_db_mb"]),
    ("catalog (without work area), MB", lambda r: r["incremental"]["last"]["catalog_mb"]),
    ("work area, MB", lambda r: r["incremental"]["last"]["work_mb"]),
    ("catalog versions after all builds", lambda r: r["incremental"]["last"]["version"]),
    ("frames Parquet files of the latest version", lambda r: r["reads"]["frames_parquet_files"]),
    ("read frames (latest), s", lambda r: r["reads"]["frames_s"]),
    ("read frames / same rows as one fresh Parquet file", lambda r: r["reads"]["frames_ratio"]),
    ("read frames at the Delta layer / same rows as a fresh Delta table",
     lambda r: r["reads"]["frames_delta_ratio"]),
    ("open a random session's arrays, ms", lambda r: r["reads"]["arrays_ms"]),
]


def growth_table(results: list[dict], target: int) -> str:
    """Each cost against N, its log-log slope, and a linear fit's value at ``target``."""
    import numpy as np

    cpu = 0.0
    for r in results:  # a grown cold build's CPU: the previous size's plus its own
        cpu = r["cold"]["cpu_s"] + (cpu if r.get("grown_from") else 0.0)
        r["cold_cpu_total_s"] = cpu
    ns = [r["n"] for r in results]
    extrapolate = max(ns) < target and len(ns) >= 2
    head = "| cost | " + " | ".join(f"N={n}" for n in ns) + " | growth exponent |" + (
        f" per added session (fit) | fit at N={target} |" if extrapolate else "")
    lines = [head, "|" + "---|" * (len(ns) + 2 + 2 * extrapolate)]
    for label, get in ROWS:
        try:
            values = [float(get(r)) for r in results]
        except (KeyError, TypeError, ZeroDivisionError):
            continue
        cells = [f"{v:.3g}" for v in values]
        slope = "" if len(ns) < 2 or min(values) <= 0 else \
            f"{np.log(values[-1] / values[0]) / np.log(ns[-1] / ns[0]):.2f}"
        row = f"| {label} | " + " | ".join(cells) + f" | {slope} |"
        if extrapolate:  # least squares a + b N; a falling fit is noise: say "flat"
            b, a = np.polyfit(ns, values, 1)
            row += (f" {b:.3g} | {a + b * target:.3g} |" if b > 0 else
                    f" {b:.3g} | flat (<= {max(values):.3g}) |")
        lines.append(row)
    return "\n".join(lines)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == PROBE:
        ap = argparse.ArgumentParser()
        ap.add_argument(PROBE)
        ap.add_argument("--seed", type=int, default=0)
        ap.add_argument("--repeat", type=int, default=5)
        a = ap.parse_args()
        print(json.dumps(read_probe(a.read_probe, a.seed, a.repeat)))
        return
    if len(sys.argv) > 1 and sys.argv[1] == "--table":  # runs' JSON files -> one table
        results = sorted((r for f in sys.argv[2:] for r in json.loads(Path(f).read_text())[
            "results"]), key=lambda r: r["n"])
        print(growth_table(results, 1000))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 300, 1000])
    ap.add_argument("--short", action="store_true",
                    help="make bench: --sizes 3 6 --arrivals 2 --incremental 3")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--profile", default="easy")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seed", type=int, default=10000)
    ap.add_argument("--arrivals", type=int, default=10)
    ap.add_argument("--incremental", type=int, nargs="+", default=[50],
                    help="incremental builds in a row, per size (the last value is used for "
                         "the remaining sizes)")
    ap.add_argument("--change", choices=["label", "depth"], default="label")
    ap.add_argument("--grow", action=argparse.BooleanOptionalAction, default=True,
                    help="start each size from the previous size's cold catalog (default)")
    ap.add_argument("--dask", default=None, help="passed to graspcap build (local:N|ADDRESS)")
    ap.add_argument("--read-repeat", type=int, default=5)
    ap.add_argument("--extrapolate", type=int, default=1000)
    ap.add_argument("--out", type=Path, default=None,
                    help="folder for the session pool, catalogs and logs (kept; default: a "
                         "new temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep each size's final catalog")
    ap.add_argument("--grow-from", type=Path, default=None, metavar="SNAPSHOT",
                    help="start the first size from this cold catalog of an earlier run "
                         "(its cold-N folder; kept with --keep) instead of building it cold")
    ap.add_argument("--grow-from-cold-s", type=float, default=None,
                    help="the cold wall seconds of --grow-from's size (from its scale.json)")
    args = ap.parse_args()
    # a SIGTERM unwinds like an exception, so the changed session files are put back
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if args.short:
        args.sizes, args.arrivals, args.incremental = [3, 6], 2, [3]
    sizes = sorted(args.sizes)
    base = args.out or Path(tempfile.mkdtemp(prefix="graspcap-scale-"))
    base.mkdir(parents=True, exist_ok=True)
    print(f"bench/scale.py: sizes {sizes}, {args.frames} frames, profile {args.profile}, "
          f"preset {args.preset}, {args.arrivals} arrivals, {args.incremental} incremental "
          f"builds ({args.change}), {'grown' if args.grow else 'fresh'} cold builds, "
          f"files under {base}", flush=True)
    sessions = generate_pool(base / "pool", sizes[-1] + args.arrivals, args.profile,
                             args.frames, args.seed)
    results: list[dict] = []
    previous, previous_cold = args.grow_from, args.grow_from_cold_s
    for i, n in enumerate(sizes):
        r = measure_size(n, sessions, base, previous if args.grow else None, previous_cold,
                         args, args.incremental[min(i, len(args.incremental) - 1)])
        results.append(r)
        previous, previous_cold = base / f"cold-{n}", r["cold_total_s"]
        (base / f"scale-{'-'.join(map(str, sizes))}.json").write_text(json.dumps({"args": {
            k: str(v) for k, v in vars(args).items()}, "results": results}, indent=1))
    if args.grow and not args.keep:
        for n in sizes:
            shutil.rmtree(base / f"cold-{n}", ignore_errors=True)
    print()
    print(growth_table(results, args.extrapolate))
    print(f"\n(all numbers: {base}/scale-{'-'.join(map(str, sizes))}.json; build logs "
          f"{base}/builds-N.log)")


if __name__ == "__main__":
    main()
