"""A dataset build: every session's DAG in ONE Prefect flow run, one catalog version.

    report = build_dataset(["captures/"], "catalog/")

1. discover the sessions under the roots (``session.discover.discover``; folders beside them
   without ``session.json`` are named in the report, not skipped without a word);
2. submit every session's stage tasks into this one flow run (not a subflow per session:
   measured in ``docs/architecture.md``), so sessions run concurrently on the task runner;
3. wait for each task; a failed session never stops the others, and its downstream tasks
   do not run;
4. turn the results into catalog rows (``flows/rows.py``); a session whose stages all hit the
   cache and whose catalog row has the same input and config digests is ``unchanged``;
5. commit added, changed and failed sessions as one catalog version, with the build record
   (which stages ran or hit the cache, retries, failures, parameters, timings) in the
   ``builds`` table; with nothing to commit there is no new version, and the report says so;
6. write the build's report page, ``<catalog>/reports/<build_id>/index.html``
   (``catalog/report_page.py``), with each session's pictures, which step 4 stored by content
   under ``<catalog>/pictures/`` (named per session in the build record).

A session that fails keeps its previous good rows (the failure is in the build record);
without previous good rows it gets a ``status="failed"`` row with the reason. Nothing that
happens to one session loses the others: a failure assembling its rows, or rows the catalog
would refuse (its checks run per session before the commit), fails that session alone;
pictures that cannot be written are a note, a report page that cannot be written a warning.
A folder reusing another's ``session_id`` (sorted:
the first is built) is failed in the build record only. A failure of the build as a whole
(the catalog's lock, the disk) raises :class:`BuildFailed`; the work area keeps every stage
result for the next build. See ``docs/architecture.md``, "Build".
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
import subprocess
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from prefect import flow
from prefect.context import FlowRunContext
from prefect.futures import as_completed

import graspcap
import graspcap.catalog as gc
from graspcap.catalog.commit import mesh_group
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.validate import check_commit
from graspcap.flows.cached import reads_digest, session_files, session_id_of
from graspcap.flows.progress import ProgressFn, Tracker, reporting_to
from graspcap.flows.report import BuildFailed, BuildReport, Outcome, SessionReport
from graspcap.flows.retention import RunRetention, prune_flow_runs
from graspcap.flows.rows import (
    NEWEST_COLUMNS,
    failed_row,
    manifest_labels,
    predates_columns,
    session_rows,
)
from graspcap.flows.runtime import build_settings, task_runner, worker_api
from graspcap.flows.session import InSession, Settled, failure_text, submit_session
from graspcap.flows.workarea import ResultRef, WorkArea
from graspcap.schemas.tables import Status
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.session.discover import discover

BUILDS_LOG = "builds.jsonl"
OPTIMIZE_EVERY = 20
"""A build whose version number is a multiple of this compacts the catalog's tables
(``catalog.optimize``: one more version, same rows, fewer files); None or 0: never."""
__all__ = ["BuildFailed", "ProgressFn", "build_dataset", "build_flow"]


@functools.cache
def code_version() -> str:
    """graspcap's version and, in a git checkout, its revision."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5, cwd=Path(graspcap.__file__).parent)
        if rev.returncode == 0 and rev.stdout.strip():
            return f"{graspcap.__version__}+g{rev.stdout.strip()}"
    except OSError:
        pass
    return graspcap.__version__


def resolve_configs(preset: str, overrides: Mapping[str, Any] | None) -> dict[str, StageConfig]:
    """Every stage's config for ``preset``; ``overrides`` per stage: a config, or a dict of
    fields applied over the preset (validated: unknown fields are rejected)."""
    from graspcap.tasks.pipeline import STAGES, configs_for

    base = configs_for(preset)
    out = dict(base)
    for name, value in (overrides or {}).items():
        if name not in STAGES:
            raise KeyError(f"no such stage {name!r}; stages are {list(STAGES)}")
        out[name] = value if isinstance(value, StageConfig) else STAGES[name].config_type(
            **{**base[name].model_dump(), **dict(value)})
    return out


