"""The work area's build log (``flows/build_log.py``): a record lists the keys of the sessions
whose keys changed, readers fold them (from the snapshot on), old full records read as before."""

from __future__ import annotations

import json

from graspcap.flows.build_log import KEYS_SNAPSHOT, append_build, session_keys
from graspcap.flows.workarea import BUILDS_LOG

STAGES = ("load_session", "fit_hand", "qa_metrics")


def _keys(n: int, tag: str = "k") -> dict[str, dict[str, str]]:
    return {f"s{i:04d}": {st: f"{tag}{i}-{st}" for st in STAGES} for i in range(n)}


def _records(work) -> list[dict]:
    return [json.loads(x) for x in (work / BUILDS_LOG).read_text().splitlines()]


def test_a_record_lists_only_the_sessions_whose_keys_changed(tmp_path):
    used = _keys(2)
    append_build(tmp_path, {"build_id": "cold"}, used)
    append_build(tmp_path, {"build_id": "same"}, used)  # an unchanged rebuild
    changed = {**used, "s0001": {**used["s0001"], "qa_metrics": "new"}}
    append_build(tmp_path, {"build_id": "one"}, changed)
    failed = {**changed, "s0000": {"load_session": used["s0000"]["load_session"]}}
    append_build(tmp_path, {"build_id": "failed"}, failed)
    retry = {"s0002": {"load_session": "x"}}  # a --retry-failed build of a new session
    append_build(tmp_path, {"build_id": "retry"}, retry)
    recs = _records(tmp_path)
    assert [r["build_id"] for r in recs] == ["cold", "same", "one", "failed", "retry"]
    assert [r["keys"] for r in recs] == [used, {}, {"s0001": changed["s0001"]},
                                         {"s0000": failed["s0000"]}, retry]
    keys, newest = session_keys(tmp_path)
    assert keys == {**failed, **retry} and newest == recs[-1]
    (tmp_path / KEYS_SNAPSHOT).unlink()  # the whole log folded: the same answer
    assert session_keys(tmp_path) == (keys, newest)


def test_record_size_does_not_grow_with_unchanged_sessions(tmp_path):
    sizes = {}
    for n in (2, 200):
        work = tmp_path / str(n)
        work.mkdir()
        used = _keys(n)
        append_build(work, {"build_id": "cold"}, used)
        append_build(work, {"build_id": "same"}, used)
        append_build(work, {"build_id": "one"}, {**used, "s0000": _keys(1, "new")["s0000"]})
        sizes[n] = [len(x) for x in (work / BUILDS_LOG).read_bytes().splitlines()]
    assert sizes[200][0] > 50 * sizes[2][0]  # the cold build lists every session
    assert sizes[2][1:] == sizes[200][1:]  # the rebuilds: what changed, whatever N


def test_old_full_records_and_torn_lines_read_as_before(tmp_path):
    old = [{"build_id": "a", "keys": {"s0": {"x": "1"}, "s1": {"x": "1"}}},
           {"build_id": "retry", "keys": {"s1": {"x": "2"}}},  # a --retry-failed build
           {"build_id": "b", "keys": {"s0": {"x": "3"}}}]
    log = tmp_path / BUILDS_LOG
    log.write_bytes(b"".join(json.dumps(r).encode() + b"\n" for r in old)
                    + b'[1]\n{"build_id": "torn", "ke')
    assert session_keys(tmp_path) == ({"s0": {"x": "3"}, "s1": {"x": "2"}}, old[-1])
    # a new record after the torn line starts a line of its own: not lost with it
    append_build(tmp_path, {"build_id": "new"}, {"s0": {"x": "3"}, "s1": {"x": "4"}})
    lines = log.read_bytes().splitlines()
    assert lines[-2] == b'{"build_id": "torn", "ke'
    assert json.loads(lines[-1]) == {"build_id": "new", "keys": {"s1": {"x": "4"}}}
    assert session_keys(tmp_path)[0] == {"s0": {"x": "3"}, "s1": {"x": "4"}}


def test_a_record_without_keys_starts_the_fold_afresh(tmp_path):
    recs = [{"build_id": "a", "keys": {"s0": {"x": "1"}}}, {"build_id": "older-graspcap"}]
    (tmp_path / BUILDS_LOG).write_text("".join(json.dumps(r) + "\n" for r in recs))
    assert session_keys(tmp_path) == ({}, recs[1])
    append_build(tmp_path, {"build_id": "c"}, {"s0": {"x": "1"}})  # listed again: unknown
    assert _records(tmp_path)[-1]["keys"] == {"s0": {"x": "1"}}
    assert session_keys(tmp_path)[0] == {"s0": {"x": "1"}}


