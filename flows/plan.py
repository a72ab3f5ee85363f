"""``graspcap build --plan``: what a build would run and why, running and writing nothing.

For every session under the roots and every stage, in DAG order, the plan computes the
stage's cache key as a build would (the same :func:`~graspcap.flows.cached.cache_key`) from
the upstream results the work area holds, and says:

- ``cached``: the work area holds a usable result under that key (no stage body runs);
- ``fails again``: it holds a deterministic failure under that key (replayed without running;
  ``--retry-failed`` runs it);
- ``not ready``: an upstream stage fails again, so this one does not run;
- ``run``: and why (:data:`~graspcap.flows.cached.REASONS`), from a diff of the key's parts
  against the key manifest of the stage's latest run for that session: new session, changed
  input file (role: file), changed config (field), changed code (module), changed library
  (name: old -> new), changed stage version, not run before (an upstream failed until now),
  upstream changed (which stages), failed last time, stored result unusable (why), stored
  result gone;
- ``runs if upstream changes``: an upstream would run and nothing of the stage's own parts
  changed. Its key is not known before that upstream has run (an unchanged upstream result is
  a cache hit downstream: early cutoff), so whether it runs is decided then. A stage with an
  upstream that would run *and* a change of its own is ``run``, with both reasons.

So the ``run`` lines are exactly the stages that will run; the conditional ones are the most
that may run besides. ``load_session``'s result is in no downstream key (a stage takes the
files of its roles and its manifest fields itself), so a stage whose only running upstream is
``load_session`` is planned from its own key.

No catalog is opened or created, no Prefect run is started and the work area is opened to read
only (:meth:`WorkArea.reader`).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from graspcap.flows.cached import (
    REASONS,
    cache_key,
    diff_parts,
    first_run,
    key_parts,
    run_reasons,
    session_id_of,
)
from graspcap.flows.session_roles import SessionRoles
from graspcap.flows.workarea import ResultRef, WorkArea
from graspcap.tasks.core.config import StageConfig

RUN = "run"
IF_UPSTREAM = "runs if upstream changes"
"""A stage whose own key parts are unchanged but which waits on an upstream that runs: it runs
only when that upstream's new result differs from the one its key holds (early cutoff), which
no plan can know before the upstream has run (terraform's "known after apply")."""


@dataclass(frozen=True)
class StagePlan:
    """What a build would do with one stage of one session."""

    session_id: str
    stage: str
    action: str
    """``cached``, ``run``, ``runs if upstream changes``, ``fails again`` or ``not ready``."""
    reasons: tuple[tuple[str, str], ...] = field(default=())
    """(reason, detail) pairs for ``run`` and ``runs if upstream changes`` (a reason from
    ``REASONS``)."""


def plan_session(session_dir: Path, session_id: str, configs: Mapping[str, StageConfig],
                 work: WorkArea, retry_failed: bool = False) -> list[StagePlan]:
    """The plan of one session's stages, in DAG order (module docstring)."""
    from graspcap.tasks.pipeline import STAGES

    refs: dict[str, ResultRef] = {}
    action: dict[str, str] = {}
    out: list[StagePlan] = []
    role_digests = SessionRoles(work, session_dir).digests
    for name, stage in STAGES.items():
        ups = stage.upstream
        if any(action[u] in ("fails again", "not ready") for u in ups):
            action[name] = "not ready"
            out.append(StagePlan(session_id, name, "not ready"))
            continue
        # load_session's result is not in its downstream keys (they take their roles and
        # manifest fields themselves): a stage whose only running upstream is load_session
        # knows its key now
        running = [u for u in stage.key_upstream if action[u] in (RUN, IF_UPSTREAM)]
        if running:
            own: list[tuple[str, str]] = []
            parts = key_parts(name, session_dir, configs[name], refs, work)
            latest = work.latest_manifest(name, session_id)
            if latest is None:
                own.append(first_run(work, session_id))
            elif parts is not None:
                own += diff_parts(latest.get("parts") or {}, parts)
            action[name] = RUN if own else IF_UPSTREAM
            out.append(StagePlan(session_id, name, action[name],
                                 (*own, ("upstream changed", ", ".join(running)))))
            continue
        held = {u: refs[u] for u in ups if u in refs}
        key = cache_key(name, session_dir, configs[name], held, work, role_digests)
        ref = work.lookup(name, key) if key is not None else None
        if ref is not None:
            refs[name] = ref
            action[name] = "cached"
            out.append(StagePlan(session_id, name, "cached"))
            continue
        failure = work.lookup_failure(name, key) if key is not None else None
        if failure is not None and not retry_failed:
            action[name] = "fails again"
            out.append(StagePlan(session_id, name, "fails again",
                                 (("failed last time", str(failure.get("reason", ""))),)))
            continue
        parts = (key_parts(name, session_dir, configs[name], held, work)
                 if key is not None else None)
        action[name] = RUN
        out.append(StagePlan(session_id, name, RUN, tuple(
            run_reasons(work, name, session_id, key, parts, replay_failures=not retry_failed))))
    return out


def plan_build(roots: Sequence[Path | str], catalog: Path | str, preset: str = "default",
               overrides: Mapping[str, Any] | None = None, retry_failed: bool = False,
               work_root: Path | str | None = None) -> list[StagePlan]:
    """The plan of a build of ``roots`` into ``catalog`` (module docstring); writes nothing.
    ``retry_failed`` plans as ``--retry-failed`` would run: remembered failures run again (the
    build's choice of sessions from the last build's record is not applied)."""
    from graspcap.flows.build import resolve_configs
    from graspcap.tasks.session.discover import discover

    work = WorkArea.reader(work_root or Path(catalog).expanduser().resolve() / "work")
    configs = resolve_configs(preset, overrides)
    out: list[StagePlan] = []
    seen: set[str] = set()
    for d in discover([Path(r) for r in roots]).sessions:
        sid = session_id_of(d)
        if sid in seen:
            continue  # a duplicate id: the build reports it and builds the first folder
        seen.add(sid)
        out += plan_session(Path(d).resolve(), sid, configs, work, retry_failed)
    return out


def plan_text(plans: Sequence[StagePlan]) -> str:
    """The plan for a person: one line per stage that does anything but hit the cache, a
    line per session that is all cached, and a summary line counting each reason."""
    lines: list[str] = []
    by_session: dict[str, list[StagePlan]] = {}
    for p in plans:
        by_session.setdefault(p.session_id, []).append(p)
    for sid, stages in by_session.items():
        if all(p.action == "cached" for p in stages):
            lines.append(f"{sid}: all {len(stages)} stages cached")
            continue
        lines.append(f"{sid}:")
        for p in stages:
            why = "; ".join(f"{r} ({d})" if d else r for r, d in p.reasons)
            lines.append(f"  {p.stage:<20} {p.action}" + (f": {why}" if why else ""))
    lines.append(summary_line(plans))
    return "\n".join(lines)


def summary_line(plans: Sequence[StagePlan]) -> str:
    """``plan: N stages of S sessions: a cached, b run (reason: count, ...), ...``; "all
    cached" when nothing would run."""
    actions = Counter(p.action for p in plans)
    sessions = len({p.session_id for p in plans})
    if actions.get("cached", 0) == len(plans):
        return f"plan: all cached ({len(plans)} stages of {sessions} sessions); nothing runs"
    reasons = Counter(r for p in plans if p.action == RUN for r in {r for r, _ in p.reasons})
    counted = ", ".join(f"{r}: {reasons[r]}" for r in REASONS if reasons.get(r))
    parts = [f"{actions.get('cached', 0)} cached", f"{actions.get(RUN, 0)} run"
             + (f" ({counted})" if counted else "")]
    parts += [f"{actions[a]} {a}" for a in (IF_UPSTREAM, "fails again", "not ready")
              if actions.get(a)]
    return f"plan: {len(plans)} stages of {sessions} sessions: " + ", ".join(parts)


def run_plan(roots: Sequence[Path], catalog: Path, preset: str = "default",
             retry_failed: bool = False, settings: Sequence[str] = (),
             out: Any = None) -> int:
    """``graspcap build --plan``: print the plan; 0, or 2 (usage) for a wrong ``--set`` or
    no session under the roots."""
    import sys

    from graspcap.tasks.pipeline import settings_overrides

    out = out or sys.stdout
    try:
        overrides = settings_overrides(list(settings), preset)
    except ValueError as exc:
        print(f"graspcap build --plan: {exc}", file=sys.stderr)
        return 2
    plans = plan_build(roots, catalog, preset, overrides or None, retry_failed)
    if not plans:
        print(f"no session.json found under {' '.join(map(str, roots))}", file=sys.stderr)
        return 2
    print(plan_text(plans), file=out)
    return 0
