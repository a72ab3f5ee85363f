"""A dataset build: every session's DAG in ONE Prefect flow run, one catalog version.

    report = build_dataset(["captures/"], "catalog/")

1. discover the sessions under the roots (``session.discover.discover``; folders beside them
   without ``session.json`` are named in the report, not skipped without a word);
2. submit every session's stage tasks into this one flow run (not a subflow per session:
   measured in ``docs/architecture.md``), so sessions run concurrently on the task runner;
3. wait for each task; a failed session never stops the others, and its downstream tasks
   do not run;
4. turn the results into catalog rows and failures (``flows/assemble.py``, with
   ``flows/rows.py``); a session whose stages all hit the cache and whose catalog row has the
   same input and config digests is ``unchanged``;
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
from graspcap.flows.assemble import assemble, last_build_failures, recorded_failures
from graspcap.flows.build_log import append_build
from graspcap.flows.cached import session_id_of
from graspcap.flows.progress import ProgressFn, Tracker, reporting_to
from graspcap.flows.report import BuildFailed, BuildReport, Outcome
from graspcap.flows.retention import RunRetention, prune_flow_runs
from graspcap.flows.runtime import build_settings, task_runner, worker_api
from graspcap.flows.session import InSession, Settled, failure_text, submit_session
from graspcap.flows.workarea import BUILDS_LOG, WorkArea
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.session.discover import discover

OPTIMIZE_EVERY = 20
"""A build whose version number is a multiple of this compacts the catalog's tables
(``catalog.optimize``: one more version, same rows, fewer files); None or 0: never."""
__all__ = ["BuildFailed", "ProgressFn", "build_dataset", "build_flow", "last_build_failures",
           "recorded_failures"]


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
    from graspcap.tasks.pipeline import STAGES, configs_for, tie_configs

    base = configs_for(preset)
    out = dict(base)
    for name, value in (overrides or {}).items():
        if name not in STAGES:
            raise KeyError(f"no such stage {name!r}; stages are {list(STAGES)}")
        out[name] = value if isinstance(value, StageConfig) else STAGES[name].config_type(
            **{**base[name].model_dump(), **dict(value)})
    return tie_configs(out)


def configs_digest(configs: Mapping[str, StageConfig]) -> str:
    from graspcap.tasks.pipeline import STAGES

    text = json.dumps({n: [STAGES[n].version, c.canonical_json()] for n, c in configs.items()},
                      sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


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


@dataclasses.dataclass
class _Prepared:
    """A build up to its stage tasks: what discovery found and what the work area settles."""

    t0: float
    cat: gc.Catalog
    work: WorkArea
    configs: dict[str, StageConfig]
    cdigest: str
    version: str
    found: Any
    dirs: list[Path]
    ids: list[str]
    duplicate: dict[str, str]
    settled: dict[str, dict[str, Settled]]
    """By session directory: the stages the work area settles (``settle_session``)."""
    t_discover: float
    done: Any = None
    """The assembled rows, when a build outside Prefect found something to write."""
    t_run: float = 0.0

    @property
    def idle(self) -> bool:
        """True when every stage of every session is settled: no stage task to run."""
        from graspcap.tasks.pipeline import STAGES

        return all(len(s) == len(STAGES) for s in self.settled.values())


_HANDOFF: dict[str, _Prepared] = {}
"""Preparations made before Prefect started, by build id, for the flow run to take over."""


def _prepare(roots: list[str], catalog: str, preset: str, overrides: dict[str, Any] | None,
             retry_failed: bool, work_root: str | None) -> _Prepared:
    """Steps 1 and the settling part of 2 (module docstring), without Prefect."""
    from graspcap.flows.session import settle_session

    t0 = time.perf_counter()
    cat = gc.open(catalog, create=True)
    work = WorkArea(work_root or cat.layout.root / "work")
    configs = resolve_configs(preset, overrides)
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
    settled = {str(d): settle_session(str(Path(d).resolve()), configs, work,
                                      replay_failures=not retry_failed)
               for d in dirs if str(d) not in duplicate}
    return _Prepared(t0, cat, work, configs, configs_digest(configs), code_version(), found,
                     dirs, ids, duplicate, settled, t_discover)


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
    build_id = build_id or _new_build_id()
    prep = _HANDOFF.pop(build_id, None) or _prepare(roots, catalog, preset, overrides,
                                                     retry_failed, work_root)
    return _build(prep, roots, preset, retry_failed, build_id, gates, optimize_every,
                  retention)


def _new_build_id() -> str:
    return time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:8]


def _build(prep: _Prepared, roots: list[str], preset: str, retry_failed: bool, build_id: str,
           gates: dict[str, Any] | None, optimize_every: int | None,
           retention: dict[str, Any] | None, quiet: bool = False) -> BuildReport | None:
    """Steps 2-6 of the module docstring. ``quiet``: outside Prefect, for a build whose
    stages are all settled (``prep.idle``): the report when it has nothing to commit either,
    else None, with ``prep`` in ``_HANDOFF`` for the flow run to finish."""
    gates = gc.AuditGates(**(gates or {}))
    cat, work, configs, version = prep.cat, prep.work, prep.configs, prep.version
    dirs, ids, duplicate, cdigest = prep.dirs, prep.ids, prep.duplicate, prep.cdigest
    t0, t_discover = prep.t0, prep.t_discover
    # on Dask, one task per session (its stages plain calls in it): a dispatch costs ~0.4 s
    runner = getattr(FlowRunContext.get(), "task_runner", None)
    per_session = type(runner).__name__ == "DaskTaskRunner"
    submitted = {str(d): submit_session(d, configs, work, build_id, session_id=sid,
                                        replay_failures=not retry_failed, settle=True,
                                        per_session=per_session,
                                        settled=prep.settled.get(str(d)))
                 for d, sid in zip(dirs, ids, strict=True) if str(d) not in duplicate}
    log = None if quiet else _run_log()
    session_ids = {str(d): sid for d, sid in zip(dirs, ids, strict=True)}
    if not quiet:
        _watch(submitted, session_ids, log)
    outcomes = {d: _stage_outcomes(f) for d, f in submitted.items()}
    # the stored result each stage used, by session (`catalog vacuum --work` keeps them)
    used = {sid: {name: ref.key for name, ref in outcomes[str(d)][0].items()}
            for d, sid in zip(dirs, ids, strict=True) if str(d) in outcomes}
    t_run = prep.t_run if prep.done is not None else time.perf_counter()

    previous = cat.base_version()  # planned against what the commit writes on top of
    done = prep.done if prep.done is not None else assemble(
        cat, work, gc.BuildInfo(build_id, version, cdigest), previous,
        list(zip(dirs, ids, strict=True)), duplicate, outcomes)
    if quiet and (done.rows or done.new_failures):
        prep.done, prep.t_run = done, t_run
        _HANDOFF[build_id] = prep
        return None
    if quiet:
        _watch(submitted, session_ids)  # progress: every stage settled
    reports = done.reports
    t_rows = time.perf_counter()

    params = {"roots": [str(r) for r in roots], "catalog": str(cat.layout.root),
              "preset": preset, "retry_failed": retry_failed, "work": str(work.root),
              "gates": gates.model_dump(mode="json"),
              "configs": {n: json.loads(c.canonical_json()) for n, c in configs.items()},
              "not_sessions": [str(p) for p in prep.found.not_sessions]}
    run = FlowRunContext.get()
    if run is not None and getattr(run, "flow_run", None) is not None:
        params["flow_run_id"] = str(run.flow_run.id)  # the Prefect run (UI) of this build
    seconds = {"discover": t_discover - t0, "run": t_run - t_discover, "rows": t_rows - t_run}
    draft = BuildReport(build_id, None, previous, tuple(reports), seconds, params)
    new_version = None
    if done.rows or done.new_failures:
        try:
            new_version = cat.commit(gc.BuildCommit(
                build=gc.BuildInfo(build_id, version, cdigest,
                                   parameters={**params, "report": draft.record()},
                                   sessions_unchanged=tuple(draft.unchanged)),
                sessions=done.rows, frames=done.frames, session_arrays=done.arrays,
                object_meshes=done.meshes),
                gates)
        except Exception as exc:
            seconds["total"] = time.perf_counter() - t0
            kept = sum(len(s.ran) + len(s.cached) for s in reports)
            failed = BuildFailed(
                f"build {build_id} committed nothing: {type(exc).__name__}: {exc}. The "
                f"{kept} completed stage result(s) stay in the work area {work.root}; the next "
                "build commits them without running those stages again")
            _log_build(work, {**draft.record(), "error": str(failed)}, used)
            raise failed from exc
    seconds["commit"] = time.perf_counter() - t_rows
    publication = _publication(cat, new_version)
    if new_version is not None and optimize_every and new_version % optimize_every == 0:
        publication["optimized"] = _optimize(cat)
    t_prune = time.perf_counter()  # a quiet build made no flow run: nothing new to prune
    if not quiet and prune_flow_runs(RunRetention(**(retention or {}))) is not None:
        seconds["prune_runs"] = time.perf_counter() - t_prune
    seconds["total"] = time.perf_counter() - t0
    report = BuildReport(build_id, new_version, previous, tuple(reports), seconds, params,
                         publication=publication)
    report = dataclasses.replace(report, report_page=_report_page(cat, report))
    _log_build(work, report.record(), used)
    if not quiet:
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


def _log_build(work: WorkArea, record: dict, used: dict[str, dict[str, str]]) -> None:
    """Append a build's record to the work area's ``builds.jsonl`` (``graspcap status``) with
    the keys of the sessions whose ``used`` keys changed (``flows/build_log.py``); a record
    that cannot be written (disk full) is a warning: the catalog has the build."""
    try:
        append_build(work.root, record, used)
    except OSError as exc:
        logging.getLogger(__name__).warning("build record not written to %s: %s",
                                            work.root / BUILDS_LOG, exc)


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
                  retention: RunRetention | None = None,
                  flow_when_idle: bool = False) -> BuildReport:
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

    A build that has nothing to run (every stage of every session settled by the work area)
    and nothing to commit (every session unchanged, no new failure) starts no Prefect: no
    API server, no flow run, no QA artifact, no pruning; it writes what any build without a
    version writes (its record in ``builds.jsonl``, its report page) and returns the same
    report. ``flow_when_idle=True`` runs it as a flow run all the same. A build with
    something to run or commit hands what it settled before Prefect started to its flow run
    (nothing is settled twice).
    """
    if isinstance(gates, gc.AuditGates):
        gates = gates.model_dump()
    gates = gc.AuditGates(**dict(gates or {})).model_dump()  # a bad gate fails before Prefect
    build_id = build_id or _new_build_id()
    args = ([str(r) for r in roots], str(catalog), preset, dict(overrides or {}), retry_failed,
            None if work is None else str(work))
    retention_ = (retention or RunRetention()).model_dump()
    try:
        with reporting_to(progress):
            prep = _prepare(*args)
            if prep.idle and not flow_when_idle:
                report = _build(prep, args[0], preset, retry_failed, build_id, gates,
                                optimize_every, retention_, quiet=True)
                if report is not None:
                    return report
            _HANDOFF[build_id] = prep
        runner = task_runner_ or task_runner(dask, workers)
        with reporting_to(progress), worker_api(dask) as api_url, build_settings(api_url):
            return build_flow.with_options(task_runner=runner)(
                *args, build_id, gates, optimize_every, retention_)
    finally:
        _HANDOFF.pop(build_id, None)
