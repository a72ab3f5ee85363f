"""Prefect flow-run retention: however many runs, the database keeps the newest N."""

from __future__ import annotations

import pytest

from graspcap.flows.retention import RunRetention, prune_flow_runs


def test_retention_bounds_the_flow_and_task_runs(prefect_harness):
    """Six finished flow runs of two task runs each, made through the client API (a real
    flow's task runs reach the database later, as events); retention 3 keeps the newest
    three and their six task runs."""
    from prefect import flow, task
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId
    from prefect.states import Completed, Running

    @task
    def stage(i: int) -> int:
        return i + 1

    @flow(name="graspcap-retention-test")
    def build(i: int) -> int:
        return stage(i)

    with get_client(sync_client=True) as client:
        prune_flow_runs(RunRetention(max_runs=1, max_age_days=None), client)  # a clean start
        before = client.count_flow_runs()
        assert before <= 1
        runs = []
        for i in range(6):
            run = client.create_flow_run(build, parameters={"i": i})
            client.set_flow_run_state(run.id, Running())
            for k in range(2):
                client.create_task_run(stage, run.id, dynamic_key=str(k), state=Completed())
            client.set_flow_run_state(run.id, Completed())
            runs.append(client.read_flow_run(run.id))
        assert client.count_flow_runs() == before + 6
        mine = FlowRunFilter(id=FlowRunFilterId(any_=[r.id for r in runs]))
        assert len(client.read_task_runs(flow_run_filter=mine)) == 12
        newest = sorted(runs, key=lambda r: r.start_time, reverse=True)[:3]

        report = prune_flow_runs(RunRetention(max_runs=3, max_age_days=None), client)
        assert report is not None and report.kept == 3 and report.deleted == 3 + before
        assert client.count_flow_runs() == 3
        assert {r.id for r in client.read_flow_runs()} == {r.id for r in newest}
        # their task runs went with them (ON DELETE CASCADE): two per remaining run
        left = client.read_task_runs(flow_run_filter=mine)
        assert sorted(str(t.flow_run_id) for t in left) == sorted(
            str(r.id) for r in newest for _ in range(2))
        # a second pass deletes nothing more
        again = prune_flow_runs(RunRetention(max_runs=3, max_age_days=None), client)
        assert (again.kept, again.deleted) == (3, 0)


def test_retention_settings_are_checked():
    assert RunRetention() == RunRetention(max_runs=100, max_age_days=30.0)
    with pytest.raises(ValueError, match="max_runs"):
        RunRetention(max_runs=0)
    assert prune_flow_runs(RunRetention(max_runs=None, max_age_days=None)).deleted == 0


def _rows(db, sql, args=()):
    import sqlite3
    from contextlib import closing

    with closing(sqlite3.connect(db)) as con:
        return con.execute(sql, args).fetchall()


def test_retention_bounds_events_logs_and_artifacts(prefect_harness):
    """Deleting a flow run leaves its events, event resources, logs and artifacts (no foreign
    key); with ``history`` on, after retention 2 of five runs the per-run tables hold the kept
    runs' rows only, and the kept runs' logs still read through the API."""
    import time

    from prefect import flow
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.actions import ArtifactCreate, LogCreate
    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId
    from prefect.states import Completed, Running
    from prefect.types._datetime import now

    from graspcap.flows.retention import local_database

    @flow(name="graspcap-history-test")
    def build(i: int) -> int:
        return i

    with get_client(sync_client=True) as client:
        prune_flow_runs(RunRetention(max_runs=1, max_age_days=None), client)  # a clean start
        runs = []
        for i in range(5):
            run = client.create_flow_run(build, parameters={"i": i})
            client.set_flow_run_state(run.id, Running())
            client.create_logs([LogCreate(name="graspcap.test", level=30, message=f"run {i} {k}",
                                          timestamp=now("UTC"), flow_run_id=run.id)
                                for k in range(3)])
            client.create_artifact(ArtifactCreate(key="graspcap-qa", type="markdown",
                                                  data=f"run {i}", flow_run_id=run.id))
            client.set_flow_run_state(run.id, Completed())
            runs.append(client.read_flow_run(run.id))
        ids = [str(r.id) for r in runs]
        db = local_database(ids)
        assert db is not None, "the harness's API database is a local SQLite file"

        def run_events(which):
            marks = ",".join("?" * len(which))
            return _rows(db, "SELECT count(DISTINCT event_id) FROM event_resources WHERE "
                         f"resource_id IN ({marks})",
                         [f"prefect.flow-run.{r}" for r in which])[0][0]

        deadline = time.monotonic() + 90  # the server persists events in batches (every
        seen, steady = -1, 0  # 5 s): wait for three per run and no more in 7 s
        while time.monotonic() < deadline and (seen < 3 * len(ids) or steady < 14):
            time.sleep(0.5)
            count = run_events(ids)
            seen, steady = count, (steady + 1 if count == seen else 0)
        assert seen >= 3 * len(ids)  # pending, running, completed per run
        newest = sorted(runs, key=lambda r: r.start_time, reverse=True)[:2]
        kept = [str(r.id) for r in newest]
        gone = [i for i in ids if i not in kept]
        named = "SELECT event_id FROM event_resources WHERE resource_id IN (?, ?)"
        kept_events = {e for (e,) in _rows(db, named, [f"prefect.flow-run.{r}" for r in kept])}

        report = prune_flow_runs(RunRetention(max_runs=2, max_age_days=None), client)
        assert report is not None and report.kept == 2 and report.deleted >= 3
        assert report.history["events"] >= 3 * len(gone)
        # no event names a deleted run; the kept runs' events are all there
        assert run_events(gone) == 0
        left = _rows(db, "SELECT id FROM events WHERE id IN ({})".format(",".join(
            "?" * len(kept_events))), sorted(kept_events))
        assert len(left) == len(kept_events)
        # every event left of this test's runs names a kept run or its artifact (events of
        # other tests' runs may still be arriving from the shared harness's event pipeline)
        mine = ",".join("?" * len(ids))
        unnamed = _rows(db, f"SELECT event, resource_id FROM events e WHERE resource_id IN "
                        f"({mine}) AND NOT EXISTS (SELECT 1 FROM event_resources r "
                        "WHERE r.event_id = e.id AND (r.resource_id IN (?, ?) OR r.resource_id "
                        "IN (SELECT 'prefect.artifact.' || id FROM artifact)))",
                        [f"prefect.flow-run.{r}" for r in ids]
                        + [f"prefect.flow-run.{r}" for r in kept])
        assert not unnamed
        orphans = _rows(db, "SELECT count(*) FROM event_resources r WHERE NOT EXISTS "
                        "(SELECT 1 FROM events e WHERE e.id = r.event_id)")[0][0]
        assert orphans == 0
        logs = _rows(db, f"SELECT flow_run_id, count(*) FROM log WHERE flow_run_id IN ({mine}) "
                     "GROUP BY flow_run_id", ids)
        assert sorted(logs) == sorted((r, 3) for r in kept)
        arts = _rows(db, f"SELECT flow_run_id FROM artifact WHERE flow_run_id IN ({mine})",
                     ids)  # one key, as a build's QA table
        assert sorted(a for (a,) in arts) == sorted(kept)
        read = client.read_logs(LogFilter(flow_run_id=LogFilterFlowRunId(any_=[newest[0].id])))
        assert sorted(x.message for x in read) == [f"run {ids.index(kept[0])} {k}"
                                                   for k in range(3)]
        again = prune_flow_runs(RunRetention(max_runs=2, max_age_days=None), client)
        assert (again.kept, again.deleted) == (2, 0) and not any(again.history.values())
