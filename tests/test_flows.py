# ruff: noqa: F811  (fixtures imported from tests.flow_fixtures)
"""The session DAG as Prefect tasks: cache keys, retry policy, upstream failures."""

from __future__ import annotations

import dataclasses
import shutil

from graspcap.catalog.workarea import ResultRef, WorkArea
from graspcap.flows.cached import reads_digest, stage_key
from graspcap.tasks.errors import StageError
from graspcap.tasks.load_session import LoadSessionConfig
from tests.flow_fixtures import PRESET, executions, prefect_harness, synth_root, warm  # noqa: F401


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
