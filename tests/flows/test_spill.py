"""A build's assembled arrays wait in the work area (``Spill``), and the commit reads them one
session at a time: a build's memory does not grow with its sessions' arrays (issue 21)."""

from __future__ import annotations

import gc as pygc
import os
import socket
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np

import graspcap.catalog as gc
from graspcap.flows.workarea import TEMP_PREFIX, Spill, WorkArea
from tests.catalog_factory import GeneratedArrays, make_build


def test_spill_round_trip_and_lifetime(tmp_path: Path) -> None:
    work = WorkArea(tmp_path / "work")
    spill = Spill(work)
    spill.put("a", {"x": np.arange(3)})
    spill.put("b", None)  # no mesh: absent, like a missing key
    assert "a" in spill and "b" not in spill and list(spill) == ["a"] and len(spill) == 1
    np.testing.assert_array_equal(spill["a"]["x"], np.arange(3))
    assert spill["a"] is not spill["a"]  # read from disk each time, never held
    assert spill.get("b") is None
    folder = next(p for p in work.root.iterdir() if p.name.startswith(TEMP_PREFIX))
    assert folder.is_dir() and len(list(folder.iterdir())) == 1
    del spill
    pygc.collect()
    assert not folder.exists()


def test_a_killed_builds_spill_is_swept(tmp_path: Path) -> None:
    work = WorkArea(tmp_path / "work")
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    stale = work.root / f"{TEMP_PREFIX}{socket.gethostname()}-{gone}-k1ll3d"
    stale.mkdir()
    (stale / "0-abcd.pkl").write_bytes(b"arrays")
    live = Spill(work)
    live.put("a", 1)
    removed = work.remove_stale_temp()
    assert stale in removed and not stale.exists()
    assert Path(live._dir.name).is_dir() and live["a"] == 1  # this process's own stays
    assert str(os.getpid()) in Path(live._dir.name).name


def test_commit_reads_each_sessions_arrays_when_it_writes_them(tmp_path: Path) -> None:
    ids = [f"p{i:02d}-mug-use-00" for i in range(50)]
    build = make_build(ids, seed=3, frames=2)
    objects = {r["session_id"]: r["object_id"] for r in build.sessions}
    # 2.4 MB a session: 120 MB in all
    arrays = GeneratedArrays(objects, vertices=100_000, faces=100_000)
    one = sum(a.nbytes for a in (arrays[ids[0]].hand_vertices, arrays[ids[0]].hand_faces))
    cat = gc.open(tmp_path / "cat", create=True)
    tracemalloc.start()
    try:
        version = cat.commit(gc.BuildCommit(build=build.build, sessions=build.sessions,
                                            frames=build.frames, session_arrays=arrays,
                                            object_meshes=build.object_meshes))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # four writer threads each hold one group (and its encoded chunks) at a time: ~11 sessions'
    # worth measured; before, every session's checked arrays until the writes (56)
    assert peak < 16 * one, (peak, one)
    for sid in (ids[0], ids[-1]):
        verts, faces = cat.hand_mesh(sid, version)
        np.testing.assert_array_equal(verts, arrays[sid].hand_vertices)
        np.testing.assert_array_equal(faces, arrays[sid].hand_faces)
