"""`graspcap catalog vacuum --work`: cached stage results no build needs are deleted, the ones
the newest build used and each session's latest run stay, and a real build records its keys."""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import pytest

import graspcap.catalog as gc
from graspcap.cli import main
from graspcap.flows.build_log import session_keys
from graspcap.flows.work_vacuum import vacuum_work
from tests.flow_fixtures import copy_catalog

HOUR = 3600.0


def _result(folder: Path, key: str, size: int, age_s: float) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{key}.pkl").write_bytes(b"p" * size)
    (folder / f"{key}.json").write_text(json.dumps({"digest": "d", "bytes": size}))
    for f in (folder / f"{key}.pkl", folder / f"{key}.json"):
        t = time.time() - age_s
        os.utime(f, (t, t))


def _work_area(work: Path, keys: dict | None = None) -> Path:
    """Stage ``s``: ``used`` (the newest build's), ``retried`` (session c's, whose newest build
    is the one before), ``latest`` (a session's latest run), ``old`` (session a's in the build
    before: replaced), ``young`` (neither, written just now), an old unrecorded pickle and a
    remembered failure; stage ``t``: ``gone`` (neither)."""
    s = work / "results" / "s"
    for key in ("used", "latest", "old"):
        _result(s, key, 100, 2 * HOUR)
    _result(s, "young", 100, 0.0)
    _result(work / "results" / "t", "gone", 50, 2 * HOUR)
    (s / "orphan.pkl").write_bytes(b"x" * 10)
    os.utime(s / "orphan.pkl", (time.time() - 2 * HOUR,) * 2)
    (s / "failing.failed.json").write_text('{"reason": "no platter plane"}')
    (s / "latest").mkdir()
    (s / "latest" / "0123.json").write_text(json.dumps({"key": "latest", "ok": True}))
    _result(s, "retried", 100, 2 * HOUR)  # session c's: its newest build is b0
    records = [{"build_id": "b0", "keys": {"a": {"s": "old"}, "c": {"s": "retried"}}},
               {"build_id": "b1", **({"keys": keys} if keys is not None else {})}]
    (work / "builds.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return s


def test_vacuum_work_removes_what_no_build_needs(tmp_path, capsys):
    cat = gc.open(tmp_path / "cat", create=True)
    s = _work_area(cat.layout.root / "work", keys={"a": {"s": "used"}, "b": {"s": "used"}})
    assert main(["catalog", "vacuum", "--work", "--catalog", str(cat.layout.root)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    freed = 100 + len(json.dumps({"digest": "d", "bytes": 100})) + 50 + len(
        json.dumps({"digest": "d", "bytes": 50})) + 10
    assert out == (f"work area: removed 3 cached stage result(s) (s 2, t 1), {freed:,} bytes "
                   f"({freed / 1e6:.2f} MB) freed; kept 4 (0.00 MB): those each session's "
                   "newest build used, its latest run of each stage, and those of the last "
                   "hour\n")
    assert sorted(p.name for p in s.iterdir()) == [
        "failing.failed.json", "latest", "latest.json", "latest.pkl", "retried.json",
        "retried.pkl", "used.json", "used.pkl", "young.json", "young.pkl"]
    assert list((s.parent / "t").iterdir()) == []


def test_vacuum_work_refuses_when_the_newest_build_did_not_record_its_keys(tmp_path, capsys):
    cat = gc.open(tmp_path / "cat", create=True)
    s = _work_area(cat.layout.root / "work", keys=None)
    before = sorted(p.name for p in s.iterdir())
    assert main(["catalog", "vacuum", "--work", "--catalog", str(cat.layout.root)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (f"graspcap catalog vacuum: {cat.layout.root / 'work' / 'builds.jsonl'}: the "
                   "newest build (b1) did not record which stage results it used (written by "
                   "an older graspcap), so nothing is removed; run `graspcap build` once, then "
                   "vacuum --work again\n")
    assert sorted(p.name for p in s.iterdir()) == before


def test_a_build_records_the_result_every_stage_used(warm, tmp_path):  # noqa: F811
    from graspcap.tasks.pipeline import STAGES

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    work = catalog / "work"
    record = json.loads((work / "builds.jsonl").read_text().splitlines()[-1])
    sessions = {s.session_id for s in warm[1].sessions}
    assert set(record["keys"]) == sessions
    for keys in record["keys"].values():
        assert set(keys) == set(STAGES)
        for stage, key in keys.items():
            assert (work / "results" / stage / f"{key}.pkl").is_file()
    # every stored result is one the build used: nothing to remove, even with no grace period
    report = vacuum_work(work, min_age_s=0)
    assert report.removed_results == 0 and report.kept_results == len(sessions) * len(STAGES)
    # a result of an earlier config of a stage (not used, not the latest run) goes
    stage = "qa_metrics"
    key = next(iter(record["keys"].values()))[stage]
    for suffix in (".pkl", ".json"):
        shutil.copy(work / "results" / stage / f"{key}{suffix}",
                    work / "results" / stage / f"{'0' * 64}{suffix}")
    report = vacuum_work(work, min_age_s=0)
    assert (report.removed_results, report.removed_by_stage) == (1, {stage: 1})
    assert not (work / "results" / stage / f"{'0' * 64}.pkl").exists()
    assert (work / "results" / stage / f"{key}.pkl").exists()
    assert session_keys(work)[0] == record["keys"]


@pytest.mark.slow  # four builds, 2-5 min on 2 cores; the vacuum's default tests above
def test_after_one_session_changed_its_replaced_results_go_and_the_others_stay(
        warm, synth_root, tmp_path):
    """Build, rebuild unchanged, change one session (a scan depth pixel), rebuild, vacuum:
    the unchanged rebuild's record lists no keys, the next one that session's keys only; the
    results of the unchanged session and the changed session's new ones stay, the ones its
    new keys replaced go."""
    import cv2
    import numpy as np

    from graspcap.flows.build import build_dataset
    from graspcap.tasks.pipeline import STAGES
    from tests.flow_fixtures import PRESET, executions

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    work = catalog / "work"
    root = tmp_path / "sessions"
    dirs = sorted(p for p in Path(synth_root).iterdir() if (p / "session.json").exists())
    for d in dirs:
        shutil.copytree(d, root / d.name)
    warm_keys, _ = session_keys(work)
    build_dataset([root], catalog, PRESET, build_id="first")  # the copies' paths: some run
    before, _ = session_keys(work)
    same = build_dataset([root], catalog, PRESET, build_id="same")
    assert executions(catalog, "same") == [] and same.catalog_version is None
    target = root / dirs[0].name
    sid = json.loads((target / "session.json").read_text())["session_id"]
    depth_png = target / json.loads((target / "session.json").read_text()
                                    )["scan"]["views"][0]["depth"]
    depth = cv2.imread(str(depth_png), cv2.IMREAD_UNCHANGED)
    ys, xs = np.nonzero(depth)
    depth[ys[0], xs[0]] += 1
    assert cv2.imwrite(str(depth_png), depth)
    changed = build_dataset([root], catalog, PRESET, build_id="changed")
    assert changed.changed == [sid] and changed.failed == {}
    records = {r["build_id"]: r for r in map(json.loads, (work / "builds.jsonl").read_text()
                                             .splitlines())}
    assert records["same"]["keys"] == {}
    after, newest = session_keys(work)
    assert newest["build_id"] == "changed" and list(records["changed"]["keys"]) == [sid]
    assert records["changed"]["keys"][sid] == after[sid] != before[sid]
    replaced = {(st, k) for st, k in before[sid].items() if after[sid][st] != k}
    assert replaced and {st for st, _ in replaced} >= {st for s, st in
                                                       executions(catalog, "changed")}
    # what the copies' first build and the change replaced: no build uses it any more
    gone = {(st, k) for keys in (*warm_keys.values(), *before.values())
            for st, k in keys.items()} - {(st, k) for keys in after.values()
                                          for st, k in keys.items()}
    assert replaced <= gone
    report = vacuum_work(work, min_age_s=0)
    assert report.removed_results == len(gone)
    for session, keys in after.items():  # the unchanged session's and the new ones stay
        assert set(keys) == set(STAGES)
        for stage, key in keys.items():
            assert (work / "results" / stage / f"{key}.pkl").is_file(), (session, stage)
    for stage, key in gone:
        assert not (work / "results" / stage / f"{key}.pkl").exists()
        assert not (work / "results" / stage / f"{key}.json").exists()
    again = build_dataset([root], catalog, PRESET, build_id="again")  # nothing to run
    assert executions(catalog, "again") == [] and again.catalog_version is None
