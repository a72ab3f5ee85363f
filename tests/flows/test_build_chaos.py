"""Chaos: SIGKILL a real build process at seeded random moments, through the stages and
through the commit; after each kill every earlier catalog version reads back identically and
the next build completes without running again a stage whose result was stored."""

from __future__ import annotations

import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import graspcap.catalog as gc
from graspcap.catalog.commit import PAUSE_ENV, PAUSE_POINTS, PAUSE_SIGNAL_ENV
from graspcap.flows.build import build_dataset
from tests.conftest import REPO
from tests.flow_fixtures import PRESET, require_pipeline_passes

CHAOS_SEED = 15
CHAOS_KILLS = 20
CHILD = """
import sys
from graspcap.flows.runtime import configure
configure(sys.argv[3])
from graspcap.flows.build import build_dataset
build_dataset([sys.argv[1]], sys.argv[2], sys.argv[5], build_id=sys.argv[4])
"""


def _records(path: Path, build_id: str) -> list[dict]:
    if not path.exists():
        return []
    lines = path.read_text().splitlines()
    out = []
    for line in lines:
        try:
            rec = json.loads(line)
        except ValueError:  # a line being written when the process died
            continue
        if rec.get("build_id") == build_id:
            out.append(rec)
    return out


def _stored(work: Path) -> set[tuple[str, str]]:
    """(stage, key) of every stage result the work area holds (its record written last)."""
    return {(p.parent.name, p.name.removesuffix(".json"))
            for p in (work / "results").glob("*/*.json") if not p.name.endswith(".failed.json")}


