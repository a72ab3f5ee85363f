"""The ``frames`` layout (issue 21): a build that changes one session of many rewrites a bounded
number of Parquet files (counted from the Delta log's add and remove actions), older versions
still read their old rows, and ``optimize`` keeps the bound."""

from __future__ import annotations

import json

import pyarrow.compute as pc

import graspcap.catalog as gc
from graspcap.catalog import commit, optimize
from graspcap.catalog.optimize import optimize_catalog
from tests.catalog_factory import log_entry, make_build

N = 60
FRAMES = 100
IDS = [f"p{i:02d}-{('mug', 'drill', 'bowl')[i % 3]}-use-00" for i in range(N)]
TARGET = 1 << 20
"""A small target file size, so 60 sessions make several files: deltalake checks the size
after each 1,024 rows (over 1 MiB here), so every file holds 1,024 rows, ~10 sessions."""


def _frames_pin(cat: gc.Catalog, version: int) -> int:
    row = cat.versions().filter(pc.equal(cat.versions()["version"], version)).to_pylist()[0]
    return int(json.loads(row["table_versions"])["frames"])


def _actions(cat: gc.Catalog, first_version: int, last_version: int) -> tuple[list, list]:
    """The add and remove actions of ``frames``' Delta commits from after ``first_version``'s
    pin up to ``last_version``'s."""
    adds, removes = [], []
    for n in range(_frames_pin(cat, first_version) + 1, _frames_pin(cat, last_version) + 1):
        for line in log_entry(cat.layout.root, "frames", n).read_text().splitlines():
            action = json.loads(line)
            adds += [action["add"]] if "add" in action else []
            removes += [action["remove"]] if "remove" in action else []
    return adds, removes


def _inside_one_file(cat: gc.Catalog) -> str:
    """A session whose rows all lie in one file of the newest version: strictly between that
    file's smallest and largest ``session_id``."""
    ranges = []
    for n in range(_frames_pin(cat, cat.latest_version()) + 1):
        for line in log_entry(cat.layout.root, "frames", n).read_text().splitlines():
            action = json.loads(line)
            if "add" in action:
                stats = json.loads(action["add"]["stats"])
                ranges.append((action["add"]["path"], stats["minValues"]["session_id"],
                               stats["maxValues"]["session_id"]))
    live = {p.rsplit("/", 1)[-1] for p in cat.files("frames")}
    for path, low, high in ranges:
        if path in live:
            inside = [s for s in IDS if low < s < high]
            if inside:
                return inside[len(inside) // 2]
    raise AssertionError("no file holds three sessions")


def _session_rows(cat: gc.Catalog, sid: str, version: int):
    frames = cat.table("frames", version)
    return frames.filter(pc.equal(frames["session_id"], sid)).sort_by("frame")


def test_one_session_build_rewrites_one_file_and_optimize_keeps_it(tmp_path, monkeypatch):
    monkeypatch.setattr(commit, "FRAMES_FILE_BYTES", TARGET)
    monkeypatch.setitem(optimize.TARGET_BYTES, "frames", TARGET)
    cat = gc.open(tmp_path / "cat", create=True)
    assert cat.commit(make_build(IDS, seed=1, build_id="cold", frames=FRAMES)) == 1
    cold = cat.files("frames")
    assert len(cold) >= 5  # the cold build is split into files of about TARGET bytes
    frames_v1 = cat.table("frames", 1)
    assert frames_v1["session_id"].to_pylist() == sorted(frames_v1["session_id"].to_pylist())

    # one changed session: its file is replaced, every other file stays
    sid = _inside_one_file(cat)
    assert cat.commit(make_build([sid], seed=2, build_id="one", frames=FRAMES)) == 2
    adds, removes = _actions(cat, 1, 2)
    assert len(removes) == 1 and 1 <= len(adds) <= 2, (len(adds), len(removes))
    assert len(set(cold) & set(cat.files("frames", 2))) == len(cold) - 1
    # time travel: version 1 reads the old rows, version 2 the new ones, the rest unchanged
    assert cat.table("frames", 1).equals(frames_v1)
    old, new = _session_rows(cat, sid, 1), _session_rows(cat, sid, 2)
    assert old.num_rows == new.num_rows == FRAMES
    assert not old["T_w_c"].equals(new["T_w_c"])
    assert new["build_id"].to_pylist() == ["one"] * FRAMES
    others = pc.invert(pc.equal(frames_v1["session_id"], sid))
    rest = cat.table("frames", 2)
    rest = rest.filter(pc.invert(pc.equal(rest["session_id"], sid)))
    key = [("session_id", "ascending"), ("frame", "ascending")]
    assert rest.sort_by(key).equals(frames_v1.filter(others).sort_by(key))
    cat.tag(2, "before-optimize")

    # small builds of new sessions add small files; optimize merges those, not the large ones
    new_ids = [f"p{i:02d}-{('mug', 'drill', 'bowl')[i % 3]}-use-01" for i in range(3, N, 15)]
    for k, new_id in enumerate(new_ids):  # ~180 kB of frames each, sorting among the old
        cat.commit(make_build([new_id], seed=10 + k, build_id=f"new{k}", frames=FRAMES))
    before = cat.latest_version()
    files_before = cat.files("frames")
    report = optimize_catalog(cat)
    cat = gc.open(tmp_path / "cat")
    after = cat.latest_version()
    assert report.version == after
    adds, removes = _actions(cat, before, after)
    assert len(removes) >= 2 and len(adds) < len(removes)  # merged the small files
    assert len(cat.files("frames")) < len(files_before)
    big = [a for a in removes if a["size"] >= TARGET]
    assert big == []  # no file at or over the target was rewritten
    assert max(a["size"] for a in adds) < 2 * TARGET
    key_rows = cat.table("frames", before).sort_by(key)
    assert cat.table("frames").sort_by(key).equals(key_rows)
    assert cat.table("frames", "before-optimize").equals(cat.table("frames", 2))
    assert cat.table("frames", 1).equals(frames_v1)

    # after optimize a one-session build still rewrites at most the two files that hold it
    sid2 = IDS[N // 3]
    v = cat.commit(make_build([sid2], seed=3, build_id="two", frames=FRAMES))
    adds, removes = _actions(cat, after, v)
    assert 1 <= len(removes) <= 2 and 1 <= len(adds) <= 3, (len(adds), len(removes))
    assert all(a["size"] < 2 * TARGET for a in removes)
    assert _session_rows(cat, sid2, v)["build_id"].to_pylist() == ["two"] * FRAMES
    assert _session_rows(cat, sid2, after).equals(_session_rows(cat, sid2, 1))
    assert cat.problems() == []
