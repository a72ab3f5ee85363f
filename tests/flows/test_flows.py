"""The session DAG as Prefect tasks: cache keys, retry policy, upstream failures."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from graspcap.flows.cached import reads_digest, stage_key
from graspcap.flows.workarea import ResultRef, WorkArea
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.session.load_session import LoadSessionConfig
from tests.flow_fixtures import PRESET, executions


def _ref(digest: str) -> ResultRef:
    return ResultRef("s", "k", "/nowhere", digest, "b")


def test_stage_key_changes_with_each_ingredient_and_nothing_else(tmp_path):
    work = WorkArea(tmp_path / "work")
    f = tmp_path / "a.bin"
    f.write_bytes(b"abc")
    files = {"x": [f]}
    cfg = LoadSessionConfig()
    base = stage_key("v/1", cfg, reads_digest(work, files, ("x",)), {"up": _ref("d1")})
    assert base == stage_key("v/1", LoadSessionConfig(), reads_digest(work, files, ("x",)),
                             {"up": _ref("d1")})
    assert base != stage_key("v/2", cfg, reads_digest(work, files, ("x",)), {"up": _ref("d1")})
    assert base != stage_key("v/1", LoadSessionConfig(check_images=False),
                             reads_digest(work, files, ("x",)), {"up": _ref("d1")})
    assert base != stage_key("v/1", cfg, reads_digest(work, files, ("x",)), {"up": _ref("d2")})
    f.write_bytes(b"abd")  # same size, new bytes
    assert base != stage_key("v/1", cfg, reads_digest(work, files, ("x",)), {"up": _ref("d1")})


def test_workarea_lookup_ignores_a_result_without_its_record(tmp_path):
    work = WorkArea(tmp_path)
    ref = work.save("st", "k1", {"a": 1}, "b1", seconds=0.5)
    hit = work.lookup("st", "k1")
    assert hit is not None and hit.cached and hit.digest == ref.digest and hit.build_id == "b1"
    assert WorkArea.load(hit) == {"a": 1}
    (tmp_path / "results" / "st" / "k1.json").unlink()  # killed between pickle and record
    assert work.lookup("st", "k1") is None


def test_transient_faults_are_retried_and_deterministic_ones_are_not():
    from graspcap.flows.session import is_transient

    assert is_transient(OSError(5, "I/O error"))
    assert is_transient(TimeoutError())  # an OSError subclass
    assert not is_transient(FileNotFoundError("gone"))
    assert not is_transient(PermissionError("no"))
    # CPython 3.11's ast thread race (python/cpython#106905) is retried, other SystemErrors not
    assert is_transient(SystemError("AST constructor recursion depth mismatch (before=57, "
                                    "after=65)"))
    assert not is_transient(SystemError("something else"))
    assert not is_transient(StageError("fit_hand", "did not converge"))
    assert not is_transient(ValueError("bad"))
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    assert is_transient(KilledWorker("t", "w", 3))
    assert is_transient(CommClosedError("closed"))


def test_session_flow_on_a_warm_work_area_runs_no_stage(warm, synth_root, tmp_path):
    from graspcap.flows.session import session_flow

    catalog, _ = warm
    shutil.copytree(catalog / "work", tmp_path / "work")
    session = sorted(p for p in synth_root.iterdir() if p.is_dir())[0]
    refs = session_flow(str(session), str(tmp_path / "work"), PRESET, build_id="again")
    from graspcap.tasks.pipeline import STAGES

    assert set(refs) == set(STAGES)
    assert all(r.cached for r in refs.values())
    assert executions(tmp_path, "again") == []


def test_downstream_of_a_failed_stage_does_not_run(warm, synth_root, tmp_path, monkeypatch):
    from prefect import flow

    from graspcap.flows.session import submit_session
    from graspcap.tasks import pipeline

    catalog, _ = warm
    shutil.copytree(catalog / "work", tmp_path / "work")
    shutil.rmtree(tmp_path / "work" / "results" / "reconstruct_hand")
    calls = []

    def broken(session, config, **_):
        calls.append(1)
        raise StageError("reconstruct_hand", "solver did not converge", session="x")

    monkeypatch.setitem(pipeline.STAGES, "reconstruct_hand",
                        dataclasses.replace(pipeline.STAGES["reconstruct_hand"], run=broken))
    session = sorted(p for p in synth_root.iterdir() if p.is_dir())[0]

    @flow
    def one():
        futures = submit_session(session, pipeline.configs_for(PRESET),
                                 WorkArea(tmp_path / "work"), "b-fail")
        return {name: f.wait() or f.state for name, f in futures.items()}

    states = one()
    assert states["reconstruct_hand"].is_failed()
    assert len(calls) == 1  # a StageError is not retried
    for name in ("crosscheck_sfm", "fit_hand", "propagate_poses"):
        assert not states[name].is_completed() and not states[name].is_failed()
    assert states["register_scan"].is_completed()  # independent branch still ran (cached)
    assert executions(tmp_path, "b-fail") == []


def test_file_digests_are_remembered_until_the_file_changes(tmp_path, monkeypatch):
    import os

    from graspcap.flows import workarea
    from graspcap.flows.workarea import sha256_file

    work = WorkArea(tmp_path / "work")
    f = tmp_path / "a.bin"
    f.write_bytes(b"one")
    old = 1_700_000_000_000_000_000
    os.utime(f, ns=(old, old))
    hashed = []
    real = workarea.sha256_file
    monkeypatch.setattr(workarea, "sha256_file", lambda p: hashed.append(p) or real(p))
    d1 = work.file_digest(f)
    assert d1 == sha256_file(f) and work.file_digest(f) == d1 and len(hashed) == 1
    assert WorkArea(tmp_path / "work").file_digest(f) == d1 and len(hashed) == 1
    big = tmp_path / "big.bin"  # every file's digest is remembered on disk for other processes
    big.write_bytes(bytes(1 << 20))
    os.utime(big, ns=(old, old))
    db = work.file_digest(big)
    WorkArea._memo.clear()  # as in a new process
    WorkArea._folders.clear()
    assert WorkArea(tmp_path / "work").file_digest(big) == db and len(hashed) == 2
    assert work.file_digest(f) == d1 and len(hashed) == 2  # a small one too: no hash
    assert list((tmp_path / "work" / "digests").glob("dir-*.json"))  # one memo per folder
    WorkArea._memo.clear()
    WorkArea._folders.clear()
    assert WorkArea.reader(tmp_path / "work").file_digest(f) == d1 and len(hashed) == 2
    f.write_bytes(b"two")  # same size, new bytes: a new mtime
    os.utime(f, ns=(old + 1, old + 1))
    assert work.file_digest(f) == sha256_file(f) != d1 and len(hashed) == 3
    WorkArea._memo.clear()  # a new process sees the new digest in the folder memo
    WorkArea._folders.clear()
    assert WorkArea(tmp_path / "work").file_digest(f) == sha256_file(f) and len(hashed) == 3
    g = tmp_path / "b.bin"  # same size and mtime, replaced by a rename: a new inode
    g.write_bytes(b"one")
    os.utime(g, ns=(old + 1, old + 1))
    os.replace(g, f)
    assert work.file_digest(f) == d1 and len(hashed) == 4
    f.write_bytes(b"new")  # modified just now: may change again in the same mtime tick
    for _ in range(2):
        assert work.file_digest(f) == sha256_file(f)
    assert len(hashed) == 6
    WorkArea._memo.clear()  # and the racy digest is not in the folder memo either
    WorkArea._folders.clear()
    assert WorkArea(tmp_path / "work").file_digest(f) == sha256_file(f) and len(hashed) == 7
    # the known risk, documented: same size, mtime_ns and inode, new bytes (written in place
    # and the mtime set back) keeps the remembered digest
    with open(f, "r+b") as out:
        out.write(b"NEW")
    os.utime(f, ns=(old + 2, old + 2))
    d_new = work.file_digest(f)
    with open(f, "r+b") as out:
        out.write(b"nEW")
    os.utime(f, ns=(old + 2, old + 2))
    assert work.file_digest(f) == d_new != sha256_file(f)


def test_results_in_memory_are_keyed_by_their_content_digest(tmp_path):
    work = WorkArea(tmp_path)
    a, b = {"v": np.arange(3)}, {"v": np.arange(4)}
    ref_a = work.save("st", "k", a, "b1")
    ref_b = work.save("st", "k", b, "b2")  # same key and path, other bytes
    assert ref_a.path == ref_b.path and ref_a.digest != ref_b.digest
    assert WorkArea.load(ref_b) is b and WorkArea.load(ref_a) is a  # no read: saved here
    WorkArea._loaded.clear()
    loaded = WorkArea.load(ref_b)
    np.testing.assert_array_equal(loaded["v"], b["v"])
    assert WorkArea.load(ref_b) is loaded  # remembered once read
    WorkArea._loaded.clear()
    wrong = dataclasses.replace(ref_b, digest="0" * 64)  # a ref whose file changed since
    np.testing.assert_array_equal(WorkArea.load(wrong)["v"], b["v"])
    assert "0" * 64 not in WorkArea._loaded  # never remembered under a digest it lacks
    with pytest.raises(FileNotFoundError):
        WorkArea.load(dataclasses.replace(ref_a, path=str(tmp_path / "gone.pkl")))


def test_settle_session_settles_hits_and_failures_and_leaves_the_rest(warm, synth_root,
                                                                      tmp_path):
    from graspcap.flows.session import settle_session
    from graspcap.tasks.pipeline import STAGES, configs_for

    catalog, _ = warm
    shutil.copytree(catalog / "work", tmp_path / "work")
    work = WorkArea(tmp_path / "work")
    session = sorted(p for p in synth_root.iterdir() if p.is_dir())[0]
    configs = configs_for(PRESET)
    settled = settle_session(session, configs, work)
    assert list(settled) == list(STAGES) and {s.state for s in settled.values()} == {"Cached"}
    assert all(s.ref.cached and s.ref.stage == n for n, s in settled.items())
    downstream = {"fit_hand"}
    for name, stage in STAGES.items():  # topological order
        if downstream & set(stage.upstream):
            downstream.add(name)
    key = settled["fit_hand"].ref.key
    for p in (tmp_path / "work" / "results" / "fit_hand").glob(f"{key}.*"):
        p.unlink()
    settled = settle_session(session, configs, work)
    assert set(settled) == set(STAGES) - downstream  # fit_hand and its downstream must run
    work.save_failure("fit_hand", key, "fit_hand", "did not converge", "s", "b")
    settled = settle_session(session, configs, work)
    assert settled["fit_hand"].state == "Failed"
    assert settled["fit_hand"].error.reason == "did not converge"
    assert {settled[n].state for n in downstream - {"fit_hand"}} == {"NotReady"}
    assert set(settle_session(session, configs, work, replay_failures=False)) == (
        set(STAGES) - downstream)


def test_a_session_task_runs_the_stages_left_and_says_how_each_ended(warm, synth_root,
                                                                     tmp_path, monkeypatch):
    """What a Dask worker gets (``per_session=True``): one task for the session's stages that
    must run, each a plain call (no task run of its own); a failed stage's downstream is
    NotReady inside it."""
    from prefect import flow

    from graspcap.flows.session import InSession, Settled, submit_session
    from graspcap.tasks import pipeline

    catalog, _ = warm
    shutil.copytree(catalog / "work", tmp_path / "work")
    for stage in ("fit_hand", "register_scan"):
        shutil.rmtree(tmp_path / "work" / "results" / stage)

    def broken(session, config, **_):
        raise StageError("register_scan", "fitness 0.1 below 0.5", session="x")

    monkeypatch.setitem(pipeline.STAGES, "register_scan",
                        dataclasses.replace(pipeline.STAGES["register_scan"], run=broken))
    session = sorted(p for p in synth_root.iterdir() if p.is_dir())[0]

    @flow
    def one():
        out = submit_session(session, pipeline.configs_for(PRESET), WorkArea(tmp_path / "work"),
                             "b-session", settle=True, per_session=True)
        futures = {id(v.future) for v in out.values() if isinstance(v, InSession)}
        states = {n: v.state for n, v in out.items() if isinstance(v, Settled)}
        inner = next(v for v in out.values() if isinstance(v, InSession)).future.result()
        return len(futures), states, {n: (s.state, s.why) for n, s in inner.items()}

    n_futures, settled, inner = one()
    assert n_futures == 1
    assert settled == {n: "Cached" for n in ("load_session", "register_object",
                                             "detect_keypoints", "select_steady",
                                             "joint_solve", "reconstruct_hand",
                                             "crosscheck_sfm")}
    assert list(inner) == [n for n in pipeline.STAGES if n not in settled]  # DAG order
    assert inner["fit_hand"][0] == "Completed" and inner["estimate_adjustment"][0] == "Completed"
    assert inner["register_scan"] == ("Failed", "session x: register_scan: fitness 0.1 below 0.5")
    for name in ("build_contactmap", "refine_grasp", "propagate_poses", "qa_metrics", "pictures"):
        assert inner[name] == ("NotReady", None), name
    ran = {st for _, st in executions(tmp_path, "b-session")}  # downstream: hits if unchanged
    assert {"fit_hand"} <= ran <= {"fit_hand", "estimate_adjustment"}


def _worker_settings() -> dict:
    """What a build's Dask worker runs with (called in the worker)."""
    import os

    import dask
    import open3d as o3d

    return {"trim": os.environ.get("MALLOC_TRIM_THRESHOLD_"),
            "omp": os.environ.get("OMP_NUM_THREADS"),
            "open3d_threads": o3d.utility.get_max_threads(),
            "profile": dask.config.get("distributed.worker.profile.enabled"),
            "tick": dask.config.get("distributed.admin.tick.interval")}