def test_the_snapshot_is_used_only_while_the_log_holds_its_record(tmp_path):
    append_build(tmp_path, {"build_id": "a"}, {"s0": {"x": "1"}})
    snap = json.loads((tmp_path / KEYS_SNAPSHOT).read_text())
    assert (snap["build_id"], snap["start"], snap["keys"]) == ("a", 0, {"s0": {"x": "1"}})
    # the snapshot is what readers take: a log line before its end is not parsed again
    log = tmp_path / BUILDS_LOG
    snap["keys"] = {"s0": {"x": "from-snapshot"}}
    (tmp_path / KEYS_SNAPSHOT).write_text(json.dumps(snap))
    assert session_keys(tmp_path)[0] == {"s0": {"x": "from-snapshot"}}
    # records appended after it (an older graspcap, a snapshot not written) are folded on top
    with open(log, "a") as f:
        f.write(json.dumps({"build_id": "b", "keys": {"s1": {"x": "2"}}}) + "\n")
    assert session_keys(tmp_path)[0] == {"s0": {"x": "from-snapshot"}, "s1": {"x": "2"}}
    # a log rewritten under it (another record at its place): the whole log is folded
    log.write_text(json.dumps({"build_id": "z", "keys": {"s9": {"x": "9"}}}) + "\n")
    assert session_keys(tmp_path) == ({"s9": {"x": "9"}}, {"build_id": "z",
                                                             "keys": {"s9": {"x": "9"}}})
    (tmp_path / KEYS_SNAPSHOT).write_text("{not json")
    assert session_keys(tmp_path)[0] == {"s9": {"x": "9"}}
    log.unlink()
    assert session_keys(tmp_path) == ({}, None)


def _report(n: int, changed: int | None = None, notes: tuple[str, ...] = ()):
    """A build of ``n`` sessions, unchanged (every stage cached, five pictures) but session
    ``changed`` (its stages ran) and session 1 with ``notes``."""
    from graspcap.flows.report import BuildReport, Outcome, SessionReport

    pictures = {f"p{i}.png": f"pictures/{i:02d}/{'ab' * 32}.png" for i in range(5)}
    sessions = tuple(SessionReport(
        f"s{i:04d}", f"/data/sessions/s{i:04d}",
        Outcome.CHANGED if i == changed else Outcome.UNCHANGED, "flagged" if i == 2 else "ok",
        ran=STAGES if i == changed else (), cached=() if i == changed else STAGES,
        notes=notes if i == 1 else (), pictures=pictures) for i in range(n))
    return BuildReport("b", None, 1, sessions, {"total": 1.0}, {"preset": "x"})


def test_a_record_lists_only_the_sessions_with_something_to_say(tmp_path):
    """Unchanged sessions with nothing else to say are counted (``unlisted``), not listed;
    the record's bytes, ``sessions`` and ``summary`` included, are flat in N."""
    from graspcap.flows.commands import run_line

    rec = _report(5, changed=3, notes=("pictures not written",)).record()
    assert [(s["session_id"], s["outcome"]) for s in rec["sessions"]] == [
        ("s0001", "unchanged"), ("s0003", "changed")]
    assert rec["sessions"][0]["notes"] == ["pictures not written"]
    assert rec["summary"] == {"added": [], "changed": ["s0003"], "unchanged": 4, "failed": {}}
    assert rec["unlisted"] == {"sessions": 3, "cached": dict.fromkeys(STAGES, 3),
                               "status": {"ok": 2, "flagged": 1}}
    assert run_line("r", "Completed", None, rec).endswith(
        "no new version (still 1): 0 added, 1 changed, 4 unchanged, 0 failed")
    sizes = {}
    for n in (20, 2000):
        work = tmp_path / str(n)
        work.mkdir()
        used = _keys(n)
        append_build(work, {**_report(n).record(), "build_id": "first"}, used)
        append_build(work, {**_report(n).record(), "build_id": "same"}, used)
        append_build(work, {**_report(n, changed=0).record(), "build_id": "one"},
                     {**used, "s0000": _keys(1, "new")["s0000"]})
        sizes[n] = [len(x) for x in (work / BUILDS_LOG).read_bytes().splitlines()]
    # 100x the sessions: a few more digits in the counts (the first record keys them all)
    assert [0 < b - a <= 16 for a, b in zip(sizes[20][1:], sizes[2000][1:], strict=True)] \
        == [True, True] and max(sizes[20][1:]) < 3000, sizes
    last = _records(tmp_path / "2000")[-1]
    assert len(last["sessions"]) == 1 and last["summary"]["unchanged"] == 1999
