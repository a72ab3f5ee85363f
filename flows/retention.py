"""Retention of Prefect's flow runs: the local database stays bounded however many builds run.

Every build is one flow run with one task run per stage and session (a 1,000-session build
adds ~14,000 task runs with their states), kept in Prefect's database (``<work>/prefect/`` by
default, ``flows/runtime.py``). Prefect's own ``db_vacuum`` service deletes old flow runs only
in a long-running server with ``flow_runs`` vacuum enabled, after at least an hour; a build's
ephemeral API never runs it. So after each build :func:`prune_flow_runs` deletes, through
Prefect's client API (``read_flow_runs``, ``delete_flow_run``), every finished flow run beyond
the newest ``max_runs`` or older than ``max_age_days``; the database deletes their task runs
and states with them (foreign keys ``ON DELETE CASCADE``). Runs that have not finished are
never touched (a build running beside this one, a scheduled run). What the catalog needs of a
build is in the catalog and the work area (``builds.jsonl``), never in Prefect's database.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from pydantic import BaseModel, ConfigDict, Field

log = logging.getLogger(__name__)

PAGE = 200
"""Flow runs read per request (the API's default limit)."""


class RunRetention(BaseModel):
    """How many of Prefect's finished flow runs a build leaves behind."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    max_runs: int | None = Field(100, ge=1)
    """Keep the newest this many finished flow runs (None: no count limit)."""
    max_age_days: float | None = Field(30.0, gt=0)
    """Delete finished flow runs that started longer ago than this (None: no age limit)."""


@dataclass(frozen=True)
class PruneReport:
    """What :func:`prune_flow_runs` did."""

    kept: int
    deleted: int
    seconds: float


def prune_flow_runs(retention: RunRetention, client=None) -> PruneReport | None:
    """Delete the finished flow runs ``retention`` does not keep (module docstring); None (with
    a warning) when the API cannot be reached: retention is housekeeping, never a reason to
    fail a build. ``client``: a synchronous Prefect client (default: the current API's)."""
    if retention.max_runs is None and retention.max_age_days is None:
        return PruneReport(0, 0, 0.0)
    t0 = time.perf_counter()
    try:
        if client is None:
            from prefect.client.orchestration import get_client

            with get_client(sync_client=True) as own:
                kept, deleted = _prune(own, retention)
        else:
            kept, deleted = _prune(client, retention)
    except Exception as exc:  # noqa: BLE001 - the build is committed; say why and go on
        log.warning("Prefect flow-run retention skipped: %s: %s", type(exc).__name__, exc)
        return None
    return PruneReport(kept, deleted, time.perf_counter() - t0)


def _prune(client, retention: RunRetention) -> tuple[int, int]:
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterState,
        FlowRunFilterStateType,
    )
    from prefect.client.schemas.objects import StateType
    from prefect.client.schemas.sorting import FlowRunSort

    finished = FlowRunFilter(state=FlowRunFilterState(type=FlowRunFilterStateType(any_=[
        StateType.COMPLETED, StateType.FAILED, StateType.CRASHED, StateType.CANCELLED])))
    runs = []
    while True:  # newest first; ties broken by id so pages do not overlap
        page = client.read_flow_runs(flow_run_filter=finished, sort=FlowRunSort.START_TIME_DESC,
                                     limit=PAGE, offset=len(runs))
        runs += page
        if len(page) < PAGE:
            break
    cutoff = (datetime.now(UTC) - timedelta(days=retention.max_age_days)
              if retention.max_age_days is not None else None)
    doomed = []
    for i, run in enumerate(runs):
        started = run.start_time or run.expected_start_time or run.created
        too_many = retention.max_runs is not None and i >= retention.max_runs
        too_old = cutoff is not None and started is not None and started < cutoff
        if too_many or too_old:
            doomed.append(run.id)
    for run_id in doomed:
        client.delete_flow_run(run_id)
    return len(runs) - len(doomed), len(doomed)
