"""A Dask worker preload for ``test_dask_cluster.py``: the first worker to start stage
``$GRASPCAP_TEST_KILL_STAGE`` (of any session) claims ``$GRASPCAP_TEST_KILL_MARKER`` (created
with ``O_EXCL``, so exactly one process claims it), writes ``"<pid> <session_dir>"`` into it
and sleeps inside the stage until the test kills it. Every other call, including the retry of
that stage on another worker, runs the real stage. Loaded with ``dask worker --preload
PATH`` after ``graspcap.flows.worker``; does nothing without the two variables."""

from __future__ import annotations

import os
import time

STAGE_ENV = "GRASPCAP_TEST_KILL_STAGE"
MARKER_ENV = "GRASPCAP_TEST_KILL_MARKER"


def dask_setup(worker=None) -> None:
    stage_name, marker = os.environ.get(STAGE_ENV), os.environ.get(MARKER_ENV)
    if not stage_name or not marker:
        return
    from graspcap.tasks import pipeline

    original = pipeline.run_stage

    def run_stage(stage, session_dir, config, results):
        if stage.name == stage_name:
            try:
                fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                return original(stage, session_dir, config, results)
            os.write(fd, f"{os.getpid()} {session_dir}".encode())
            os.close(fd)
            time.sleep(600)  # killed here, mid-stage
        return original(stage, session_dir, config, results)

    pipeline.run_stage = run_stage