def _digest(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(str((a.dtype, a.shape)).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def _snapshot(catalog: Path, version: int) -> dict:
    """Everything a reader sees of one catalog version: its tables and every array."""
    cat = gc.open(catalog)  # a fresh reader: nothing cached from before the kill
    keys = {"sessions": ["session_id"], "frames": ["session_id", "frame"],
            "builds": ["build_id"]}
    tables = {name: cat.table(name, version).sort_by([(k, "ascending") for k in key])
              for name, key in keys.items()}
    arrays = {}
    for row in tables["sessions"].to_pylist():
        sid = row["session_id"]
        if row["contact_digest"]:
            arrays[sid, "contact"] = _digest(*cat.contactmap(sid, version))
        if row["hand_mesh_digest"]:
            arrays[sid, "hand"] = _digest(*cat.hand_mesh(sid, version),
                                          cat.hand_joints(sid, version))
        if row["object_mesh_digest"]:
            arrays[sid, "object"] = _digest(*cat.object_mesh(version=version, session_id=sid))
    return {"tables": tables, "arrays": arrays}


def _same(a: dict, b: dict) -> bool:
    return a["arrays"] == b["arrays"] and all(
        a["tables"][n].equals(b["tables"][n]) for n in a["tables"])


def _perturb(root: Path, rng: random.Random) -> str:
    """Change one input of one session a little, so that some stages must run again: one
    millimetre on one pixel of a depth image, or one keypoint's confidence."""
    session = rng.choice(sorted(p for p in root.iterdir() if (p / "session.json").exists()))
    m = json.loads((session / "session.json").read_text())
    kind = rng.choice(["scan_depth", "stage1_depth", "keypoints"])
    if kind == "keypoints":
        frame = rng.randrange(m["grasp"]["count"])
        path = session / m["grasp"]["keypoints"].format(index=frame)
        data = json.loads(path.read_text())
        pts = data["people"][0][f"hand_{m['hand']}_keypoints_2d"]
        j = 3 * rng.randrange(len(pts) // 3) + 2
        pts[j] = round(pts[j] * 0.97, 6)
        path.write_text(json.dumps(data))
    else:
        rel = (m["scan"]["views"][rng.randrange(len(m["scan"]["views"]))]["depth"]
               if kind == "scan_depth" else m["stage1"]["depth"])
        path = session / rel
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        ys, xs = np.nonzero(depth)
        k = rng.randrange(len(ys))
        depth[ys[k], xs[k]] += 1
        assert cv2.imwrite(str(path), depth)
    return f"{kind} {path.relative_to(root)}"


def _kill_at(root: Path, catalog: Path, prefect: Path, build_id: str, stage_kill: int | None,
             pause: str, log: Path) -> str:
    """Start a build process paused at commit step ``pause`` and SIGKILL its process group
    after ``stage_kill`` stage executions, or once it is paused; say where it died."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", PAUSE_ENV: pause,
           PAUSE_SIGNAL_ENV: str(log.with_suffix(".paused"))}
    env.pop("PREFECT_API_URL", None)
    env.pop("PREFECT_HOME", None)
    executions = catalog / "work" / "executions.jsonl"
    with open(log, "w") as out:
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(root), str(catalog), str(prefect), build_id,
             PRESET], env=env, cwd=REPO, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)  # its own group: the Prefect server it starts dies too
    deadline = time.monotonic() + 300
    where = None
    while where is None:
        assert child.poll() is None, f"the build ended on its own:\n{log.read_text()[-3000:]}"
        assert time.monotonic() < deadline, f"no kill point in 300 s:\n{log.read_text()[-3000:]}"
        done = sum(r["ok"] for r in _records(executions, build_id))
        if log.with_suffix(".paused").exists():
            where = f"commit {pause} (after {done} stage run(s))"
        elif stage_kill is not None and done >= stage_kill:
            where = f"stages, after {done} stage run(s)"
        else:
            time.sleep(0.05)
    os.killpg(child.pid, signal.SIGKILL)
    child.wait()
    return where


@pytest.mark.slow
def test_sigkill_at_random_moments_loses_nothing_and_reruns_nothing(synth_root, tmp_path,
                                                                    prefect_harness):
    rng = random.Random(CHAOS_SEED)
    root = tmp_path / "sessions"
    for s in sorted(synth_root.iterdir()):
        shutil.copytree(s, root / s.name)
    catalog = tmp_path / "catalog"
    work = catalog / "work"
    first = build_dataset([root], catalog, PRESET, build_id="base")
    require_pipeline_passes(first)
    snapshots = {1: _snapshot(catalog, 1)}
    ids = sorted(snapshots[1]["tables"]["sessions"]["session_id"].to_pylist())
    log = []
    for i in range(CHAOS_KILLS):
        changed = _perturb(root, rng)
        # about half the kills in the stages (after 1-6 stage runs; the build is held at the
        # lock should it get there first), the others at a commit step
        in_stages = rng.random() < 0.5
        pause = "after_lock" if in_stages else rng.choice(PAUSE_POINTS)
        latest = gc.open(catalog).latest_version()
        where = _kill_at(root, catalog, tmp_path / "prefect", f"killed-{i}",
                         rng.randint(1, 6) if in_stages else None, pause,
                         tmp_path / f"child-{i}.log")
        # every version committed before reads back identically; the killed build is invisible
        cat = gc.open(catalog)
        assert cat.latest_version() == latest, where
        for v, snap in snapshots.items():
            assert _same(_snapshot(catalog, v), snap), f"version {v} changed: kill {i} {where}"
        stored = _stored(work)
        report = build_dataset([root], catalog, PRESET, build_id=f"next-{i}")
        again = {(r["stage"], r["key"]) for r in _records(work / "executions.jsonl",
                                                          f"next-{i}")}
        assert not again & stored, f"kill {i} ({where}): ran again {sorted(again & stored)}"
        assert report.failed == {}, (i, where, report.failed)
        assert report.catalog_version == latest + 1, (i, where, report.summary())
        snapshots[latest + 1] = _snapshot(catalog, latest + 1)
        assert sorted(snapshots[latest + 1]["tables"]["sessions"]["session_id"]
                      .to_pylist()) == ids
        log.append(f"kill {i:2d}: {changed}; killed in {where}; the next build ran "
                   f"{len(again)} stage(s), {len(stored)} results stored")
    for v, snap in snapshots.items():  # and at the end, all of them once more
        assert _same(_snapshot(catalog, v), snap), f"version {v} changed"
    print("\n".join(log))
