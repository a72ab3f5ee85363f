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

Deleting a flow run leaves what is not tied to it by a foreign key: its ``events`` and
``event_resources`` (a dozen events and three dozen resource rows per tiny flow run; three
state events per task run), its ``log`` rows (the API deletes them in a background task that a
build's short-lived ephemeral server may not get to run) and its ``artifact`` (the QA table of
each build). Prefect's own ``server.events.retention_period``
(``PREFECT_SERVER_EVENTS_RETENTION_PERIOD``, default 7 days; its event vacuum runs when a
server starts, the ephemeral one included, and hourly) bounds events by age only: 50 builds a
day keep 350 builds' events.
So with ``history`` on (the default) :func:`prune_history` then deletes, directly in Prefect's
SQLite database when the API's runs are in that file (:func:`local_database`), the events that
name a deleted flow run (every task-run event names its flow run) with their event resources,
the deleted runs' logs and artifacts (an artifact that is a collection's latest stays), and
any of these older than the oldest kept run by over an hour (leftovers, events of no run). A
server on another database (``PREFECT_API_URL`` elsewhere, Postgres) is left to its own
``db_vacuum`` service (``PREFECT_SERVER_SERVICES_DB_VACUUM_ENABLED=events,flow_runs``). SQLite
reuses the freed pages, so the file stops growing near the retained runs' size
(``bench/prefect_db.py``, ``docs/benchmarks.md``).
"""

from __future__ import annotations

import logging
import sqlite3
import time
from collections.abc import Sequence
from contextlib import closing
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

log = logging.getLogger(__name__)

PAGE = 200
"""Flow runs read per request (the API's default limit)."""
BATCH = 5000
"""Rows deleted per statement and transaction of :func:`prune_history` (the server writes
between them)."""
FINISHED = ("COMPLETED", "FAILED", "CRASHED", "CANCELLED")
TABLES = {"flow_run", "events", "event_resources", "log", "artifact", "artifact_collection"}
"""Prefect's tables :func:`prune_history` reads or deletes from (checked before it runs)."""
MARGIN = timedelta(hours=1)
"""History older than the oldest kept flow run by more than this is deleted whatever run it
belonged to (a run's first event can precede its row by the client's clock skew)."""


class RunRetention(BaseModel):
    """How many of Prefect's finished flow runs a build leaves behind."""

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    max_runs: int | None = Field(100, ge=1)
    """Keep the newest this many finished flow runs (None: no count limit)."""
    max_age_days: float | None = Field(30.0, gt=0)
    """Delete finished flow runs that started longer ago than this (None: no age limit)."""
    history: bool = True
    """Also delete the events, event resources, logs and artifacts older than the runs kept
    (:func:`prune_history`); False leaves them to Prefect's own retention."""


@dataclass(frozen=True)
class PruneReport:
    """What :func:`prune_flow_runs` did."""

    kept: int
    deleted: int
    seconds: float
    history: dict[str, int] = field(default_factory=dict)
    """Rows deleted per table by :func:`prune_history` (empty: not run)."""


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
    history: dict[str, int] = {}
    if retention.history:
        try:
            db = local_database(kept)
            if db is None:
                log.info("Prefect's database is not a local SQLite file holding the API's runs: "
                         "its events and logs are left to the server's db_vacuum service")
            else:
                history = prune_history(db, kept, deleted)
        except Exception as exc:  # noqa: BLE001 - housekeeping: say why and go on
            log.warning("Prefect event/log retention skipped: %s: %s", type(exc).__name__, exc)
    return PruneReport(len(kept), len(deleted), time.perf_counter() - t0, history)


def _prune(client, retention: RunRetention) -> tuple[list[str], list[str]]:
    """Delete the flow runs ``retention`` does not keep: (ids kept, ids deleted)."""
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
    gone = set(doomed)
    return [str(r.id) for r in runs if r.id not in gone], [str(d) for d in doomed]


def local_database(kept: list[str]) -> Path | None:
    """The SQLite file of Prefect's current settings when it is the API's database: it exists,
    has Prefect's tables and holds the runs the API just listed (``kept``; with none kept, no
    finished run at all). None otherwise: a server elsewhere, Postgres, another home."""
    from prefect.settings import get_current_settings

    url = get_current_settings().server.database.connection_url
    url = url.get_secret_value() if hasattr(url, "get_secret_value") else url
    prefix = next((p for p in ("sqlite+aiosqlite:///", "sqlite:///") if (url or "").startswith(p)),
                  None)
    if prefix is None:
        return None
    path = Path(url[len(prefix):].split("?")[0])
    if not path.is_file():
        return None
    with closing(_connect(path)) as con:
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        if not TABLES <= tables:
            return None
        sample = kept[:50]
        if sample:
            found = con.execute(f"SELECT count(*) FROM flow_run WHERE id IN "
                                f"({_marks(sample)})", sample).fetchone()[0]
            return path if found == len(sample) else None
        finished = con.execute(f"SELECT count(*) FROM flow_run WHERE state_type IN "
                               f"({_marks(FINISHED)})", FINISHED).fetchone()[0]
        return path if finished == 0 else None


def prune_history(db: Path, kept: Sequence[str], deleted: Sequence[str]) -> dict[str, int]:
    """Delete from Prefect's SQLite database ``db`` the rows that deleting the flow runs
    ``deleted`` left (module docstring): their logs and artifacts (an artifact that is a
    collection's latest stays), the events with one of these runs or artifacts as a resource
    (each task-run event names its flow run) and their event resources; and whatever of
    these is older than :data:`MARGIN` before the oldest kept flow run was created (before now
    with none kept: leftovers of runs deleted earlier, events of no run). Rows deleted per
    table."""
    counts = dict.fromkeys(("events", "event_resources", "log", "artifact"), 0)
    with closing(_connect(db)) as con:
        oldest = None
        for i in range(0, len(kept), 500):
            chunk = list(kept[i:i + 500])
            first = con.execute(f"SELECT min(created) FROM flow_run WHERE id IN "
                                f"({_marks(chunk)})", chunk).fetchone()[0]
            oldest = first if oldest is None or (first and first < oldest) else oldest
        start = datetime.fromisoformat(oldest) if oldest else datetime.now(UTC).replace(
            tzinfo=None)
        cutoff = (start - MARGIN).strftime("%Y-%m-%d %H:%M:%S.%f")
        orphan = ("flow_run_id IS NOT NULL AND {time} < ? AND NOT EXISTS "
                  "(SELECT 1 FROM flow_run f WHERE f.id = {table}.flow_run_id)")
        for temp in ("gone_events", "gone_artifacts"):
            con.execute(f"CREATE TEMP TABLE IF NOT EXISTS {temp} (id TEXT PRIMARY KEY)")
            con.execute(f"DELETE FROM {temp}")
        with con:
            latest = " AND id NOT IN (SELECT latest_id FROM artifact_collection WHERE " \
                     "latest_id IS NOT NULL)"
            for i in range(0, len(deleted), 500):
                chunk = tuple(deleted[i:i + 500])
                con.execute(f"INSERT OR IGNORE INTO gone_artifacts SELECT id FROM artifact WHERE "
                            f"flow_run_id IN ({_marks(chunk)}){latest}", chunk)
            con.execute("INSERT OR IGNORE INTO gone_artifacts SELECT id FROM artifact WHERE "
                        + orphan.format(time="created", table="artifact") + latest, (cutoff,))
            named = [f"prefect.flow-run.{run}" for run in deleted] + [
                f"prefect.artifact.{a}" for (a,) in con.execute("SELECT id FROM gone_artifacts")]
            for resource in named:
                con.execute("INSERT OR IGNORE INTO gone_events SELECT event_id FROM "
                            "event_resources WHERE resource_id = ?", (resource,))
            con.execute("INSERT OR IGNORE INTO gone_events SELECT id FROM events "
                        "WHERE occurred < ?", (cutoff,))
        counts["event_resources"] = _delete(con, "event_resources", "event_id IN (SELECT id FROM "
                                            "gone_events) OR occurred < ?", (cutoff,))
        counts["events"] = _delete(con, "events", "id IN (SELECT id FROM gone_events)", ())
        counts["artifact"] = _delete(con, "artifact", "id IN (SELECT id FROM gone_artifacts)", ())
        for i in range(0, len(deleted), 500):
            chunk = tuple(deleted[i:i + 500])
            counts["log"] += _delete(con, "log", f"flow_run_id IN ({_marks(chunk)})", chunk)
        counts["log"] += _delete(con, "log", orphan.format(time="timestamp", table="log"),
                                 (cutoff,))
    return counts


def _marks(items: Sequence) -> str:
    return ",".join("?" * len(items))


def _connect(path: Path) -> sqlite3.Connection:
    """A connection that waits for the server's writes (SQLite's busy timeout)."""
    con = sqlite3.connect(path, timeout=60)
    con.execute("PRAGMA busy_timeout = 60000")
    return con


def _delete(con: sqlite3.Connection, table: str, cond: str, args: tuple) -> int:
    """Delete ``table``'s rows matching ``cond``, :data:`BATCH` rows per transaction (the
    server writes between them)."""
    total = 0
    while True:
        with con:
            n = con.execute(f"DELETE FROM {table} WHERE id IN (SELECT id FROM {table} "
                            f"WHERE {cond} LIMIT {BATCH})", args).rowcount
        total += n
        if n < BATCH:
            return total
