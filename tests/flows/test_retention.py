# ruff: noqa: F811  (fixtures imported from tests.flow_fixtures)
"""Prefect flow-run retention: however many runs, the database keeps the newest N."""

from __future__ import annotations

import pytest

from graspcap.flows.retention import RunRetention, prune_flow_runs
from tests.flow_fixtures import prefect_harness  # noqa: F401


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