def test_local_runner_sizes_each_workers_pools_to_its_share_of_the_cores():
    import os

    from graspcap.flows.runtime import task_runner
    from graspcap.flows.worker import THREADS_ENV

    for n in (1, 2):
        kwargs = task_runner(f"local:{n}").cluster_kwargs
        assert kwargs["n_workers"] == n and kwargs["threads_per_worker"] == 1
        assert kwargs["env"][THREADS_ENV] == str(max(1, os.cpu_count() // n))
        assert kwargs["preload"] == ["graspcap.flows.worker"]


@pytest.mark.slow
def test_local_cluster_workers_get_the_build_settings(monkeypatch):
    """``--dask local:1`` as the product makes it: Open3D's pool sized to the worker's cores,
    Dask's profiler off, slow ticks, and no ``MALLOC_TRIM_THRESHOLD_`` from Dask (it fixes
    glibc's mmap threshold: 12x the page faults on the stages)."""
    import os

    from distributed import Client

    from graspcap.flows.runtime import task_runner
    from graspcap.flows.worker import DASK_CONFIG, local_cluster

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    runner = task_runner("local:1")
    assert runner.cluster_class == "graspcap.flows.worker.local_cluster"
    with local_cluster(**runner.cluster_kwargs) as cluster, Client(cluster) as client:
        got = client.submit(_worker_settings, pure=False).result(timeout=120)
    assert got == {"trim": None, "omp": "1", "open3d_threads": os.cpu_count(),
                   "profile": False, "tick": DASK_CONFIG["distributed.admin.tick.interval"]}
    assert "MALLOC_TRIM_THRESHOLD_" not in os.environ  # nor leaked into this process


def test_a_stage_in_a_session_task_retries_transient_faults_only(warm, synth_root, tmp_path,
                                                                 monkeypatch):
    """``run_retrying`` (a stage inside a Dask session task): an ``OSError`` twice, then the
    stage runs; a ``StageError`` is raised at once; every attempt is an execution record."""
    from graspcap.flows import session as fs
    from graspcap.tasks import pipeline

    catalog, _ = warm
    shutil.copytree(catalog / "work", tmp_path / "work")
    shutil.rmtree(tmp_path / "work" / "results" / "register_scan")
    work = WorkArea(tmp_path / "work")
    monkeypatch.setattr(fs, "RETRY_DELAYS_S", [0.0, 0.0, 0.0])
    original = pipeline.STAGES["register_scan"]
    calls = []

    def flaky(session, config, **kw):
        calls.append(1)
        if len(calls) <= 2:
            raise OSError(5, "Input/output error (injected)")
        return original.run(session, config, **kw)

    monkeypatch.setitem(pipeline.STAGES, "register_scan",
                        dataclasses.replace(original, run=flaky))
    session = str(sorted(p for p in synth_root.iterdir() if p.is_dir())[0].resolve())
    up = fs.settle_session(session, pipeline.configs_for(PRESET), work)["load_session"].ref
    ref = fs.run_retrying("register_scan", session, "s0", pipeline.configs_for(PRESET)[
        "register_scan"], work, "b-retry", True, {"load_session": up})
    assert ref.stage == "register_scan" and not ref.cached and len(calls) == 3
    assert [r["ok"] for r in work.executions("b-retry")] == [False, False, True]

    def broken(session, config, **_):
        calls.append(1)
        raise StageError("register_scan", "fitness 0.1 below 0.5", session="x")

    shutil.rmtree(tmp_path / "work" / "results" / "register_scan")
    monkeypatch.setitem(pipeline.STAGES, "register_scan",
                        dataclasses.replace(original, run=broken))
    with pytest.raises(StageError, match="fitness 0.1"):
        fs.run_retrying("register_scan", session, "s0", pipeline.configs_for(PRESET)[
            "register_scan"], work, "b-det", True, {"load_session": up})
    assert len(calls) == 4 and len(work.executions("b-det")) == 1


def test_load_session_file_lists_are_remembered_by_the_result_digest(tmp_path, monkeypatch):
    """A new process reads a ``load_session`` result's file list from the work area's memo
    (named by the result's content digest) instead of unpickling it; ``--plan`` writes none."""
    from graspcap.flows import cached
    from graspcap.flows.workarea import ResultRef

    listing = {"manifest": [tmp_path / "s" / "session.json"],
               "grasp_rgb": [tmp_path / "s" / f"{i}.png" for i in range(3)]}
    loads = []

    class Loaded:
        def input_files(self):
            return {k: list(v) for k, v in listing.items()}

    monkeypatch.setattr(WorkArea, "load", classmethod(lambda cls, ref: loads.append(ref)
                                                      or Loaded()))
    ref = ResultRef("load_session", "k1", str(tmp_path / "r.pkl"), "d" * 64, "b")

    def fresh(work):
        cached._FILES.clear()  # as in a new process
        return cached.loaded_session_files(ref, work)

    assert fresh(WorkArea.reader(tmp_path / "work")) == listing and len(loads) == 1
    assert not (tmp_path / "work").exists()  # a read-only work area writes nothing
    work = WorkArea(tmp_path / "work")
    assert fresh(work) == listing and len(loads) == 2
    assert (tmp_path / "work" / "digests" / f"files-{'d' * 64}.json").exists()
    assert fresh(work) == listing and len(loads) == 2  # from the memo: nothing unpickled
    assert fresh(WorkArea.reader(tmp_path / "work")) == listing and len(loads) == 2
    other = ResultRef("load_session", "k2", str(tmp_path / "r2.pkl"), "e" * 64, "b")
    cached._FILES.clear()
    cached.loaded_session_files(other, work)
    assert len(loads) == 3  # another result: its own list
