"""Dataset builds: re-run only what changed, isolate failures, retry transient faults."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.tasks.core.errors import StageError
from tests.conftest import REPO
from tests.flow_fixtures import (
    PRESET,
    copy_catalog,
    executions,
    fit_hand_failing_for,
    require_pipeline_passes,
)
from tests.report_html import check_page


def _sessions(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if (p / "session.json").exists())


def _ids(root: Path) -> list[str]:
    return [json.loads((p / "session.json").read_text())["session_id"] for p in _sessions(root)]


def _tweak(config):
    """The config with its first float field moved by 10 % (a real parameter change)."""
    for name, value in config.model_dump().items():
        if isinstance(value, float) and value != 0:
            return config.model_copy(update={name: value * 1.1})
    raise AssertionError(f"{type(config).__name__} has no float field to change")


def test_cold_build_runs_every_stage_and_commits_one_version(warm, synth_root):
    from graspcap.tasks.pipeline import STAGES

    catalog, report = warm
    ids = _ids(synth_root)
    assert report.catalog_version == 1 and sorted(report.added) == sorted(ids)
    assert executions(catalog, "warm") == sorted((s, st) for s in ids for st in STAGES)
    cat = gc.open(catalog)
    sessions = cat.table("sessions").to_pylist()
    assert sorted(r["session_id"] for r in sessions) == sorted(ids)
    assert all(r["status"] in ("ok", "flagged") and r["error"] is None for r in sessions)
    # the fixture sessions carry OpenPose JSON, so that backend ran; its frames with a hand
    from graspcap.tasks.keypoints.detect_keypoints import PRESETS as DETECT_PRESETS
    from graspcap.tasks.keypoints.detect_keypoints import detect_keypoints
    from graspcap.tasks.session.load_session import load_session

    dirs = dict(zip(_ids(synth_root), _sessions(synth_root), strict=True))
    for r in sessions:
        kp = detect_keypoints(load_session(dirs[r["session_id"]]),
                              DETECT_PRESETS.get(PRESET, DETECT_PRESETS["default"]))
        assert r["keypoint_backend"] == "openpose_json" == str(kp.backend)
        assert r["keypoint_frames_detected"] == kp.frames_with_hand > 0
    frames = cat.table("frames")
    for r in sessions:
        count = json.loads((synth_root / r["session_id"] / "session.json").read_text()
                           )["grasp"]["count"] if (synth_root / r["session_id"]).exists() else None
        n = sum(1 for s in frames["session_id"].to_pylist() if s == r["session_id"])
        assert count is None or n == count - r["steady_from"]
        values, observed = cat.contactmap(r["session_id"])
        assert len(values) == len(observed) > 0
    build = cat.table("builds").sort_by("catalog_version").to_pylist()[-1]
    record = json.loads(build["parameters_json"])["report"]
    assert {s["session_id"]: len(s["ran"]) for s in record["sessions"]} == {
        s: len(STAGES) for s in ids}


def test_unchanged_rebuild_runs_nothing_and_makes_no_version(warm, synth_root, tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    report = build_dataset([synth_root], catalog, PRESET, build_id="noop")
    assert executions(catalog, "noop") == []
    assert report.catalog_version is None and report.previous_version == 1
    assert sorted(report.unchanged) == sorted(_ids(synth_root))
    assert "nothing changed" in report.summary()
    assert gc.open(catalog).latest_version() == 1


def test_a_build_with_nothing_to_run_or_write_starts_no_prefect(warm, synth_root, tmp_path,
                                                                monkeypatch):
    """No API server, no flow run: the record in builds.jsonl and the report page as any
    build without a version writes them; ``flow_when_idle`` makes the flow run all the same."""
    import graspcap.flows.build as build
    from graspcap.flows.workarea import BUILDS_LOG

    catalog = copy_catalog(warm[0], tmp_path / "catalog")

    def no_prefect(*_, **__):
        raise AssertionError("Prefect started for a build with nothing to do")

    with monkeypatch.context() as m:
        m.setattr(build, "worker_api", no_prefect)
        m.setattr(build, "prune_flow_runs", no_prefect)
        m.setattr(build, "_qa_artifact", no_prefect)
        events = []
        report = build_dataset([synth_root], catalog, PRESET, build_id="quiet",
                               progress=events.append)
    assert report.catalog_version is None and sorted(report.unchanged) == sorted(
        _ids(synth_root))
    from graspcap.tasks.pipeline import STAGES

    assert len(events) == len(STAGES) * 2 and events[-1].sessions_done == 2
    assert all(e.state == "Cached" for e in events)
    records = [json.loads(line) for line in
               (catalog / "work" / BUILDS_LOG).read_text().splitlines()]
    quiet = [r for r in records if r["build_id"] == "quiet"]
    assert len(quiet) == 1 and quiet[0]["catalog_version"] is None
    # no session's keys changed: the record lists none (its size does not grow with them)
    assert "flow_run_id" not in quiet[0]["parameters"] and quiet[0]["keys"] == {}
    assert report.report_page and Path(report.report_page).exists()
    # the unchanged sessions are counted, not listed; the page and status still show them
    assert quiet[0]["sessions"] == [] and quiet[0]["summary"]["unchanged"] == 2
    assert quiet[0]["unlisted"]["sessions"] == 2
    page = check_page(Path(report.report_page))
    assert sorted(r.session_id for r in page.rows) == sorted(_ids(synth_root))
    assert all(len(r.images) == 4 and "unchanged" in r.text for r in page.rows)
    from graspcap.flows.commands import status_text

    status = status_text(catalog)
    assert ("build quiet (no new version): 0 added, 0 changed, 2 unchanged, 0 failed; 0 stage "
            f"run(s), {2 * len(STAGES)} cache hit(s)") in status
    assert "\n    2 more unchanged (every stage cached)" in status
    assert build._HANDOFF == {}
    flowed = build_dataset([synth_root], catalog, PRESET, build_id="flowed",
                           flow_when_idle=True)
    assert flowed.parameters.get("flow_run_id") and flowed.catalog_version is None
    assert flowed.unchanged == report.unchanged and build._HANDOFF == {}


def test_rows_from_before_the_keypoint_columns_are_rewritten_from_cached_results(
        warm, synth_root, tmp_path):
    """Rows of a migrated catalog have null keypoint columns; the next build fills them in
    without running a stage (the results are in the work area)."""
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    cat = gc.open(catalog)
    filled = cat.table("sessions")
    old = filled
    for col in ("keypoint_backend", "keypoint_frames_detected"):
        i = old.schema.get_field_index(col)
        old = old.set_column(i, old.schema.field(i), pa.nulls(old.num_rows, old.schema[i].type))
    v = cat.commit(gc.BuildCommit(gc.BuildInfo("pre-columns", "old", "x" * 64), sessions=old,
                                  frames=cat.table("frames")))
    assert cat.table("sessions", v)["keypoint_backend"].null_count == old.num_rows
    report = build_dataset([synth_root], catalog, PRESET, build_id="fill")
    assert executions(catalog, "fill") == []
    assert report.catalog_version == v + 1 and sorted(report.changed) == sorted(_ids(synth_root))
    new = cat.table("sessions", v + 1).sort_by("session_id")
    filled = filled.sort_by("session_id")
    for col in ("keypoint_backend", "keypoint_frames_detected"):
        assert new[col].to_pylist() == filled[col].to_pylist(), col
    assert set(new["keypoint_backend"].to_pylist()) == {"openpose_json"}


def test_config_change_reruns_that_stage_and_downstream_only(warm, synth_root, tmp_path):
    from graspcap.tasks.pipeline import STAGES, configs_for

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    changed = _tweak(configs_for(PRESET)["register_scan"])
    report = build_dataset([synth_root], catalog, PRESET,
                           overrides={"register_scan": changed}, build_id="cfg")
    downstream = {"register_scan"}
    for name, stage in STAGES.items():  # topological order
        if downstream & set(stage.upstream):
            downstream.add(name)
    ran = executions(catalog, "cfg")
    assert {st for _, st in ran} <= downstream and "register_scan" in {st for _, st in ran}
    assert sorted(s for s, st in ran if st == "register_scan") == sorted(_ids(synth_root))
    assert report.failed == {}
    assert report.catalog_version == 2  # config_digest of every row changed


def test_file_change_reruns_only_its_readers_in_that_session(synth_root, tmp_path,
                                                             prefect_harness):
    from graspcap.tasks.pipeline import STAGES

    root = tmp_path / "sessions"
    for s in _sessions(synth_root):
        shutil.copytree(s, root / s.name)
    catalog = tmp_path / "catalog"
    first = build_dataset([root], catalog, PRESET, build_id="b1")
    require_pipeline_passes(first)
    assert first.catalog_version == 1
    target = _sessions(root)[0]
    depth_png = target / json.loads((target / "session.json").read_text()
                                    )["scan"]["views"][0]["depth"]
    depth = cv2.imread(str(depth_png), cv2.IMREAD_UNCHANGED)
    ys, xs = np.nonzero(depth)
    depth[ys[0], xs[0]] += 1  # one millimetre on one pixel
    assert cv2.imwrite(str(depth_png), depth)
    second = build_dataset([root], catalog, PRESET, build_id="b2")
    sid = _ids(root)[0]
    readers = {n for n, st in STAGES.items() if "scan_depth" in st.reads}
    allowed = readers - {"load_session"}
    for name, stage in STAGES.items():  # topological order: add the downstream stages
        if allowed & set(stage.upstream):
            allowed.add(name)
    ran = executions(catalog, "b2")
    assert {s for s, _ in ran} == {sid}
    stages_ran = {st for _, st in ran}
    # every reader of the file re-runs; downstream of them only what could see a change
    # (a stage whose upstream result came out byte-identical is a cache hit: early cutoff);
    # load_session reads every file but its result is unchanged, so nothing else re-runs
    assert readers <= stages_ran <= allowed | {"load_session"}, ran
    for name in stages_ran - readers:
        assert set(STAGES[name].upstream) & stages_ran, (name, ran)
    assert second.catalog_version == 2 and sid in second.changed


def test_malformed_session_is_reported_and_the_good_ones_are_kept(warm, synth_root, tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    bad = tmp_path / "more" / "bad"
    shutil.copytree(_sessions(synth_root)[0], bad)
    manifest = json.loads((bad / "session.json").read_text())
    manifest["session_id"] = "bad-one"
    del manifest["depth_scale_m"]
    (bad / "session.json").write_text(json.dumps(manifest))
    report = build_dataset([synth_root, tmp_path / "more"], catalog, PRESET, build_id="mixed")
    assert set(report.failed) == {"bad-one"}
    assert "session.json" in report.failed["bad-one"]
    assert "depth_scale_m" in report.failed["bad-one"]
    assert sorted(report.unchanged) == sorted(_ids(synth_root))
    cat = gc.open(catalog)
    rows = {r["session_id"]: r for r in cat.table("sessions").to_pylist()}
    assert rows["bad-one"]["status"] == "failed" and "depth_scale_m" in rows["bad-one"]["error"]
    assert all(rows[s]["status"] != "failed" for s in _ids(synth_root))
    build = cat.table("builds").sort_by("catalog_version").to_pylist()[-1]
    assert [f["session_id"] for f in build["sessions_failed"]] == ["bad-one"]

    # fix it; --retry-failed touches only the session that failed
    manifest["depth_scale_m"] = 0.001
    (bad / "session.json").write_text(json.dumps(manifest))
    retry = build_dataset([synth_root, tmp_path / "more"], catalog, PRESET,
                          retry_failed=True, build_id="retry")
    assert [s.session_id for s in retry.sessions] == ["bad-one"]
    assert {s for s, _ in executions(catalog, "retry")} == {"bad-one"}
    assert retry.failed == {} and retry.changed == ["bad-one"]
    assert gc.open(catalog).table("sessions").num_rows == 3


def test_transient_fault_is_retried_and_recorded(warm, synth_root, tmp_path, monkeypatch):
    from graspcap.tasks import pipeline

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    shutil.rmtree(catalog / "work" / "results" / "register_scan")
    original = pipeline.STAGES["register_scan"]
    lock, failures = threading.Lock(), [0]

    def flaky(session, config, **kw):
        with lock:
            failures[0] += 1
            fail = failures[0] <= 2
        if fail:
            raise OSError(5, "Input/output error (injected)")
        return original.run(session, config, **kw)

    monkeypatch.setitem(pipeline.STAGES, "register_scan",
                        dataclasses.replace(original, run=flaky))
    report = build_dataset([synth_root], catalog, PRESET, build_id="flaky")
    assert report.failed == {}
    assert sum(s.retries.get("register_scan", 0) for s in report.sessions) == 2
    recs = [json.loads(x) for x in (catalog / "work" / "executions.jsonl").read_text()
            .splitlines()]
    bad = [r for r in recs if r["build_id"] == "flaky" and not r["ok"]]
    assert len(bad) == 2 and all("OSError" in r["error"] for r in bad)
    scans = [s for s, st in executions(catalog, "flaky") if st == "register_scan"]
    assert sorted(scans) == sorted(_ids(synth_root))
    # the retries are in the build record: the catalog's builds table and the work area log
    builds = gc.open(catalog).table("builds").sort_by("catalog_version").to_pylist()
    in_catalog = json.loads(builds[-1]["parameters_json"])["report"]
    in_log = json.loads((catalog / "work" / "builds.jsonl").read_text().splitlines()[-1])
    for rec in (in_catalog, in_log):
        assert rec["build_id"] == "flaky"
        assert sum(s["retries"].get("register_scan", 0) for s in rec["sessions"]) == 2
    from graspcap.flows.commands import status_text

    assert "retries: {'register_scan': " in status_text(catalog)


def test_failed_session_keeps_its_previous_good_rows(warm, synth_root, tmp_path, monkeypatch):
    from graspcap.tasks import pipeline

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    shutil.rmtree(catalog / "work" / "results" / "register_scan")
    calls = []

    def broken(session, config, **_):
        calls.append(session.session_id)
        raise StageError("register_scan", "fitness 0.1 below 0.5", session=session.session_id)

    monkeypatch.setitem(pipeline.STAGES, "register_scan",
                        dataclasses.replace(pipeline.STAGES["register_scan"], run=broken))
    before = gc.open(catalog).table("sessions").to_pylist()
    report = build_dataset([synth_root], catalog, PRESET, build_id="broken")
    assert sorted(calls) == sorted(_ids(synth_root))  # once each: never retried
    assert set(report.failed) == set(_ids(synth_root))
    assert all(s.kept_previous for s in report.sessions)
    assert all("fitness 0.1 below 0.5" in e for e in report.failed.values())
    cat = gc.open(catalog)
    assert report.catalog_version == 2  # the failure is recorded ...
    after = cat.table("sessions").to_pylist()
    assert [r["build_id"] for r in after] == [r["build_id"] for r in before]  # ... rows kept
    last = cat.table("builds").sort_by("catalog_version").to_pylist()[-1]
    record = json.loads(last["parameters_json"])["report"]
    assert set(record["summary"]["failed"]) == set(_ids(synth_root))


KILL_SCRIPT = """
import sys
from graspcap.flows.runtime import configure
configure(sys.argv[3])
from graspcap.flows.build import build_dataset
build_dataset([sys.argv[1]], sys.argv[2], "fast", build_id="killed")
"""


@pytest.mark.slow
def test_build_killed_half_way_completes_on_rerun(synth_root, tmp_path, prefect_harness):
    from graspcap.tasks.pipeline import STAGES

    catalog = tmp_path / "catalog"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("PREFECT_API_URL", None)
    env.pop("PREFECT_HOME", None)
    child = subprocess.Popen([sys.executable, "-c", KILL_SCRIPT, str(synth_root), str(catalog),
                              str(tmp_path / "prefect-work")], env=env, cwd=REPO)
    total = 2 * len(STAGES)
    deadline = time.monotonic() + 600
    while len(executions(catalog, "killed")) < total // 2 and child.poll() is None:
        assert time.monotonic() < deadline, "child build made no progress"
        time.sleep(0.2)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    done_before = len(executions(catalog, "killed"))
    assert 0 < done_before < total
    report = build_dataset([synth_root], catalog, PRESET, build_id="rerun")
    require_pipeline_passes(report)
    rerun = executions(catalog, "rerun")
    assert len(rerun) + done_before >= total and len(rerun) <= total - done_before + 2
    assert report.failed == {} and report.catalog_version == 1
    cat = gc.open(catalog)
    assert sorted(cat.table("sessions")["session_id"].to_pylist()) == sorted(_ids(synth_root))
    assert set(cat.table("frames")["session_id"].to_pylist()) == set(_ids(synth_root))


@pytest.mark.slow
def test_dask_local_cluster_builds_the_same_tables(warm, synth_root, tmp_path):
    catalog = tmp_path / "catalog"
    report = build_dataset([synth_root], catalog, PRESET, dask="local:2", build_id="dask",
                           work=tmp_path / "work")
    assert report.failed == {}
    from graspcap.tasks.pipeline import STAGES

    assert len(executions(tmp_path, "dask")) == len(warm[1].sessions) * len(STAGES)
    drop = ["build_id", "code_version"]
    # array digests hash the bytes, which differ in the last bits like the floats below;
    # the arrays themselves are compared up to rounding instead
    drop += ["contact_digest", "hand_mesh_digest", "object_mesh_digest"]
    cat_a, cat_b = gc.open(warm[0]), gc.open(catalog)
    a = cat_a.table("sessions").drop(drop).sort_by("session_id")
    b = cat_b.table("sessions").drop(drop).sort_by("session_id")
    _assert_same_table(a, b)
    for sid in a.column("session_id").to_pylist():
        for x, y in zip((*cat_a.contactmap(sid), *cat_a.hand_mesh(sid)),
                        (*cat_b.contactmap(sid), *cat_b.hand_mesh(sid)), strict=True):
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    order = [("session_id", "ascending"), ("frame", "ascending")]
    fa = gc.open(warm[0]).table("frames").drop(["build_id"]).sort_by(order)
    fb = gc.open(catalog).table("frames").drop(["build_id"]).sort_by(order)
    _assert_same_table(fa, fb)


def _assert_same_table(a, b) -> None:
    """Equal tables, floats up to rounding: worker processes and threads may sum in another
    order (seen: differences in the 16th digit of pose entries), nothing more."""
    import pyarrow as pa

    assert a.schema == b.schema and a.num_rows == b.num_rows
    for name in a.column_names:
        ca, cb = a.column(name).combine_chunks(), b.column(name).combine_chunks()
        t = ca.type
        if pa.types.is_floating(t) or (hasattr(t, "value_type")
                                       and pa.types.is_floating(t.value_type)):
            va = np.asarray(ca.flatten() if hasattr(t, "value_type") else ca, dtype=float)
            vb = np.asarray(cb.flatten() if hasattr(t, "value_type") else cb, dtype=float)
            assert ca.is_null().equals(cb.is_null()), name
            np.testing.assert_allclose(va, vb, rtol=1e-9, atol=1e-12, equal_nan=True,
                                       err_msg=name)
        else:
            assert ca.equals(cb), name


@pytest.mark.slow
def test_serve_runs_the_build_on_a_schedule_with_its_own_server(synth_root, tmp_path,
                                                                 prefect_harness):
    catalog = tmp_path / "catalog"
    env = {k: v for k, v in os.environ.items()
           if k not in ("PREFECT_API_URL", "PREFECT_HOME")} | {"OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "graspcap.cli", "serve", str(synth_root),
                             "--catalog", str(catalog), "--preset", PRESET, "--interval", "5"],
                            env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    log = catalog / "work" / "builds.jsonl"
    deadline = time.monotonic() + 600
    try:
        while not log.exists() and proc.poll() is None:
            assert time.monotonic() < deadline, "no scheduled build within 600 s"
            time.sleep(1)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert log.exists(), out[-3000:]
    assert "Prefect server (UI and API) at http://127.0.0.1:" in out
    assert gc.open(catalog).latest_version() == 1
    port = out.split("http://127.0.0.1:")[1].split()[0].strip("/")
    import socket

    with socket.socket() as s:  # the supervised server is gone
        assert s.connect_ex(("127.0.0.1", int(port))) != 0


def test_progress_reports_every_task_and_the_qa_artifact_is_made(warm, synth_root, tmp_path):
    import io

    from graspcap.flows.progress import _SINK, ConsoleProgress
    from graspcap.tasks.pipeline import STAGES

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    events = []
    stream = io.StringIO()  # not a TTY: plain lines
    console = ConsoleProgress(stream)

    def sink(event):
        events.append(event)
        console(event)

    with console:
        report = build_dataset([synth_root], catalog, PRESET, build_id="progress",
                               progress=sink, flow_when_idle=True)  # a flow run: the artifact
    assert _SINK.get() is None  # scoped to the call
    ids = _ids(synth_root)
    assert sorted((e.session_id, e.stage) for e in events) == sorted(
        (s, st) for s in ids for st in STAGES)
    assert [e.done for e in events] == list(range(1, len(events) + 1))
    assert all(e.total == len(events) and e.sessions_total == len(ids) for e in events)
    assert sorted(e.session_id for e in events if e.session_done) == sorted(ids)
    assert events[-1].sessions_done == len(ids)
    assert all(e.state == "Cached" for e in events)  # settled in the flow, no task run
    lines = stream.getvalue().splitlines()
    assert len(lines) == len(ids) and all("all stages done" in ln for ln in lines)
    assert not console.tty and "\x1b[" not in stream.getvalue()

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(
            key=ArtifactFilterKey(any_=["graspcap-build-qa"])))
    latest = max(arts, key=lambda a: a.created)
    table = latest.data if isinstance(latest.data, list) else json.loads(latest.data)
    assert sorted(r["session"] for r in table) == sorted(ids)
    assert all(r["outcome"] == "unchanged" and r["cached"] == len(STAGES) for r in table)
    assert report.build_id in latest.description
    # every session (unchanged ones too) with every qa_* value and the flag reasons, every
    # row with the same columns (the UI takes them from the first row)
    from graspcap.schemas.qa import qa_columns

    metrics = [m.column for m in qa_columns()]
    assert all(list(r) == list(table[0]) for r in table)
    assert {"flags", "qa_notes", *metrics} <= set(table[0])
    stored = {r["session_id"]: r for r in gc.open(catalog).table("sessions").to_pylist()}
    for r in table:
        row = stored[r["session"]]
        assert r["status"] == row["status"]
        assert r["flags"] == "; ".join(row["qa_flags"] or ())
        for m in metrics:
            v = row[m]
            assert r[m] == (None if isinstance(v, float) and v != v else v), m
    assert any(r[m] is not None for r in table for m in metrics)


def test_console_progress_draws_bars_on_a_terminal():
    import io

    from graspcap.flows.progress import ConsoleProgress, StageEvent

    stream = io.StringIO()
    with ConsoleProgress(stream, tty=True) as console:
        for i, (sid, stage) in enumerate([("a", "s1"), ("b", "s1"), ("a", "s2"), ("b", "s2")]):
            console(StageEvent(sid, stage, "Completed" if sid == "a" else "Failed", i + 1, 4,
                               i >= 2, max(i - 1, 0), 2))
    out = stream.getvalue()
    assert "\x1b[" in out  # drawn with terminal control codes
    assert "sessions" in out and "stages" in out and "2/2" in out and "4/4" in out
    assert console.failed == {"b": "s1"}


def test_retry_failed_reruns_only_the_tasks_that_did_not_complete(warm, synth_root, tmp_path,
                                                                  monkeypatch):
    from graspcap.tasks import pipeline

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    for stage in ("crosscheck_sfm", "fit_hand", "estimate_adjustment", "propagate_poses"):
        shutil.rmtree(catalog / "work" / "results" / stage)
    good, bad = _ids(synth_root)
    with monkeypatch.context() as m:
        m.setitem(pipeline.STAGES, "fit_hand", fit_hand_failing_for(bad))
        first = build_dataset([synth_root], catalog, PRESET, build_id="half")
    assert set(first.failed) == {bad}
    # the report page: the failure first, with its reason, though the rows kept are ok
    page = check_page(Path(first.report_page))
    assert [(r.session_id, r.status) for r in page.rows][0] == (bad, "failed")
    assert {r.session_id for r in page.rows} == {good, bad} and len(page.rows) == 2
    assert "did not converge (injected)" in first.failed[bad]
    assert (f"failed in this build (its previous rows are kept): {first.failed[bad]}"
            in page.row_text(bad))
    assert len(page.rows[0].images) == 4  # the kept rows' pictures, from the build of them
    ran_first = executions(catalog, "half")
    assert (bad, "crosscheck_sfm") in ran_first  # completed in the failed session
    assert (bad, "fit_hand") not in ran_first  # failed: recorded, but not ok

    # unchanged: the deterministic failure is replayed from the work area, nothing runs
    plain = build_dataset([synth_root], catalog, PRESET, build_id="plain")
    assert executions(catalog, "plain") == [] and plain.failed == first.failed
    assert plain.executed == 0
    assert plain.catalog_version is None  # the failure is already recorded: no new version
    recs = (catalog / "work" / "executions.jsonl").read_text()
    assert '"build_id":"plain"' not in recs  # not even a failed attempt

    retry = build_dataset([synth_root], catalog, PRESET, retry_failed=True, build_id="again")
    assert [s.session_id for s in retry.sessions] == [bad] and retry.failed == {}
    # only the failed task and the ones it kept from running (those whose stored result was
    # removed must run; the others may hit the cache); the completed sibling is cached
    downstream = {"fit_hand"}
    for name, stage in pipeline.STAGES.items():  # topological order
        if downstream & set(stage.upstream):
            downstream.add(name)
    ran = executions(catalog, "again")
    assert {s for s, _ in ran} == {bad}
    assert {"fit_hand", "estimate_adjustment", "propagate_poses"} <= {st for _, st in ran}
    assert {st for _, st in ran} <= downstream
    (s,) = retry.sessions
    assert "crosscheck_sfm" in s.cached and "reconstruct_hand" in s.cached
