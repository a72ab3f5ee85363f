"""A build's sessions -> the rows it commits and its per-session reports (no Prefect here).

After every stage settled, :func:`assemble` turns each session's stage outcomes into its
catalog rows (``flows/rows.py``) or, when it failed, into its failure: a ``status="failed"``
row unless it keeps its previous good rows, and none at all for a failure the catalog's
latest build already records (the same error on the same inputs and configs: no new version
for it). Each session's rows pass the commit's checks here, one session at a time, so a
session the catalog would refuse fails alone. :func:`recorded_failures` and
:func:`last_build_failures` read what the last build recorded. See ``flows/build.py``.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa

import graspcap.catalog as gc
from graspcap.catalog.commit import ObjectMesh, SessionArrays
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.validate import check_commit, to_table
from graspcap.flows.build_log import session_keys
from graspcap.flows.cached import reads_digest, session_files
from graspcap.flows.report import Outcome, SessionReport
from graspcap.flows.rows import (
    NEWEST_COLUMNS,
    failed_row,
    manifest_labels,
    predates_columns,
    session_rows,
)
from graspcap.flows.session_roles import SessionRoles
from graspcap.flows.workarea import ResultRef, Spill, WorkArea
from graspcap.schemas.tables import Status


def last_build_failures(cat: gc.Catalog, work: WorkArea) -> set[str]:
    """Sessions that failed in the last build (the work area's log, else the catalog); after a
    build that failed as a whole (nothing committed), every session its record lists (all but
    the unchanged ones with nothing else to say, ``BuildReport.record``: the catalog has their
    rows as they are)."""
    _, last = session_keys(work.root)  # the log's newest record, read from its snapshot on
    if last is not None:
        if last.get("error"):
            return {s["session_id"] for s in last["sessions"]}
        return set(last["summary"]["failed"])
    last = _last_build_row(cat)
    if last is None:
        return set()
    failed = {f["session_id"] for f in last["sessions_failed"]}
    record = json.loads(last["parameters_json"]).get("report", {})
    return failed | set(record.get("summary", {}).get("failed", {}))


def _last_build_row(cat: gc.Catalog) -> dict | None:
    """The base version's (the newest not rejected: what a build writes on top of) newest
    builds row made by a build (a ``catalog remove`` version's row records no build's
    failures: the one before it does), None without one."""
    base = cat.base_version()
    if base is None:
        return None
    for row in cat.table("builds", base).sort_by("catalog_version").to_pylist()[::-1]:
        if json.loads(row["parameters_json"]).get("command") != "catalog remove":
            return row
    return None


def recorded_failures(cat: gc.Catalog) -> dict[str, str]:
    """Failed sessions and their errors in the catalog's latest build record."""
    last = _last_build_row(cat)
    if last is None:
        return {}
    failed = {f["session_id"]: f["error"] for f in last["sessions_failed"]}
    record = json.loads(last["parameters_json"]).get("report", {})
    return {**failed, **record.get("summary", {}).get("failed", {})}


def _shared_object_notes(built: Mapping[str, tuple[str, str | None]],
                         previous: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """A note for each session of ``built`` (``(object_id, mesh digest)`` by session id) whose
    ``object_id`` labels more than one object mesh once committed (``previous``: the latest
    version's rows). Allowed by the contract (a re-scanned object): each session keeps its
    own mesh and contact map, but a reader grouping by ``object_id`` should know."""
    latest = {sid: (r["object_id"], r["object_mesh_digest"]) for sid, r in previous.items()}
    latest.update(built)
    by_object: dict[str, dict[str, list[str]]] = {}
    for sid, (object_id, digest) in sorted(latest.items()):
        if digest:
            by_object.setdefault(object_id, {}).setdefault(digest, []).append(sid)
    notes = {}
    for object_id, meshes in by_object.items():
        if len(meshes) > 1:
            groups = "; ".join(f"{d[:12]}: {', '.join(s)}" for d, s in meshes.items())
            for sid, (label, _) in built.items():
                if label == object_id:
                    notes[sid] = (f"object_id {object_id!r} labels {len(meshes)} different "
                                  f"object meshes ({groups}); each session keeps its own mesh "
                                  "and contact map")
    return notes


def _input_digest(work: WorkArea, session_dir: Path) -> str:
    from graspcap.tasks.pipeline import ALL_FILES

    roles = SessionRoles(work, session_dir)
    files = {} if all(r in roles.digests for r in ALL_FILES) else session_files(session_dir)
    if files is None:
        return hashlib.sha256(b"unreadable manifest").hexdigest()
    try:
        digest = reads_digest(work, files, ALL_FILES, roles.digests)
    except OSError:
        return hashlib.sha256(b"missing files").hexdigest()
    roles.save()
    return digest


def _write_pictures(layout: CatalogLayout, session_id: str, pictures: Any) -> dict[str, str]:
    """Store a session's QA pictures (``tasks.pictures.Pictures``) by content
    (``layout.picture_file``); their paths relative to the catalog root by file name. A file
    already there is kept; a new one is written to a temporary name and renamed (a reader sees
    the whole file or none). ``session_id``: whose pictures they are (a caller's messages)."""
    stored = {}
    for name, data in pictures.files().items():
        path = layout.picture_file(hashlib.sha256(data).hexdigest(), Path(name).suffix)
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
            try:
                tmp.write_bytes(data)
                os.replace(tmp, path)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
        stored[name] = path.relative_to(layout.root).as_posix()
    return stored


def _store_pictures(layout: CatalogLayout, session_id: str, ref: ResultRef
                    ) -> tuple[dict[str, str], tuple[str, ...]]:
    """Store a session's pictures under the catalog's ``pictures/`` (by content: a session id
    is never a path there); (their paths by name, ()) when stored, else ({}, a note naming
    the folder and the error: disk full, permission): pictures are a QA aid and never fail a
    session or the build."""
    try:
        return _write_pictures(layout, session_id, WorkArea.load(ref)), ()
    except Exception as exc:  # noqa: BLE001 - OSError above all; never fails the build
        where = getattr(exc, "filename", None) or layout.pictures_root
        return {}, (f"pictures of {session_id} not written to {where}: {type(exc).__name__}: "
                    f"{exc} (a QA aid: the session is committed without them)",)


@dataclass(frozen=True)
class Assembled:
    """What a build commits, and its report of each session (in the order of its folders).
    It stays small as sessions add up (0.09 MB a demo session, 0.70 before; docs/benchmarks.md):
    ``frames`` are Arrow tables, not Python rows, and the arrays and meshes wait in the work
    area (``Spill``) until the commit reads them one session at a time."""

    reports: tuple[SessionReport, ...]
    rows: list[dict[str, Any]]
    frames: pa.Table
    arrays: Mapping[str, SessionArrays]
    meshes: Mapping[str, ObjectMesh]
    new_failures: bool
    """A failure the catalog's latest build does not record: worth a version of its own."""


def assemble(cat: gc.Catalog, work: WorkArea, build: gc.BuildInfo, previous: int | None,
             sessions: Sequence[tuple[Path, str]], duplicate: Mapping[str, str],
             outcomes: Mapping[str, tuple]) -> Assembled:
    """Rows and reports of a build's ``sessions`` (``(folder, session_id)``, sorted), on top
    of catalog version ``previous``. ``duplicate``: the reason by folder of each folder whose
    id an earlier one has (a report, no row); ``outcomes``: ``build._stage_outcomes`` by
    folder of the others. A session whose rows cannot be assembled, or that the commit's
    checks refuse, fails alone (module docstring)."""
    from graspcap.tasks.pipeline import STAGES

    build_id, version, cdigest = build.build_id, build.code_version, build.config_digest
    prev_rows = ({r["session_id"]: r for r in cat.table("sessions", previous).select(
        ["session_id", "status", "input_digest", "config_digest", "steady_from", "object_id",
         "object_mesh_digest", *NEWEST_COLUMNS]).to_pylist()}
        if previous is not None else {})
    attempts: dict[tuple[str, str], int] = {}
    for rec in work.executions(build_id):
        k = (rec["session_id"], rec["stage"])
        attempts[k] = attempts.get(k, 0) + 1
    by_index: dict[int, SessionReport] = {}  # reports in the order of sessions
    rows: list[dict[str, Any]] = []
    frames: list[pa.Table] = []
    arrays, meshes = Spill(work), Spill(work)
    recorded: dict[str, str] | None = None
    new_failures = False
    built = []  # sessions whose rows passed the commit's checks

    def fail(i: int, d: Path, sid: str, error: str, stage: str | None, info: dict,
             common: dict, prev: dict | None, good_prev: bool,
             own_row: bool = True) -> None:
        """Report session ``i`` failed; give it a failed row unless it keeps its previous good
        rows, the catalog's latest build already records this failure (known: the same error on
        the same inputs and configs, replayed from the work area or run again, as a bad
        manifest's ``load_session`` is on every build), or the id's row is not its own
        (``own_row=False``: a duplicated id)."""
        nonlocal recorded, new_failures
        row = None
        if own_row and not good_prev:
            try:  # the failed row must not take the commit down either
                row = failed_row(d, sid, error, **common)
                check_commit(gc.BuildCommit(build=build, sessions=[row], frames=[]))
            except Exception as exc:  # noqa: BLE001 - the reason goes into the report
                error, row = f"{error} (no failed row written: {exc})", None
        # a failure the catalog's latest build already records (same error, same inputs and
        # configs) needs no new version, whether replayed or run again
        if recorded is None:
            recorded = recorded_failures(cat) if previous is not None else {}
        known = (recorded.get(sid) == error
                 and (good_prev or row is None or (prev is not None and prev["input_digest"]
                                                   == common["input_digest"]
                                                   and prev["config_digest"] == cdigest)))
        new_failures |= not known
        if row is not None and not known:
            rows.append(row)
        by_index[i] = SessionReport(outcome=Outcome.FAILED, status=Status.FAILED.value,
                                   error=error, failed_stage=stage,
                                   kept_previous=good_prev, **info)

    for i, (d, sid) in enumerate(sessions):
        common = {"input_digest": hashlib.sha256(b"unreadable session").hexdigest(),
                  "code_version": version, "build_id": build_id, "config_digest": cdigest}
        if str(d) in duplicate:  # the id's row is the first folder's: a report, no row
            info = dict(session_id=sid, session_dir=str(d), not_run=tuple(STAGES))
            fail(i, d, sid, duplicate[str(d)], None, info, common, prev_rows.get(sid), False,
                 own_row=False)
            continue
        prev = prev_rows.get(sid)
        # previous rows with results (ok, flagged, or failed by QA), not a failed build's row
        good_prev = prev is not None and (prev["status"] != Status.FAILED
                                          or prev["steady_from"] is not None)
        refs, ran, cached, not_run, error, stage, notes = outcomes[str(d)]
        retries = {st: n - 1 for (s, st), n in attempts.items() if s == sid and n > 1}
        info = dict(session_id=sid, session_dir=str(d), ran=tuple(ran), cached=tuple(cached),
                    not_run=tuple(not_run), retries=retries, notes=notes)
        try:
            common["input_digest"] = _input_digest(work, d)
            if "pictures" in refs:
                info["pictures"], note = _store_pictures(cat.layout, sid, refs["pictures"])
                info["notes"] += note
            if error is not None:
                fail(i, d, sid, error, stage, info, common, prev, good_prev)
                continue
            # a row from before a column existed (a migrated catalog's) is rewritten from
            # cached results
            if (not ran and good_prev and prev["input_digest"] == common["input_digest"]
                    and prev["config_digest"] == cdigest and not predates_columns(prev)):
                by_index[i] = SessionReport(outcome=Outcome.UNCHANGED,
                                            status=prev["status"], **info)
                continue
            sr = session_rows({k: WorkArea.load(r) for k, r in refs.items()},
                              labels=manifest_labels(d), **common)
            if sr.session["session_id"] != sid:
                raise ValueError(f"its rows are for session_id {sr.session['session_id']!r}")
        except Exception as exc:  # noqa: BLE001 - one session's bug never loses the build
            fail(i, d, sid, f"assembling the catalog rows: {type(exc).__name__}: {exc}",
                 None, info, common, prev, good_prev)
            continue
        # the checks the commit runs, per session: one whose rows, frames or arrays would make
        # it raise fails alone, with the reason, and the others are committed
        try:
            sessions_t, frames_t = check_commit(gc.BuildCommit(
                build=build, sessions=[sr.session], frames=sr.frames,
                session_arrays={sid: sr.arrays}, object_meshes={sid: sr.object_mesh}))
        except Exception as exc:  # noqa: BLE001 - CatalogSchemaError, or a bug in a check
            fail(i, d, sid, f"the catalog refused its rows: {exc}", None, info, common, prev,
                 good_prev)
            continue
        built.append((i, sid, sr.session, sr.object_id,
                      sessions_t["object_mesh_digest"][0].as_py(), info, prev))
        frames.append(frames_t)
        arrays.put(sid, sr.arrays)
        meshes.put(sid, sr.object_mesh)  # the session's own mesh (content-addressed)
    shared = _shared_object_notes({sid: (object_id, digest)
                                   for _, sid, _, object_id, digest, *_ in built}, prev_rows)
    for i, sid, row, _, _, info, prev in built:
        if sid in shared:
            info["notes"] = (*info["notes"], shared[sid])
        rows.append(row)
        by_index[i] = SessionReport(outcome=Outcome.CHANGED if prev else Outcome.ADDED,
                                   status=row["status"], error=row["error"], **info)
    return Assembled(tuple(by_index[i] for i in sorted(by_index)), rows,
                     pa.concat_tables(frames) if frames else to_table("frames", []), arrays,
                     meshes, new_failures)
