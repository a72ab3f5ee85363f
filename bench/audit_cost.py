"""The write-audit-publish audit's cost against the catalog's size (issue 21; docs/benchmarks.md).

    OMP_NUM_THREADS=1 .venv/bin/python bench/audit_cost.py [--sizes 300 1000 3000] [--frames 30]

For each size N: a new catalog gets N sessions of ``--frames`` frames rows each
(``tests/catalog_factory.make_build``: fake rows, no pipeline) in commits of ``--batch``
sessions (no audit), then ``--changes`` commits of one session each with the default gates
(``AuditGates()``): its rows rewritten with a new input digest, as a build that re-ran one
session. Times ``audit.audit_version`` of the last of them against the published version
before it (median of ``--repeat``, in this process, after one untimed call) and the whole
commit of it; prints the audit's verdict and what it measured, so runs of two commits can be
compared (the verdicts must match). ``--compare REV`` also loads ``catalog/audit.py`` as it was
at git revision REV and times its ``audit_version`` on the same catalog, the two taking turns
in each repetition (a shared machine's load weighs on both alike), and checks the two give the
same verdict, reasons and measurements (less what only the newer one measures).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import graspcap.catalog as gc  # noqa: E402
from graspcap.catalog.audit import AuditGates, audit_version  # noqa: E402
from graspcap.catalog.delta import table_versions_of  # noqa: E402
from tests.catalog_factory import make_build  # noqa: E402

OBJECTS = ("mug", "drill", "bowl")


def session_ids(n: int) -> list[str]:
    return [f"p{i // 300:02d}-{OBJECTS[i % 3]}-use-{i % 300 // 3:03d}" for i in range(n)]


def old_audit(rev: str):
    """``catalog/audit.py`` at git revision ``rev``, as a module of its own."""
    here = Path(__file__).resolve().parents[1]
    text = subprocess.run(["git", "show", f"{rev}:catalog/audit.py"], cwd=here, check=True,
                          capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "audit_old.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("graspcap_audit_old", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # (its dataclasses look themselves up there)
    spec.loader.exec_module(module)
    return module


NEW_KEYS = ("duplicate_frame_keys", "frames_read")
"""What only the newer audit measures (left out of the comparison)."""


def one_size(root: Path, n: int, frames: int, batch: int, changes: int, repeat: int,
             old=None) -> dict:
    cat = gc.open(root, create=True)
    ids = session_ids(n)
    t0 = time.perf_counter()
    for k in range(0, n, batch):
        cat.commit(make_build(ids[k:k + batch], seed=k, build_id=f"b{k}", frames=frames))
    fill_s = time.perf_counter() - t0
    gates = AuditGates()
    commit_s = []
    for c in range(changes):
        build = make_build([ids[(7 * c) % n]], seed=10_000 + c, build_id=f"c{c}", frames=frames)
        t0 = time.perf_counter()
        cat.commit(build, gates)
        commit_s.append(time.perf_counter() - t0)
    rows = {r["version"]: r for r in cat.versions().to_pylist()}
    last = max(rows)
    pins, before = table_versions_of(rows[last]), table_versions_of(rows[last - 1])
    audit = audit_version(cat.layout, pins, (last - 1, before), gates)  # warm
    times, old_times, same = [], [], None
    if old is not None:
        was = old.audit_version(cat.layout, pins, (last - 1, before), old.AuditGates())
        now = {k: v for k, v in audit.measured.items() if k not in NEW_KEYS}
        same = (was.passed, was.reasons, was.measured) == (audit.passed, audit.reasons, now)
    for _ in range(repeat):
        if old is not None:
            t0 = time.perf_counter()
            old.audit_version(cat.layout, pins, (last - 1, before), old.AuditGates())
            old_times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        again = audit_version(cat.layout, pins, (last - 1, before), gates)
        times.append(time.perf_counter() - t0)
    assert again == audit
    stored = cat.audit(last)
    frames_files = len(cat.files("frames"))
    return {"sessions": n, "frames_rows": n * frames, "frames_files": frames_files,
            "fill_s": round(fill_s, 1), "commit_s": round(statistics.median(commit_s), 3),
            "audit_s": round(statistics.median(times), 4),
            "audit_min_s": round(min(times), 4), "passed": audit.passed,
            "old_audit_s": round(statistics.median(old_times), 4) if old_times else None,
            "same_as_old": same,
            "reasons": audit.reasons, "measured": audit.measured,
            "stored_matches": stored is not None and stored["passed"] == audit.passed
            and stored["reasons"] == audit.reasons}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[300, 1000, 3000])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--batch", type=int, default=100)
    ap.add_argument("--changes", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--compare", metavar="REV", help="time catalog/audit.py of git REV too")
    args = ap.parse_args()
    old = old_audit(args.compare) if args.compare else None
    results = []
    for n in args.sizes:
        with tempfile.TemporaryDirectory(prefix="audit-cost-") as tmp:
            r = one_size(Path(tmp) / "cat", n, args.frames, args.batch, args.changes,
                         args.repeat, old)
        results.append(r)
        print(f"N={n:5d} frames rows {r['frames_rows']:7d} files {r['frames_files']:3d}  "
              f"audit {r['audit_s']*1e3:8.1f} ms (min {r['audit_min_s']*1e3:.1f}; read "
              f"{r['measured']['frames_read']}; before: every row's key)  commit "
              f"{r['commit_s']:.2f} s  passed {r['passed']} {r['reasons']}"
              + (f"  | {args.compare}: audit {r['old_audit_s']*1e3:8.1f} ms, same verdict and "
                 f"measurements: {r['same_as_old']}" if old else ""), flush=True)
    if args.out:
        args.out.write_text(json.dumps(results, indent=1, default=str))
    print(json.dumps([{k: r[k] for k in ("sessions", "measured")} for r in results],
                     default=str)[:2000])


if __name__ == "__main__":
    main()