def configs_digest(configs: Mapping[str, StageConfig]) -> str:
    from graspcap.tasks.pipeline import STAGES

    text = json.dumps({n: [STAGES[n].version, c.canonical_json()] for n, c in configs.items()},
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def last_build_failures(cat: gc.Catalog, work: WorkArea) -> set[str]:
    """Sessions that failed in the last build (the work area's log, else the catalog); after a
    build that failed as a whole (nothing committed), every session of it."""
    log = work.root / BUILDS_LOG
    if log.exists():
        lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
        if lines:
            last = json.loads(lines[-1])
            if last.get("error"):
                return {s["session_id"] for s in last["sessions"]}
            return set(last["summary"]["failed"])
    last = _last_build_row(cat)
    if last is None:
        return set()
    failed = {f["session_id"] for f in last["sessions_failed"]}
    record = json.loads(last["parameters_json"]).get("report", {})
    return failed | set(record.get("summary", {}).get("failed", {}))


def _last_build_row(cat: gc.Catalog) -> dict | None:
    """The base version's (the newest not rejected: what a build writes on top of) newest
    builds row made by a build (a ``catalog remove`` version's row records no build's
    failures: the one before it does), None without one."""
    base = cat.base_version()
    if base is None:
        return None
    for row in cat.table("builds", base).sort_by("catalog_version").to_pylist()[::-1]:
        if json.loads(row["parameters_json"]).get("command") != "catalog remove":
            return row
    return None


def recorded_failures(cat: gc.Catalog) -> dict[str, str]:
    """Failed sessions and their errors in the catalog's latest build record."""
    last = _last_build_row(cat)
    if last is None:
        return {}
    failed = {f["session_id"]: f["error"] for f in last["sessions_failed"]}
    record = json.loads(last["parameters_json"]).get("report", {})
    return {**failed, **record.get("summary", {}).get("failed", {})}


def mesh_digest(mesh: Any, owner: str) -> str | None:
    """The catalog's content digest of a session's object mesh (None: none, or one the
    commit's checks refuse, which fails that session there)."""
    try:
        return None if mesh is None else mesh_group(mesh, owner)[0]
    except Exception:  # noqa: BLE001 - reported by the per-session checks below
        return None


def _shared_object_notes(built: Mapping[str, tuple[str, str | None]],
                         previous: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """A note for each session of ``built`` (``(object_id, mesh digest)`` by session id) whose
    ``object_id`` labels more than one object mesh once committed (``previous``: the latest
    version's rows). Allowed by the contract (a re-scanned object): each session keeps its
    own mesh and contact map, but a reader grouping by ``object_id`` should know."""
    latest = {sid: (r["object_id"], r["object_mesh_digest"]) for sid, r in previous.items()}
    latest.update(built)
    by_object: dict[str, dict[str, list[str]]] = {}
    for sid, (object_id, digest) in sorted(latest.items()):
        if digest:
            by_object.setdefault(object_id, {}).setdefault(digest, []).append(sid)
    notes = {}
    for object_id, meshes in by_object.items():
        if len(meshes) > 1:
            groups = "; ".join(f"{d[:12]}: {', '.join(s)}" for d, s in meshes.items())
            for sid, (label, _) in built.items():
                if label == object_id:
                    notes[sid] = (f"object_id {object_id!r} labels {len(meshes)} different "
                                  f"object meshes ({groups}); each session keeps its own mesh "
                                  "and contact map")
    return notes


def _input_digest(work: WorkArea, session_dir: Path) -> str:
    from graspcap.tasks.pipeline import ALL_FILES

    files = session_files(session_dir)
    if files is None:
        return hashlib.sha256(b"unreadable manifest").hexdigest()
    try:
        return reads_digest(work, files, ALL_FILES)
    except OSError:
        return hashlib.sha256(b"missing files").hexdigest()


def _watch(submitted: Mapping[str, Mapping[str, Any]], session_ids: Mapping[str, str],
           log: logging.Logger | logging.LoggerAdapter | None = None) -> None:
    """Wait for every task, reporting each as it finishes (``flows/progress.py``) and in the
    run's log (``log``, INFO: one line per stage), the stages settled without a task first;
    ``session_ids`` by session directory, as in ``submitted``."""
    tracker = Tracker({session_ids[d]: len(f) for d, f in submitted.items()})

    def finished(sid: str, stage: str, state: str) -> None:
        event = tracker.finished(sid, stage, state)
        if log is not None:
            log.info("%s: %s %s (task %d/%d%s)", sid, stage, state, event.done, event.total,
                     f"; session {event.sessions_done}/{event.sessions_total} done"
                     if event.session_done else "")

    owner: dict[Any, list[tuple[str, str]]] = {}
    for d, futures in submitted.items():
        for name, fut in futures.items():
            if isinstance(fut, Settled):
                finished(session_ids[d], name, fut.state)
            else:
                key = fut.future if isinstance(fut, InSession) else fut
                owner.setdefault(key, []).append((session_ids[d], name))
    for fut in as_completed(list(owner)):
        fut.wait()  # sets the future's final state; reading .state before may ask the API
        state = fut.state
        value = state.result(raise_on_failure=False) if state.is_completed() else None
        for sid, name in owner[fut]:  # a session task (Dask) says how each stage ended
            inner = value.get(name) if isinstance(value, dict) else None
            finished(sid, name, inner.state if isinstance(inner, Settled)
                     else state.name or state.type.value)


def _outcome(fut: Any) -> tuple[str, Any, str | None]:
    """("completed", ref) / ("failed", exception) / ("not_run", None) of one stage, and
    Prefect's message; a :class:`Settled` stage says the same without a task run."""
    if isinstance(fut, Settled):
        if fut.state in ("Cached", "Completed"):
            return "completed", fut.ref, None
        if fut.state == "Failed":
            return "failed", fut.why or fut.error, None
        return "not_run", None, "NotReady: an upstream stage failed"
    if isinstance(fut, InSession):
        fut.future.wait()
        state = fut.future.state
        if state.is_completed():
            return _outcome(state.result()[fut.stage])
        exc = state.result(raise_on_failure=False)
        return "failed", failure_text(f"session task ({fut.stage})", exc, state.message), None
    fut.wait()
    state = fut.state
    if state.is_completed():
        return "completed", state.result(), None
    if state.is_failed() or state.is_crashed():
        return "failed", state.result(raise_on_failure=False), state.message
    return "not_run", None, f"{state.type.value}: {state.message}"


def _stage_outcomes(futures: Mapping[str, Any]):
    """(refs, ran, cached, not_run, error, failed_stage, notes) of one session's tasks; a
    failed aid stage (``pipeline.AID_STAGES``: pictures) is a note, not the session's error."""
    from graspcap.tasks.pipeline import AID_STAGES

    refs, ran, cached, not_run, notes = {}, [], [], [], []
    error = failed_stage = None
    for name, fut in futures.items():
        kind, value, message = _outcome(fut)
        if kind == "completed":
            refs[name] = value
            (cached if value.cached else ran).append(name)
        elif kind == "failed":
            why = value if isinstance(value, str) else failure_text(name, value, message)
            if name in AID_STAGES:
                notes.append(f"{why} (a QA aid: the session is committed without it)")
                continue
            failed_stage = failed_stage or name
            error = error or why
        else:  # NotReady (an upstream failed), Cancelled, ...
            not_run.append(name)
            if failed_stage is None:  # no failed upstream seen: say what Prefect said
                failed_stage = name
                error = f"{name} did not run ({message})"
    return refs, ran, cached, not_run, error, failed_stage, tuple(notes)


@flow(name="graspcap-build", persist_result=False, log_prints=False)
def build_flow(roots: list[str], catalog: str, preset: str = "default",
               overrides: dict[str, Any] | None = None, retry_failed: bool = False,
               work_root: str | None = None, build_id: str | None = None,
               gates: dict[str, Any] | None = None,
               optimize_every: int | None = OPTIMIZE_EVERY,
               retention: dict[str, Any] | None = None) -> BuildReport:
    """The whole build as one flow run (module docstring). ``gates``: the audit's
    (``catalog.audit.AuditGates`` fields); ``optimize_every``: see :data:`OPTIMIZE_EVERY`;
    ``retention``: Prefect's finished flow runs kept (``flows.retention.RunRetention``
    fields), pruned at the end of the build (a scheduled ``graspcap serve`` build too)."""
    from graspcap.tasks.pipeline import STAGES

    t0 = time.perf_counter()
    gates = gc.AuditGates(**(gates or {}))
    build_id = build_id or time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:8]
    cat = gc.open(catalog, create=True)
    work = WorkArea(work_root or cat.layout.root / "work")
    configs = resolve_configs(preset, overrides)
    cdigest = configs_digest(configs)
    version = code_version()
    found = discover([Path(r) for r in roots])
    dirs = found.sessions
    ids = [_session_id(d) for d in dirs]
    if retry_failed:
        wanted = last_build_failures(cat, work)
        keep = [i for i, sid in enumerate(ids) if sid in wanted]
        dirs, ids = [dirs[i] for i in keep], [ids[i] for i in keep]
    seen: dict[str, Path] = {}
    duplicate: dict[str, str] = {}
    for d, sid in zip(dirs, ids, strict=True):
        if sid in seen:
            duplicate[str(d)] = (
                f"session_id {sid!r} of {d} is also the id of {seen[sid]}, which comes first "
                "(sorted) and is the one built; session ids must be unique: rename one")
        seen.setdefault(sid, d)
    t_discover = time.perf_counter()

    # on Dask, one task per session (its stages plain calls in it): a dispatch costs ~0.4 s
    runner = getattr(FlowRunContext.get(), "task_runner", None)
    per_session = type(runner).__name__ == "DaskTaskRunner"
    submitted = {str(d): submit_session(d, configs, work, build_id, session_id=sid,
                                        replay_failures=not retry_failed, settle=True,
                                        per_session=per_session)
                 for d, sid in zip(dirs, ids, strict=True) if str(d) not in duplicate}
    log = _run_log()
    _watch(submitted, {str(d): sid for d, sid in zip(dirs, ids, strict=True)}, log)
    outcomes = {d: _stage_outcomes(f) for d, f in submitted.items()}
    # the stored result each stage used, by session (`catalog vacuum --work` keeps them)
    used = {sid: {name: ref.key for name, ref in outcomes[str(d)][0].items()}
            for d, sid in zip(dirs, ids, strict=True) if str(d) in outcomes}
    t_run = time.perf_counter()

    previous = cat.base_version()  # planned against what the commit writes on top of
    prev_rows = ({r["session_id"]: r for r in cat.table("sessions", previous).select(
        ["session_id", "status", "input_digest", "config_digest", "steady_from", "object_id",
         "object_mesh_digest", *NEWEST_COLUMNS]).to_pylist()}
        if previous is not None else {})
    attempts: dict[tuple[str, str], int] = {}
    for rec in work.executions(build_id):
        k = (rec["session_id"], rec["stage"])
        attempts[k] = attempts.get(k, 0) + 1
    by_index: dict[int, SessionReport] = {}  # reports in the order of dirs
    rows, frames, arrays, meshes = [], [], {}, {}
    recorded: dict[str, str] | None = None
    new_failures = False
    built = []  # sessions with rows, checked against the catalog's rules below

    def fail(i: int, d: Path, sid: str, error: str, stage: str | None, info: dict,
             common: dict, prev: dict | None, good_prev: bool,
             own_row: bool = True) -> None:
        """Report session ``i`` failed; give it a failed row unless it keeps its previous good
        rows, the catalog's latest build already records this failure (known: the same error on
        the same inputs and configs, replayed from the work area or run again, as a bad
        manifest's ``load_session`` is on every build), or the id's row is not its own
        (``own_row=False``: a duplicated id)."""
        nonlocal recorded, new_failures
        row = None
        if own_row and not good_prev:
            try:  # the failed row must not take the commit down either
                row = failed_row(d, sid, error, **common)
                check_commit(gc.BuildCommit(build=info_commit, sessions=[row], frames=[]))
            except Exception as exc:  # noqa: BLE001 - the reason goes into the report
                error, row = f"{error} (no failed row written: {exc})", None
        # a failure the catalog's latest build already records (same error, same inputs and
        # configs) needs no new version, whether replayed or run again
        if recorded is None:
            recorded = recorded_failures(cat) if previous is not None else {}
        known = (recorded.get(sid) == error
                 and (good_prev or row is None or (prev is not None and prev["input_digest"]
                                                   == common["input_digest"]
                                                   and prev["config_digest"] == cdigest)))
        new_failures |= not known
        if row is not None and not known:
            rows.append(row)
        by_index[i] = SessionReport(outcome=Outcome.FAILED, status=Status.FAILED.value,
                                   error=error, failed_stage=stage,
                                   kept_previous=good_prev, **info)

    info_commit = gc.BuildInfo(build_id, version, cdigest)
    for i, (d, sid) in enumerate(zip(dirs, ids, strict=True)):
        common = {"input_digest": hashlib.sha256(b"unreadable session").hexdigest(),
                  "code_version": version, "build_id": build_id, "config_digest": cdigest}
        if str(d) in duplicate:  # the id's row is the first folder's: a report, no row
            info = dict(session_id=sid, session_dir=str(d), not_run=tuple(STAGES))
            fail(i, d, sid, duplicate[str(d)], None, info, common, prev_rows.get(sid), False,
                 own_row=False)
            continue
        prev = prev_rows.get(sid)
        # previous rows with results (ok, flagged, or failed by QA), not a failed build's row
        good_prev = prev is not None and (prev["status"] != Status.FAILED
                                          or prev["steady_from"] is not None)
        refs, ran, cached, not_run, error, stage, notes = outcomes[str(d)]
        retries = {st: n - 1 for (s, st), n in attempts.items() if s == sid and n > 1}
        info = dict(session_id=sid, session_dir=str(d), ran=tuple(ran), cached=tuple(cached),
                    not_run=tuple(not_run), retries=retries, notes=notes)
        try:
            common["input_digest"] = _input_digest(work, d)
            if "pictures" in refs:
                info["pictures"], note = _store_pictures(cat.layout, sid, refs["pictures"])
                info["notes"] += note
            if error is not None:
                fail(i, d, sid, error, stage, info, common, prev, good_prev)
                continue
            # a row from before a column existed (a migrated catalog's) is rewritten from
            # cached results
            if (not ran and good_prev and prev["input_digest"] == common["input_digest"]
                    and prev["config_digest"] == cdigest and not predates_columns(prev)):
                by_index[i] = SessionReport(outcome=Outcome.UNCHANGED,
                                            status=prev["status"], **info)
                continue
            sr = session_rows({k: WorkArea.load(r) for k, r in refs.items()},
                              labels=manifest_labels(d), **common)
            if sr.session["session_id"] != sid:
                raise ValueError(f"its rows are for session_id {sr.session['session_id']!r}")
        except Exception as exc:  # noqa: BLE001 - one session's bug never loses the build
            fail(i, d, sid, f"assembling the catalog rows: {type(exc).__name__}: {exc}",
                 None, info, common, prev, good_prev)
            continue
        built.append((i, d, sid, sr, info, common, prev, good_prev))
        meshes[sid] = sr.object_mesh  # the session's own mesh (content-addressed)
    shared = _shared_object_notes({sid: (sr.object_id, mesh_digest(sr.object_mesh, sid))
                                   for _, _, sid, sr, *_ in built}, prev_rows)
    # the checks the commit runs, per session: one whose rows, frames or arrays would make it
    # raise fails alone, with the reason, and the others are committed
    for i, d, sid, sr, info, common, prev, good_prev in built:
        if sid in shared:
            info["notes"] = (*info["notes"], shared[sid])
        try:
            check_commit(gc.BuildCommit(build=info_commit, sessions=[sr.session],
                                        frames=sr.frames, session_arrays={sid: sr.arrays},
                                        object_meshes=meshes))
        except Exception as exc:  # noqa: BLE001 - CatalogSchemaError, or a bug in a check
            fail(i, d, sid, f"the catalog refused its rows: {exc}", None, info, common, prev,
                 good_prev)
            continue
        rows.append(sr.session)
        frames.extend(sr.frames)
        arrays[sid] = sr.arrays
        by_index[i] = SessionReport(outcome=Outcome.CHANGED if prev else Outcome.ADDED,
                                   status=sr.session["status"], error=sr.session["error"],
                                   **info)
    reports = [by_index[i] for i in sorted(by_index)]
    t_rows = time.perf_counter()

    params = {"roots": [str(r) for r in roots], "catalog": str(cat.layout.root),
              "preset": preset, "retry_failed": retry_failed, "work": str(work.root),
              "gates": gates.model_dump(mode="json"),
              "configs": {n: json.loads(c.canonical_json()) for n, c in configs.items()},
              "not_sessions": [str(p) for p in found.not_sessions]}
    run = FlowRunContext.get()
    if run is not None and getattr(run, "flow_run", None) is not None:
        params["flow_run_id"] = str(run.flow_run.id)  # the Prefect run (UI) of this build
    seconds = {"discover": t_discover - t0, "run": t_run - t_discover, "rows": t_rows - t_run}
    draft = BuildReport(build_id, None, previous, tuple(reports), seconds, params)
    new_version = None
    if rows or new_failures:
        try:
            new_version = cat.commit(gc.BuildCommit(
                build=gc.BuildInfo(build_id, version, cdigest,
                                   parameters={**params, "report": draft.record()},
                                   sessions_unchanged=tuple(draft.unchanged)),
                sessions=rows, frames=frames, session_arrays=arrays, object_meshes=meshes),
                gates)
        except Exception as exc:
            seconds["total"] = time.perf_counter() - t0
            kept = sum(len(s.ran) + len(s.cached) for s in reports)
            failed = BuildFailed(
                f"build {build_id} committed nothing: {type(exc).__name__}: {exc}. The "
                f"{kept} completed stage result(s) stay in the work area {work.root}; the next "
                "build commits them without running those stages again")
            _log_build(work, {**draft.record(), "error": str(failed), "keys": used})
            raise failed from exc
    seconds["commit"] = time.perf_counter() - t_rows
    publication = _publication(cat, new_version)
    if new_version is not None and optimize_every and new_version % optimize_every == 0:
        publication["optimized"] = _optimize(cat)
    t_prune = time.perf_counter()
    if prune_flow_runs(RunRetention(**(retention or {}))) is not None:
        seconds["prune_runs"] = time.perf_counter() - t_prune
    seconds["total"] = time.perf_counter() - t0
    report = BuildReport(build_id, new_version, previous, tuple(reports), seconds, params,
                         publication=publication)
    report = dataclasses.replace(report, report_page=_report_page(cat, report))
    _log_build(work, {**report.record(), "keys": used})
    _qa_artifact(cat, report)
    if log is not None:
        for s in report.sessions:
            if s.outcome == Outcome.FAILED:
                log.info("%s failed%s: %s", s.session_id,
                            f" in {s.failed_stage}" if s.failed_stage else "", s.error)
        log.info("%s", report.summary())
    return report


def _publication(cat: gc.Catalog, version: int | None) -> dict[str, Any]:
    """The version's audit and state, and the version readers now get by default."""
    states = cat.states()
    out: dict[str, Any] = {"published_version": cat.published_version()}
    if version is not None:
        out["state"] = states[version].value
        out["audit"] = cat.audit(version)
    return out


def _optimize(cat: gc.Catalog) -> dict[str, Any] | None:
    """Compact the catalog's tables (``catalog.optimize``); its report as a dict, None (with
    a warning) when it failed: compaction is housekeeping and never fails the build."""
    from graspcap.catalog.optimize import optimize_catalog

    try:
        return dataclasses.asdict(optimize_catalog(cat))
    except Exception as exc:  # noqa: BLE001 - the build's version is committed
        logging.getLogger(__name__).warning("catalog optimize after the build failed: %s: %s",
                                            type(exc).__name__, exc)
        return None


def _run_log() -> logging.Logger | logging.LoggerAdapter | None:
    """The flow run's logger (lines in the run's log in Prefect's UI), None outside a run."""
    try:
        from prefect.logging import get_run_logger

        return get_run_logger()
    except Exception:  # noqa: BLE001 - MissingContextError: called as a plain function
        return None


def _session_id(session_dir: Path) -> str:
    """``session_id_of``, or the folder's name when even that fails: the session then fails
    in ``load_session`` with the reason, on its own."""
    try:
        return session_id_of(session_dir)
    except Exception:  # noqa: BLE001 - e.g. a RecursionError of a pathological manifest
        return session_dir.name


def _log_build(work: WorkArea, record: dict) -> None:
    """Append a build's record to the work area's ``builds.jsonl`` (``graspcap status``); a
    record that cannot be written (disk full) is a warning: the catalog has the build."""
    try:
        with open(work.root / BUILDS_LOG, "a") as log:
            log.write(json.dumps(record, sort_keys=True) + "\n")
    except OSError as exc:
        logging.getLogger(__name__).warning("build record not written to %s: %s",
                                            work.root / BUILDS_LOG, exc)


def _write_pictures(layout: CatalogLayout, session_id: str, pictures: Any) -> dict[str, str]:
    """Store a session's QA pictures (``tasks.pictures.Pictures``) by content
    (``layout.picture_file``); their paths relative to the catalog root by file name. A file
    already there is kept; a new one is written to a temporary name and renamed (a reader sees
    the whole file or none). ``session_id``: whose pictures they are (a caller's messages)."""
    stored = {}
    for name, data in pictures.files().items():
        path = layout.picture_file(hashlib.sha256(data).hexdigest(), Path(name).suffix)
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
            try:
                tmp.write_bytes(data)
                os.replace(tmp, path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
        stored[name] = path.relative_to(layout.root).as_posix()
    return stored


def _store_pictures(layout: CatalogLayout, session_id: str, ref: ResultRef
                    ) -> tuple[dict[str, str], tuple[str, ...]]:
    """Store a session's pictures under the catalog's ``pictures/`` (by content: a session id
    is never a path there); (their paths by name, ()) when stored, else ({}, a note naming
    the folder and the error: disk full, permission): pictures are a QA aid and never fail a
    session or the build."""
    try:
        return _write_pictures(layout, session_id, WorkArea.load(ref)), ()
    except Exception as exc:  # noqa: BLE001 - OSError above all; never fails the build
        where = getattr(exc, "filename", None) or layout.pictures_root
        return {}, (f"pictures of {session_id} not written to {where}: {type(exc).__name__}: "
                    f"{exc} (a QA aid: the session is committed without them)",)


def _report_page(cat: gc.Catalog, report: BuildReport) -> str | None:
    """Write the build's report page (``catalog.report_page``) of the version it made, or of
    the catalog's latest when it made none; its path, or None (with a warning) when it cannot
    be written: the page is an aid and never fails the build."""
    from graspcap.catalog.report_page import write_report

    try:
        version = report.catalog_version if report.catalog_version is not None \
            else cat.base_version()
        if version is None:
            return None
        return str(write_report(cat, version, report.record()))
    except Exception as exc:  # noqa: BLE001 - an aid, like the pictures
        logging.getLogger(__name__).warning("build %s: report page not written: %s: %s",
                                            report.build_id, type(exc).__name__, exc)
        return None


QA_ARTIFACT_KEY = "graspcap-build-qa"


def qa_table(cat: gc.Catalog, report: BuildReport) -> list[dict[str, Any]]:
    """The build's QA table: one row per session of the build, every row with the same
    columns (Prefect's UI takes them from the first row): the outcome, status and error, the
    flag reasons (``qa_flags``) and notes (``qa_notes``) joined by ``"; "``, and every
    ``qa_*`` metric column, as the version the build made (else the catalog's latest) holds
    them; empty where a session has no row (a failure with none written) or no value."""
    from graspcap.schemas.qa import qa_columns

    metrics = [m.column for m in qa_columns()]
    version = report.catalog_version if report.catalog_version is not None \
        else cat.latest_version()
    stored: dict[str, dict] = {}
    if version is not None:
        table = cat.table("sessions", version=version)
        wanted = [c for c in ("session_id", "qa_flags", "qa_notes", *metrics)
                  if c in table.column_names]
        stored = {r["session_id"]: r for r in table.select(wanted).to_pylist()}
    out = []
    for s in report.sessions:
        row = stored.get(s.session_id, {})
        item: dict[str, Any] = {
            "session": s.session_id, "outcome": str(s.outcome), "status": s.status or "",
            "ran": len(s.ran), "cached": len(s.cached), "error": s.error or "",
            "flags": "; ".join(row.get("qa_flags") or ()),
            "qa_notes": "; ".join(row.get("qa_notes") or ())}
        for column in metrics:
            value = row.get(column)
            item[column] = None if isinstance(value, float) and value != value else value
        out.append(item)
    return out


def _qa_artifact(cat: gc.Catalog, report: BuildReport) -> None:
    """The build's QA table (:func:`qa_table`) as a Prefect table artifact (shows in the UI
    with a server), described by the build's summary."""
    try:
        from prefect.artifacts import create_table_artifact

        create_table_artifact(qa_table(cat, report), key=QA_ARTIFACT_KEY,
                              description=report.summary().replace("\n", "  \n"))
    except Exception as exc:  # noqa: BLE001 - an artifact is feedback, never a reason to fail
        logging.getLogger(__name__).warning("build %s: QA artifact not made: %s: %s",
                                            report.build_id, type(exc).__name__, exc)


def build_dataset(roots: Sequence[Path | str], catalog: Path | str, preset: str = "default", *,
                  overrides: Mapping[str, Any] | None = None, retry_failed: bool = False,
                  task_runner_=None, dask: str | None = None, workers: int = 2,
                  work: Path | str | None = None, build_id: str | None = None,
                  progress: ProgressFn | None = None,
                  gates: gc.AuditGates | Mapping[str, Any] | None = None,
                  optimize_every: int | None = OPTIMIZE_EVERY,
                  retention: RunRetention | None = None) -> BuildReport:
    """Build (or update) the catalog at ``catalog`` from the sessions under ``roots``.

    ``dask``: None (threads in this process, ``workers`` of them), ``"local:N"`` (a Dask
    LocalCluster of N single-threaded processes) or a scheduler address; ``task_runner_``
    overrides both. ``work``: the work area every worker can reach (default
    ``<catalog>/work``). ``overrides``: per stage a config or a dict of fields. ``gates``: the
    write-audit-publish audit (``catalog.audit.AuditGates``, default gates when None): the
    version is published when it passes, else staged. ``optimize_every``: compact the tables
    when the new version's number is a multiple of it. ``retention``: how many of Prefect's
    flow runs to keep (``flows/retention.py``; default ``RunRetention()``), pruned at the
    end of the build.
    """
    if isinstance(gates, gc.AuditGates):
        gates = gates.model_dump()
    gates = gc.AuditGates(**dict(gates or {})).model_dump()  # a bad gate fails before Prefect
    runner = task_runner_ or task_runner(dask, workers)
    with reporting_to(progress), worker_api(dask) as api_url, build_settings(api_url):
        return build_flow.with_options(task_runner=runner)(
            [str(r) for r in roots], str(catalog), preset, dict(overrides or {}),
            retry_failed, None if work is None else str(work), build_id, gates,
            optimize_every, (retention or RunRetention()).model_dump())
