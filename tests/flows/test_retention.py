# ruff: noqa: F811  (fixtures imported from tests.flow_fixtures)
"""Prefect flow-run retention: however many runs, the database keeps the newest N."""

from __future__ import annotations

import time

import pytest

from graspcap.flows.retention import RunRetention, prune_flow_runs
from tests.flow_fixtures import prefect_harness  # noqa: F401


def test_retention_bounds_the_flow_and_task_runs(prefect_harness):
    from prefect import flow, task
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    @task
    def stage(i: int) -> int:
        return i + 1

    @flow(name="graspcap-retention-test")
    def build(i: int) -> int:
        return stage(i) + stage(i + 1)

    with get_client(sync_client=True) as client:
        prune_flow_runs(RunRetention(max_runs=1, max_age_days=None), client)  # a clean start
        before = client.count_flow_runs()
        assert before <= 1
        for i in range(6):
            assert build(i) == 2 * i + 3
        runs = client.read_flow_runs()
        assert len(runs) == client.count_flow_runs() == before + 6
        mine = FlowRunFilter(id=FlowRunFilterId(any_=[r.id for r in runs]))
        deadline = time.monotonic() + 120  # Prefect records task runs from events, later
        while len(client.read_task_runs(flow_run_filter=mine)) < 12 \
                and time.monotonic() < deadline:
            time.sleep(0.5)
        assert len(client.read_task_runs(flow_run_filter=mine)) >= 12
        newest = sorted(runs, key=lambda r: r.start_time, reverse=True)[:3]

        report = prune_flow_runs(RunRetention(max_runs=3, max_age_days=None), client)
        assert report is not None and report.kept == 3 and report.deleted >= 3
        assert client.count_flow_runs() == 3
        left = client.read_flow_runs()
        assert {r.id for r in left} == {r.id for r in newest}
        # their task runs went with them (ON DELETE CASCADE): two per remaining run
        assert len(client.read_task_runs(flow_run_filter=mine)) == 6
        assert client.read_flow_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(
            any_=[r.id for r in runs if r.id not in {n.id for n in newest}]))) == []
        # a second pass deletes nothing more
        again = prune_flow_runs(RunRetention(max_runs=3, max_age_days=None), client)
        assert (again.kept, again.deleted) == (3, 0)


def test_retention_settings_are_checked():
    assert RunRetention() == RunRetention(max_runs=100, max_age_days=30.0)
    with pytest.raises(ValueError, match="max_runs"):
        RunRetention(max_runs=0)
    assert prune_flow_runs(RunRetention(max_runs=None, max_age_days=None)).deleted == 0
