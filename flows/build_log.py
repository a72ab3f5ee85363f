"""The work area's build log, ``builds.jsonl``: one JSON record a build, appended.

Each record is the build's report (``BuildReport.record()``: ``graspcap status``, the report
page) with ``keys``: ``{session_id: {stage: key}}``, the stored result each stage of a session
used, listed only for the sessions whose keys differ from what the log said before (new
sessions, sessions that ran a stage or hit an older result, sessions that failed at another
stage). An unchanged rebuild records ``"keys": {}``, so a record's keys grow with what a build
changed, not with the number of sessions; so do its ``sessions`` and ``summary``, where the
unchanged sessions with nothing else to say are counts (``BuildReport.record``).

A session's current keys are those of the newest record that lists it: :func:`session_keys`
folds the records oldest to newest. Records of a graspcap from before this listed every
session a build built; folded the same way they give the same answer, so old work areas read
as before (and an older graspcap's vacuum, taking each session's newest mention, reads new
records right). A record without ``keys`` (older still) says nothing: the fold starts afresh
after it. Lines that are not records (a build killed while writing one) are skipped.

So that no reader folds thousands of records, every append also rewrites (atomically)
``builds-keys.json``, the fold up to and including that record, with the record's byte range
in the log: a reader takes it when the log still holds that record there and folds only the
records after it (none, unless an append's snapshot could not be written or an older graspcap
appended). Without a usable snapshot (deleted, or the log truncated) it folds the whole log.
The append, its diff against the fold and the snapshot happen under an exclusive ``flock`` of
the log, so two builds of one work area never diff against the same state. Prefect-free.
"""

from __future__ import annotations

import fcntl
import json
import logging
from pathlib import Path
from typing import Any

from graspcap.flows.workarea import BUILDS_LOG, _atomic_write

KEYS_SNAPSHOT = "builds-keys.json"
"""The fold of ``builds.jsonl``'s ``keys`` up to one record (module docstring)."""
SNAPSHOT_FORMAT = 1

Keys = dict[str, dict[str, str]]


def _parse(line: bytes) -> dict | None:
    try:
        record = json.loads(line)
    except (ValueError, RecursionError):
        return None
    return record if isinstance(record, dict) and "build_id" in record else None


def _fold(state: Keys, data: bytes) -> dict | None:
    """Fold the records of ``data`` (lines of the log) into ``state``; the newest record."""
    newest = None
    for line in data.splitlines():
        record = _parse(line)
        if record is None:
            continue
        newest = record
        keys = record.get("keys")
        if not isinstance(keys, dict):
            state.clear()  # an older graspcap's record: what it used is unknown
            continue
        for session_id, stages in keys.items():
            state[str(session_id)] = {str(s): str(k) for s, k in (stages or {}).items()}
    return newest


def _snapshot(work: Path, log: Any) -> tuple[Keys, dict | None, int] | None:
    """The snapshot's keys, the record it ends with and that record's end in the log (open
    binary ``log``), or None when there is none or the log no longer holds that record."""
    try:
        snap = json.loads((work / KEYS_SNAPSHOT).read_bytes())
        start, end = int(snap["start"]), int(snap["end"])
        keys = snap["keys"]
        if snap.get("format") != SNAPSHOT_FORMAT or not isinstance(keys, dict) \
                or not 0 <= start < end:
            return None
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return None
    log.seek(start)
    record = _parse(log.read(end - start))
    if record is None or record.get("build_id") != snap.get("build_id"):
        return None
    return {str(s): dict(v) for s, v in keys.items()}, record, end


def _read(work: Path, log: Any) -> tuple[Keys, dict | None]:
    snap = _snapshot(work, log)
    state, newest, end = snap if snap is not None else ({}, None, 0)
    log.seek(end)
    return state, _fold(state, log.read()) or newest


def session_keys(work: Path | str) -> tuple[Keys, dict | None]:
    """``({session_id: {stage: key}}, newest record)`` of the work area ``work``: each
    session's keys as its newest build used them (module docstring); ``({}, None)`` without
    a log."""
    work = Path(work)
    try:
        with open(work / BUILDS_LOG, "rb") as log:
            return _read(work, log)
    except FileNotFoundError:
        return {}, None


def append_build(work: Path | str, record: dict, used: Keys) -> None:
    """Append ``record`` to the log with ``keys``: the sessions of ``used`` whose keys differ
    from the fold, then rewrite the snapshot. Raises ``OSError`` when the record cannot be
    written; a snapshot that cannot be written is a warning (the log has the record)."""
    work = Path(work)
    with open(work / BUILDS_LOG, "a+b") as log:
        fcntl.flock(log, fcntl.LOCK_EX)  # released when closed
        state, _ = _read(work, log)
        changed = {sid: dict(stages) for sid, stages in used.items()
                   if state.get(sid) != stages}
        start = log.seek(0, 2)
        if start:  # a torn last line (a build killed while writing) stays a line of its own
            log.seek(start - 1)
            if log.read(1) != b"\n":
                log.write(b"\n")
                start += 1
        data = (json.dumps({**record, "keys": changed}, sort_keys=True) + "\n").encode()
        log.write(data)
        log.flush()
        state.update(changed)
        snap = {"format": SNAPSHOT_FORMAT, "build_id": record["build_id"], "start": start,
                "end": start + len(data), "keys": state}
        try:
            _atomic_write(work / KEYS_SNAPSHOT,
                          json.dumps(snap, sort_keys=True, separators=(",", ":")).encode())
        except OSError as exc:
            logging.getLogger(__name__).warning(
                "%s not rewritten (readers fold %s instead): %s", work / KEYS_SNAPSHOT,
                BUILDS_LOG, exc)
