"""Bytes of a ``builds.jsonl`` record against the number of sessions N (no stage runs).

    .venv/bin/python bench/build_log.py <catalog>/work/builds.jsonl --sizes 16 100 1000

Takes the last record of a real build log as the template (its first session's entry in
``sessions`` and in ``keys``, its parameters, seconds and publication), makes N sessions of
it, turns them into the record ``BuildReport.record()`` writes (so the bench measures the
record format of the code it runs) and appends it through ``flows/build_log.append_build``
into a fresh work area: a cold build (every session added), an unchanged rebuild, a rebuild
with one session changed (its stages ran, its keys new), then ``--incremental`` such
one-session builds. Prints per N each record's bytes, the log's, the snapshot's, and the time
``session_keys`` takes with and without the snapshot.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from graspcap.flows.build_log import KEYS_SNAPSHOT, append_build, session_keys
from graspcap.flows.report import BuildReport, Outcome, SessionReport
from graspcap.flows.workarea import BUILDS_LOG


def _session(entry: dict, i: int, outcome: Outcome) -> SessionReport:
    """Session ``i`` made of the template's entry: every stage ran (added, changed) or hit
    the cache (unchanged)."""
    stages = tuple(entry["ran"]) + tuple(entry["cached"])
    ran = () if outcome == Outcome.UNCHANGED else stages
    return SessionReport(
        session_id=f"{entry['session_id']}-{i:05d}",
        session_dir=f"{entry['session_dir']}-{i:05d}", outcome=outcome,
        status=entry["status"], ran=ran, cached=tuple(s for s in stages if s not in ran),
        pictures=dict(entry.get("pictures") or {}))


def _record(template: dict, n: int, build_id: str, outcome: Outcome,
            changed: int | None = None) -> dict:
    """The record of a build of N sessions made of the template's first, each ``outcome``
    but session ``changed`` (changed)."""
    entry = template["sessions"][0]
    sessions = tuple(_session(entry, i, Outcome.CHANGED if i == changed else outcome)
                     for i in range(n))
    return BuildReport(build_id, template.get("catalog_version"),
                       template.get("previous_version"), sessions,
                       dict(template.get("seconds") or {}), dict(template["parameters"]),
                       template.get("report_page"), dict(template.get("publication") or {})
                       ).record()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("template", type=Path, help="a builds.jsonl (its last record is used)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[16, 100, 1000])
    ap.add_argument("--incremental", type=int, default=50)
    args = ap.parse_args()
    template = json.loads(args.template.read_text().splitlines()[-1])
    keys0 = next(iter(template["keys"].values())) if template.get("keys") else {"x": "0" * 64}
    print("N | cold | unchanged rebuild | one changed | "
          f"log after cold, unchanged and {args.incremental} one-session builds | snapshot | "
          "read keys (snapshot / whole log), ms")
    for n in args.sizes:
        with tempfile.TemporaryDirectory() as tmp:
            work, log = Path(tmp), Path(tmp) / BUILDS_LOG
            entry = template["sessions"][0]
            keys = {f"{entry['session_id']}-{i:05d}": {st: f"{i:05d}{k[5:]}"
                                                      for st, k in keys0.items()}
                    for i in range(n)}
            append_build(work, _record(template, n, "cold", Outcome.ADDED), keys)
            sizes = [log.stat().st_size]
            for b in range(args.incremental + 1):
                if b:
                    first = next(iter(keys))
                    keys = {**keys, first: {st: f"{b:05d}{k[5:]}"
                                            for st, k in keys[first].items()}}
                before = log.stat().st_size
                append_build(work, _record(template, n, f"b{b}", Outcome.UNCHANGED,
                                           changed=0 if b else None), keys)
                sizes.append(log.stat().st_size - before)
            snap_bytes = (work / KEYS_SNAPSHOT).stat().st_size
            t0 = time.perf_counter()
            got, _ = session_keys(work)
            t_snap = time.perf_counter() - t0
            (work / KEYS_SNAPSHOT).unlink()
            t0 = time.perf_counter()
            assert session_keys(work)[0] == got == keys
            t_log = time.perf_counter() - t0
            print(f"{n} | {sizes[0]:,} | {sizes[1]:,} | {sizes[2]:,} | "
                  f"{log.stat().st_size:,} | {snap_bytes:,} | "
                  f"{t_snap * 1e3:.0f} / {t_log * 1e3:.0f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
