"""``--dask ADDRESS`` across processes that share nothing but a folder: a ``dask scheduler``
and two ``dask worker`` processes started on their own, each in its own temporary working
folder, the sessions, work area and catalog on a path all of them reach (here one machine's
disk stands for the shared file system; docs/scale_out.md). A worker killed in the middle of
a stage: the session's task is retried on the other worker, the stages that worker had
finished are cache hits there, and the catalog gets one version."""

from __future__ import annotations

import collections
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from tests.flow_fixtures import PRESET

HOOK = Path(__file__).with_name("dask_kill_hook.py")
KILL_STAGE = "fit_hand"
WORKER_ENV = {  # what flows/worker.py's DASK_CONFIG sets for a local cluster
    "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False",
    "DASK_DISTRIBUTED__ADMIN__TICK__INTERVAL": "1s",
    "GRASPCAP_WORKER_THREADS": "1",
    "OMP_NUM_THREADS": "1",
}


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:  # each started in its own process group: nothing it spawned survives
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    for p in procs:
        p.wait(timeout=30)


class Cluster:
    """A scheduler and ``n`` workers, each a separate process group with its own folder."""

    def __init__(self, base: Path, n: int, env: dict[str, str]):
        self.procs: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        self.logs: list[Path] = []
        file = base / "scheduler.json"  # the scheduler picks a free port and writes it here
        self._start(base / "scheduler", [
            "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
            "--no-dashboard", "--scheduler-file", str(file)], env)
        deadline = time.monotonic() + 120
        while not file.exists() or not file.read_text().strip():
            self._check_alive(deadline, "the scheduler did not write its address")
        self.address = json.loads(file.read_text())["address"]
        for i in range(n):
            self.workers.append(self._start(base / f"worker{i}", [
                "distributed.cli.dask_worker", "--scheduler-file", str(file), "--name", f"w{i}",
                "--nthreads", "1", "--no-nanny", "--no-dashboard", "--local-directory",
                str(base / f"worker{i}" / "dask"), "--preload", "graspcap.flows.worker",
                "--preload", str(HOOK)], {**env, **WORKER_ENV,
                                          "PREFECT_HOME": str(base / f"worker{i}" / "prefect")}))
        from distributed import Client

        with Client(self.address, timeout=60) as client:
            client.wait_for_workers(n, timeout=240)  # after their preloads

    def _start(self, folder: Path, args: list[str], env: dict[str, str]) -> subprocess.Popen:
        folder.mkdir(parents=True)
        log = folder / "log.txt"
        self.logs.append(log)
        with open(log, "wb") as out:
            proc = subprocess.Popen([sys.executable, "-m", *args], cwd=folder, env=env,
                                    stdout=out, stderr=subprocess.STDOUT,
                                    start_new_session=True)
        self.procs.append(proc)
        return proc

    def _check_alive(self, deadline: float, what: str) -> None:
        dead = [p.args for p in self.procs if p.poll() is not None]
        if dead or time.monotonic() > deadline:
            raise RuntimeError(f"{what}; exited: {dead}; logs: " + " | ".join(
                lg.read_text()[-2000:] for lg in self.logs if lg.exists()))
        time.sleep(0.2)


@pytest.fixture
def cluster(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "DASK_"))}
    env.update({"GRASPCAP_TEST_KILL_STAGE": KILL_STAGE,
                "GRASPCAP_TEST_KILL_MARKER": str(tmp_path / "shared" / "killed")})
    (tmp_path / "shared").mkdir()
    c = None
    try:
        c = Cluster(tmp_path / "processes", 2, env)
        yield c
    finally:
        if c is not None:
            _stop(c.procs)


@pytest.mark.slow
def test_a_worker_killed_mid_stage_is_retried_on_the_other_and_commits_once(
        prefect_harness, synth_root, cluster, tmp_path, monkeypatch):
    from graspcap.tasks.pipeline import STAGES

    shared = tmp_path / "shared"  # the path every process reaches: catalog and work area
    marker = shared / "killed"
    killed: dict[str, object] = {}

    def kill_when_claimed() -> None:
        deadline = time.monotonic() + 400
        while time.monotonic() < deadline:
            if marker.exists() and marker.read_text().strip():
                pid, session_dir = marker.read_text().split(" ", 1)
                killed.update(pid=int(pid), session_dir=session_dir)
                os.kill(int(pid), signal.SIGKILL)
                return
            time.sleep(0.1)

    killer = threading.Thread(target=kill_when_claimed, daemon=True)
    killer.start()
    # the build's own working folder is a third one, and its paths are relative to it: the
    # build resolves them before anything reaches a worker
    (tmp_path / "build").mkdir()
    monkeypatch.chdir(tmp_path / "build")
    report = build_dataset([os.path.relpath(synth_root)], "../shared/catalog", PRESET,
                           dask=cluster.address, build_id="remote")
    killer.join(timeout=5)

    workers = {p.pid: p for p in cluster.workers}
    assert killed and killed["pid"] in workers, "no worker reached the stage to kill"
    assert workers[killed["pid"]].wait(timeout=30) == -signal.SIGKILL
    (survivor,) = set(workers) - {killed["pid"]}
    assert report.failed == {} and report.catalog_version == 1

    cat = gc.open(shared / "catalog")
    assert cat.versions().num_rows == 1 and cat.table("builds").num_rows == 1
    ids = sorted(s.session_id for s in report.sessions)
    assert sorted(cat.table("sessions")["session_id"].to_pylist()) == ids
    assert sorted(set(cat.table("frames")["session_id"].to_pylist())) == ids

    recs = [json.loads(line) for line in
            (shared / "catalog" / "work" / "executions.jsonl").read_text().splitlines()]
    assert all(r["ok"] for r in recs), [r for r in recs if not r["ok"]]
    ran = collections.Counter((r["session_id"], r["stage"]) for r in recs)
    assert ran == {(sid, name): 1 for sid in ids for name in STAGES}  # each stage once
    assert {r["pid"] for r in recs} <= set(workers)  # nothing ran in the build's process
    victim = json.loads((Path(killed["session_dir"]) / "session.json").read_text())["session_id"]
    where = {r["stage"]: r["pid"] for r in recs if r["session_id"] == victim}
    assert where[KILL_STAGE] == survivor  # retried on the other worker
    # what the killed worker finished before it died was not run again: its results were
    # already in the shared work area
    assert where["reconstruct_hand"] == killed["pid"]
