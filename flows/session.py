"""One capture session as a DAG of Prefect tasks, one per stage of ``tasks.pipeline.STAGES``.

Every task is the same thin wrapper, :func:`run_stage_task`, named per stage. Its body is
:func:`graspcap.flows.cached.run_cached`: our own cache key and work area decide whether the
stage body runs, so Prefect's result store and cache are off (``persist_result=False``,
``cache_policy=NONE``) and tasks hand each other only small :class:`ResultRef` s.

Transient faults (an ``OSError`` of the storage, a lost Dask worker) are retried with back-off;
a :class:`StageError` (invalid input, a solver that cannot converge) is deterministic and never
retried: the task fails with its reason and the session's downstream tasks do not run.

A build settles what the work area already holds in the flow itself (``settle=True``, see
:func:`settle_session`): a stage whose key hits, or whose remembered failure is replayed, gets no
Prefect task run at all (a task run costs ~40 ms in the flow's process and ~70 ms of the API
server's CPU, measured), and only the stages that must run are submitted. The build record
says which stages hit the cache; in Prefect's UI a build's flow run lists the tasks that ran.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from prefect import flow, task
from prefect.cache_policies import NONE
from prefect.futures import PrefectFuture

from graspcap.flows.cached import lookup_cached, run_cached, session_id_of
from graspcap.flows.session_roles import SessionRoles
from graspcap.flows.workarea import ResultRef, WorkArea
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError

RETRIES = 3
RETRY_DELAYS_S = [1.0, 4.0, 16.0]
"""Back-off between the attempts of a task that failed with a transient fault."""

_PERMANENT_OS_ERRORS = (FileNotFoundError, NotADirectoryError, PermissionError,
                        IsADirectoryError)


AST_THREAD_RACE = "AST constructor recursion depth mismatch"
"""CPython 3.11's ``ast`` keeps its recursion depth in module state shared by all threads, so
two threads building ASTs at once (the code digests, Prefect, a library's own parsing) can
raise ``SystemError`` with this message (python/cpython#106905; seen once in a cold build
here, a second attempt of the stage ran through)."""


def is_transient(exc: BaseException | None) -> bool:
    """True for faults worth retrying: an ``OSError`` of the storage other than a missing or
    forbidden path, a lost Dask worker / closed connection, or CPython 3.11's ``ast`` thread
    race (``AST_THREAD_RACE``)."""
    if exc is None:
        return False
    names = {cls.__name__ for cls in type(exc).__mro__}
    if names & {"KilledWorker", "CommClosedError"}:
        return True
    if isinstance(exc, SystemError) and AST_THREAD_RACE in str(exc):
        return True
    return isinstance(exc, OSError) and not isinstance(exc, _PERMANENT_OS_ERRORS)


def _retry_condition(task, task_run, state) -> bool:
    try:
        exc = state.result(raise_on_failure=False)
    except Exception as lookup_error:  # noqa: BLE001 - the state lost its exception
        exc = lookup_error
    return is_transient(exc) if isinstance(exc, BaseException) else False


@task(persist_result=False, cache_policy=NONE, retries=RETRIES,
      retry_delay_seconds=RETRY_DELAYS_S, retry_condition_fn=_retry_condition,
      log_prints=False)
def run_stage_task(stage: str, session_dir: str, session_id: str, config: StageConfig,
                   work: WorkArea, build_id: str, replay_failures: bool = True,
                   **upstream: ResultRef) -> ResultRef:
    """One stage of one session through the work area's cache (see ``flows/cached.py``)."""
    return run_cached(stage, session_dir, session_id, config, upstream, work, build_id,
                      replay_failures)


def stage_task(stage: str, session_id: str):
    """``run_stage_task`` named for ``stage`` (task name) and the session (task-run name)."""
    return run_stage_task.with_options(name=stage, task_run_name=f"{stage}[{session_id}]")


@dataclass(frozen=True)
class Settled:
    """A stage settled without a task of its own: ``state`` "Cached" (``ref``: the stored
    result), "Failed" (``error``: a remembered deterministic failure, replayed; or ``why``,
    the failure as text, from a session task) or "NotReady" (an upstream stage failed); in a
    session task (:func:`run_session_task`) also "Completed" (``ref``)."""

    state: str
    ref: ResultRef | None = None
    error: StageError | None = None
    why: str | None = None


@dataclass(frozen=True)
class InSession:
    """A stage run inside its session's task (``future``, of :func:`run_session_task`)."""

    future: PrefectFuture
    stage: str


def failure_text(stage: str, exc: BaseException | None, message: str | None = None) -> str:
    """A stage's failure as the build reports it: a ``StageError``'s own text, else the stage,
    the exception type and its message."""
    if isinstance(exc, StageError):
        return str(exc)
    if isinstance(exc, BaseException):
        return f"{stage}: {type(exc).__name__}: {exc}"
    return f"{stage}: {message}"


def run_retrying(stage: str, session_dir: str, session_id: str, config: StageConfig,
                 work: WorkArea, build_id: str, replay_failures: bool,
                 upstream: Mapping[str, ResultRef]) -> ResultRef:
    """``run_cached`` with the stage tasks' retry policy (``RETRIES`` attempts more, after
    ``RETRY_DELAYS_S``, for transient faults only), without a Prefect task run of its own."""
    for attempt in range(RETRIES + 1):
        try:
            return run_cached(stage, session_dir, session_id, config, upstream, work, build_id,
                              replay_failures)
        except Exception as exc:
            if attempt == RETRIES or not is_transient(exc):
                raise
            time.sleep(RETRY_DELAYS_S[attempt])
    raise AssertionError("unreachable")


@task(persist_result=False, cache_policy=NONE, retries=RETRIES,
      retry_delay_seconds=RETRY_DELAYS_S, retry_condition_fn=_retry_condition,
      log_prints=False)
def run_session_task(session_dir: str, session_id: str, configs: Mapping[str, StageConfig],
                     work: WorkArea, build_id: str, replay_failures: bool,
                     settled: Mapping[str, ResultRef], to_run: list[str]) -> dict[str, Settled]:
    """The stages ``to_run`` of one session, in DAG order, in this process: what a Dask worker
    gets, one dispatch per session instead of per stage (a dispatch through Dask costs ~0.4 s:
    the flow's context serialised, the settings re-validated in the worker). Each stage is a
    plain call with the stage tasks' cache, retry and failure rules (:func:`run_retrying`), not
    a nested task run: a task run costs the API server ~0.2 s of CPU (its state changes),
    which on two cores competes with the stage bodies. ``settled``: refs of the stages
    already cached. A lost worker fails the session task, which is retried: the stages that
    completed are then cache hits."""
    from graspcap.tasks.pipeline import STAGES

    refs = dict(settled)
    out: dict[str, Settled] = {}
    for name in to_run:
        stage = STAGES[name]
        if any(up not in refs for up in stage.upstream):
            out[name] = Settled("NotReady")
            continue
        try:
            refs[name] = run_retrying(name, session_dir, session_id, configs[name], work,
                                      build_id, replay_failures,
                                      {up: refs[up] for up in stage.upstream})
            out[name] = Settled("Completed", ref=refs[name])
        except Exception as exc:  # noqa: BLE001 - the session goes on; the build reports it
            out[name] = Settled("Failed", why=failure_text(name, exc))
    return out


def settle_session(session_dir: Path | str, configs: Mapping[str, StageConfig], work: WorkArea,
                   stages: Mapping | None = None, replay_failures: bool = True
                   ) -> dict[str, Settled]:
    """The stages of one session the work area settles, in DAG order: a stage whose upstream
    stages are all cached and whose own key hits (or whose failure is remembered); the
    downstream stages of a remembered failure are "NotReady". A stage left out must run."""
    from graspcap.tasks.pipeline import STAGES

    stages = STAGES if stages is None else stages
    settled: dict[str, Settled] = {}
    roles = SessionRoles(work, session_dir)
    for name, stage in stages.items():
        ups = [settled.get(up) for up in stage.upstream]
        if any(u is not None and u.state != "Cached" for u in ups):
            settled[name] = Settled("NotReady")
            continue
        if any(u is None for u in ups):
            continue
        found = lookup_cached(name, session_dir, configs[name],
                              {up: u.ref for up, u in zip(stage.upstream, ups, strict=True)},
                              work, replay_failures, roles.digests)
        if isinstance(found, ResultRef):
            settled[name] = Settled("Cached", ref=found)
        elif isinstance(found, StageError):
            settled[name] = Settled("Failed", error=found)
    roles.save()
    return settled


def submit_session(session_dir: Path | str, configs: Mapping[str, StageConfig],
                   work: WorkArea, build_id: str, session_id: str | None = None,
                   stages: Mapping | None = None, replay_failures: bool = True,
                   settle: bool = False, per_session: bool = False,
                   settled: Mapping[str, Settled] | None = None
                   ) -> dict[str, PrefectFuture | Settled | InSession]:
    """Submit the stages of one session into the running flow; futures by stage name.
    ``replay_failures=False`` runs stages whose remembered failure would be replayed.
    ``settle=True``: stages the work area settles (:func:`settle_session`) get no task; they
    are :class:`Settled` in the returned mapping and their refs are passed on as they are.
    ``settled``: what :func:`settle_session` gave for this session just before (used instead
    of settling again when ``settle``). ``per_session=True`` (a Dask runner): the stages that
    must run go to ONE task,
    :func:`run_session_task`, and are :class:`InSession` in the returned mapping.

    Upstream futures are passed as parameters, so Prefect resolves them to their refs and a
    task whose upstream failed does not run (it ends ``NotReady``).
    """
    from graspcap.tasks.pipeline import STAGES

    stages = STAGES if stages is None else stages
    session_dir = str(Path(session_dir).resolve())
    session_id = session_id or session_id_of(Path(session_dir))
    out: dict[str, PrefectFuture | Settled | InSession] = (
        dict(settled if settled is not None
             else settle_session(session_dir, configs, work, stages, replay_failures))
        if settle else {})
    if per_session:
        to_run = [name for name in stages if name not in out]
        if to_run:
            future = run_session_task.with_options(task_run_name=f"session[{session_id}]").submit(
                session_dir, session_id, {n: configs[n] for n in to_run}, work, build_id,
                replay_failures, {n: s.ref for n, s in out.items() if s.state == "Cached"},
                to_run)
            out.update({name: InSession(future, name) for name in to_run})
        return {name: out[name] for name in stages}
    for name, stage in stages.items():
        if name in out:
            continue
        out[name] = stage_task(name, session_id).submit(
            name, session_dir, session_id, configs[name], work, build_id, replay_failures,
            **{up: out[up].ref if isinstance(out[up], Settled) else out[up]
               for up in stage.upstream},
        )
    return out


@flow(name="graspcap-session", persist_result=False)
def session_flow(session_dir: str, work_root: str, preset: str = "default",
                 build_id: str = "session-flow") -> dict[str, ResultRef]:
    """Run one session on its own (no catalog commit); the refs of its stage results."""
    from graspcap.tasks.pipeline import configs_for

    work = WorkArea(work_root)
    futures = submit_session(session_dir, configs_for(preset), work, build_id)
    return {name: f.result() for name, f in futures.items()}
