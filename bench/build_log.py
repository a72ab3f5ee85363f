"""Bytes of a ``builds.jsonl`` record against the number of sessions N (no stage runs).

    .venv/bin/python bench/build_log.py <catalog>/work/builds.jsonl --sizes 16 100 1000

Takes the last record of a real build log as the template (its first session's entry in
``sessions`` and in ``keys``, its parameters), makes N sessions of it, and writes through
``flows/build_log.append_build`` into a fresh work area: a cold build, an unchanged rebuild,
a rebuild with one session's keys changed, then ``--incremental`` such one-session builds.
Prints per N each record's bytes, what the old format (every session's keys) would have
taken, the snapshot's bytes, and the time ``session_keys`` takes with and without it.
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
import time
from pathlib import Path

from graspcap.flows.build_log import KEYS_SNAPSHOT, append_build, session_keys
from graspcap.flows.workarea import BUILDS_LOG


def _record(template: dict, n: int, unchanged: bool) -> tuple[dict, dict]:
    """A record of N sessions made of the template's first, and their keys."""
    entry = template["sessions"][0]
    keys0 = next(iter(template["keys"].values()))
    sessions, keys = [], {}
    for i in range(n):
        sid = f"{entry['session_id']}-{i:05d}"
        e = copy.deepcopy(entry) | {"session_id": sid, "session_dir": f"{entry['session_dir']}"
                                    f"-{i:05d}"}
        if unchanged:
            e |= {"outcome": "unchanged", "cached": e["cached"] + e["ran"], "ran": []}
        sessions.append(e)
        keys[sid] = {st: f"{i:05d}{k[5:]}" for st, k in keys0.items()}
    ids = [s["session_id"] for s in sessions]
    summary = {"added": [], "changed": [], "failed": {}, "unchanged": ids} if unchanged \
        else {"added": ids, "changed": [], "failed": {}, "unchanged": []}
    rec = {k: v for k, v in template.items() if k != "keys"} | {
        "sessions": sessions, "summary": summary}
    return rec, keys


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("template", type=Path, help="a builds.jsonl (its last record is used)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 100, 1000])
    ap.add_argument("--incremental", type=int, default=50)
    args = ap.parse_args()
    template = json.loads(args.template.read_text().splitlines()[-1])
    print("N | cold | unchanged rebuild | one changed | old format unchanged | "
          f"log after {args.incremental} one-session builds | old format | snapshot | "
          "read keys (snapshot / whole log), ms")
    for n in args.sizes:
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            cold, keys = _record(template, n, unchanged=False)
            append_build(work, {**cold, "build_id": "cold"}, keys)
            same, _ = _record(template, n, unchanged=True)
            old_unchanged = len(json.dumps({**same, "keys": keys}, sort_keys=True)) + 1
            old_total = (log := work / BUILDS_LOG).stat().st_size
            sizes = []
            for b in range(args.incremental + 1):
                if b:
                    first = next(iter(keys))
                    keys = {**keys, first: {st: f"{b:05d}{k[5:]}"
                                            for st, k in keys[first].items()}}
                before = log.stat().st_size
                append_build(work, {**same, "build_id": f"b{b}"}, keys)
                sizes.append(log.stat().st_size - before)
                old_total += old_unchanged
            snap_bytes = (work / KEYS_SNAPSHOT).stat().st_size
            t0 = time.perf_counter()
            got, _ = session_keys(work)
            t_snap = time.perf_counter() - t0
            (work / KEYS_SNAPSHOT).unlink()
            t0 = time.perf_counter()
            assert session_keys(work)[0] == got == keys
            t_log = time.perf_counter() - t0
            cold_bytes = old_total - old_unchanged * (args.incremental + 1)
            print(f"{n} | {cold_bytes:,} | {sizes[0]:,} | {sizes[1]:,} | {old_unchanged:,} | "
                  f"{log.stat().st_size:,} | {old_total:,} | "
                  f"{snap_bytes:,} | "
                  f"{t_snap * 1e3:.0f} / {t_log * 1e3:.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
