"""``graspcap build --verify N``: re-run N randomly chosen cached stages and compare.

A cache key that misses something (a data file the code reads that no role names, a library
outside ``COMPUTING_LIBRARIES``, a nondeterministic stage) serves a result the current code
would not compute. This check finds it: it picks ``N`` stages (seeded) among those the work
area holds for the sessions under the roots (a stage whose upstream stages are all cached:
their stored results are its inputs), runs each stage body on those inputs, in this process,
and compares the result with the stored one.

Comparison: equal pickles (same digest) match; otherwise the two results are compared
structurally (dataclass and pydantic fields, mappings, sequences), arrays and floats with
``numpy.allclose(rtol=RTOL, atol=ATOL)``: stages that run native thread pools (Open3D's
registration, GTSAM's solvers, the MediaPipe graph) may differ in the last bits of a float
between runs, which is no miss. Anything else (another shape, another integer, a field that
differs beyond the tolerance) is reported with the path of the first difference. Nothing is
written: the work area is opened read-only and no catalog is touched.
"""

from __future__ import annotations

import dataclasses
import hashlib
import pickle
import random
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.flows.cached import cache_key, session_id_of
from graspcap.flows.workarea import ResultRef, WorkArea

RTOL = 1e-6
ATOL = 1e-9
"""Tolerance for floats and float arrays (module docstring)."""


@dataclass(frozen=True)
class Verified:
    """One re-run cached stage: whether the current code computes the stored result."""

    session_id: str
    stage: str
    match: bool
    how: str
    """``identical`` (same bytes), ``within tolerance``, or where and how they differ."""


def difference(a: Any, b: Any, path: str = "result") -> str | None:
    """Where ``a`` and ``b`` differ beyond the float tolerance, or None."""
    if type(a) is not type(b):
        return f"{path}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, np.ndarray):
        if a.shape != b.shape or a.dtype != b.dtype:
            return f"{path}: array {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        if np.issubdtype(a.dtype, np.inexact):
            same = np.allclose(a, b, rtol=RTOL, atol=ATOL, equal_nan=True)
        else:
            same = np.array_equal(a, b)
        return None if same else f"{path}: arrays differ"
    if isinstance(a, float | np.floating):
        return None if np.isclose(a, b, rtol=RTOL, atol=ATOL, equal_nan=True) else (
            f"{path}: {a!r} != {b!r}")
    if dataclasses.is_dataclass(a):
        return _first(((f.name, getattr(a, f.name), getattr(b, f.name))
                       for f in dataclasses.fields(a)), path)
    if hasattr(type(a), "__pydantic_fields__"):
        return _first(((n, getattr(a, n), getattr(b, n)) for n in type(a).__pydantic_fields__),
                      path)
    if isinstance(a, Mapping):
        if set(a) != set(b):
            return f"{path}: keys {sorted(map(str, a))} != {sorted(map(str, b))}"
        return _first(((str(k), a[k], b[k]) for k in a), path)
    if isinstance(a, list | tuple):
        if len(a) != len(b):
            return f"{path}: length {len(a)} != {len(b)}"
        return _first(((f"[{i}]", x, y) for i, (x, y) in enumerate(zip(a, b, strict=True))),
                      path)
    try:
        return None if a == b else f"{path}: {a!r} != {b!r}"[:300]
    except Exception:  # noqa: BLE001 - an object without a usable ==: compare its pickle
        return None if pickle.dumps(a) == pickle.dumps(b) else f"{path}: differs"


def _first(items, path: str) -> str | None:
    for name, x, y in items:
        sep = "" if name.startswith("[") else "."
        if (found := difference(x, y, f"{path}{sep}{name}")) is not None:
            return found
    return None


def cached_stages(session_dir: Path, configs: Mapping, work: WorkArea
                  ) -> dict[str, ResultRef]:
    """The refs of the stages of one session the work area holds under their current keys,
    in DAG order (a stage counts only when its upstream stages do)."""
    from graspcap.tasks.pipeline import STAGES

    refs: dict[str, ResultRef] = {}
    for name, stage in STAGES.items():
        if not all(u in refs for u in stage.upstream):
            continue
        key = cache_key(name, session_dir, configs[name], {u: refs[u] for u in stage.upstream},
                        work)
        if key is not None and (ref := work.lookup(name, key)) is not None:
            refs[name] = ref
    return refs


def verify_build(roots: Sequence[Path | str], catalog: Path | str, count: int,
                 preset: str = "default", overrides: Mapping[str, Any] | None = None,
                 seed: int = 0, stages: Sequence[str] | None = None,
                 work_root: Path | str | None = None) -> list[Verified]:
    """Re-run ``count`` cached stages chosen with ``seed`` (among ``stages`` when given) and
    compare each with its stored result (module docstring); writes nothing."""
    from graspcap.flows.build import resolve_configs
    from graspcap.tasks.pipeline import STAGES, run_stage
    from graspcap.tasks.session.discover import discover

    work = WorkArea.reader(work_root or Path(catalog).expanduser().resolve() / "work")
    configs = resolve_configs(preset, overrides)
    candidates: list[tuple[Path, str, str, dict[str, ResultRef]]] = []
    seen: set[str] = set()
    for d in discover([Path(r) for r in roots]).sessions:
        sid = session_id_of(d)
        if sid in seen:
            continue
        seen.add(sid)
        refs = cached_stages(Path(d).resolve(), configs, work)
        candidates += [(Path(d).resolve(), sid, name, refs) for name in refs
                       if stages is None or name in stages]
    chosen = random.Random(seed).sample(candidates, min(count, len(candidates)))
    out = []
    for session_dir, sid, name, refs in chosen:
        stage = STAGES[name]
        upstream = {u: WorkArea.load(refs[u]) for u in stage.upstream}
        fresh = run_stage(stage, session_dir, configs[name], upstream)
        stored = WorkArea.load(refs[name])
        data = pickle.dumps(fresh, protocol=5)
        if hashlib.sha256(data).hexdigest() == refs[name].digest:
            out.append(Verified(sid, name, True, "identical"))
        elif (diff := difference(stored, fresh)) is None:
            out.append(Verified(sid, name, True, "within tolerance"))
        else:
            out.append(Verified(sid, name, False, diff))
    return out


def verify_text(results: Sequence[Verified]) -> str:
    lines = [f"{v.session_id} {v.stage}: {'ok' if v.match else 'MISMATCH'} ({v.how})"
             for v in results]
    bad = sum(not v.match for v in results)
    lines.append(f"verify: {len(results)} cached stage(s) re-run, {bad} mismatch(es)"
                 + ("; the cache key misses something these stages depend on" if bad else ""))
    return "\n".join(lines)


def run_verify(roots: Sequence[Path], catalog: Path, count: int, preset: str = "default",
               settings: Sequence[str] = (), out: Any = None) -> int:
    """``graspcap build --verify N``: 0 when every re-run stage matches, 1 on a mismatch,
    2 for a usage error (a wrong ``--set``, N < 1)."""
    import sys

    from graspcap.tasks.pipeline import settings_overrides

    out = out or sys.stdout
    if count < 1:
        print("graspcap build --verify: N must be at least 1", file=sys.stderr)
        return 2
    try:
        overrides = settings_overrides(list(settings), preset)
    except ValueError as exc:
        print(f"graspcap build --verify: {exc}", file=sys.stderr)
        return 2
    results = verify_build(roots, catalog, count, preset, overrides or None)
    print(verify_text(results), file=out)
    return 1 if any(not v.match for v in results) else 0
