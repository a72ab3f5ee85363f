"""One build = one catalog version, atomic across every table and array.

Protocol (under the writer lock):

1. read the last ``versions`` row: the Delta version every data table must be at;
2. check that nothing after that row was published (``check_versions``: no gap in a table's log
   or in the version numbers, no pin past a table's log, no ``published.json``, tag, table
   commit or builds row made for a later version); if something was, stop with
   ``CatalogDamaged`` naming it. Otherwise roll back any table that is newer (a writer died
   after a table commit, before its versions row) with ``DeltaTable.restore``. Every table
   commit carries the catalog version it was made for (commit metadata
   ``graspcap.catalog_version``), and ``published.json`` records the newest published version
   after each versions row: the evidence that tells a killed writer's orphans from a
   published version whose row was lost. Version numbers are never reused;
3. write the arrays (content-addressed Zarr groups, temp name then rename; first remove what
   killed writers left under ``arrays/.tmp``);
4. per data table one Delta commit: replace the rows of the sessions the build touches
   (``mode="overwrite"`` with a ``session_id IN (...)`` predicate), append the builds row;
5. append the ``versions`` row: this write is the linearisation point. Readers resolve a catalog
   version through ``versions`` and read each table at its pinned Delta version, so until step 5
   lands the build is invisible, and a crash anywhere before it is undone by the next writer.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import time
from collections.abc import Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from deltalake import CommitProperties, DeltaTable, write_deltalake
from deltalake.exceptions import DeltaError

from graspcap.catalog.arrays import (
    array_digest,
    check_arrays,
    remove_temp_groups,
    write_group,
)
from graspcap.catalog.audit import AuditGates, audit_version
from graspcap.catalog.delta import (
    INITIAL_TABLE_VERSIONS,
    delta_table,
    delta_version,
    entry_path,
    intact_files,
    log_dir,
    log_problems,
    lost_versions,
    read_latest,
    read_table,
    table_versions_of,
)
from graspcap.catalog.diff import diff_sessions
from graspcap.catalog.errors import (
    CatalogDamaged,
    CatalogDiskFull,
    CatalogError,
    CatalogLockTimeout,
    CatalogSchemaError,
    writing,
)
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.states import base_of, published_of, version_states
from graspcap.catalog.validate import Batch, rows_to_columns, to_table
from graspcap.schemas.tables import (
    CATALOG_FORMAT_VERSION,
    DATA_TABLES,
    TABLE_SCHEMAS,
    ZARR_LAYOUT,
    Status,
    VersionState,
)

log = logging.getLogger(__name__)

PAUSE_ENV = "GRASPCAP_CATALOG_TEST_PAUSE_AT"
"""Test hook: name of a commit step at which the writer stops (sleeps) so a test can kill it."""
PAUSE_SIGNAL_ENV = "GRASPCAP_CATALOG_TEST_PAUSE_SIGNAL"
"""Test hook: file the paused writer creates once it has reached the step."""
ARRAY_WRITERS = 4
"""Threads writing Zarr groups at once (each mostly waits on zarr's event loop and the disk)."""
PAUSE_POINTS = ("after_lock", "after_arrays", "after_sessions", "after_frames", "after_builds")


@dataclass(frozen=True)
class BuildInfo:
    """The lineage of a build; added, changed, removed and failed sessions are derived."""

    build_id: str
    code_version: str
    config_digest: str
    parameters: Mapping[str, Any] = field(default_factory=dict)
    sessions_unchanged: tuple[str, ...] = ()
    """Sessions the build found up to date and did not rewrite."""


@dataclass(frozen=True)
class SessionArrays:
    """A session's arrays (see ``ZARR_LAYOUT``).

    contact : (n,) float32 in [0, 1] per object vertex; observed : (n,) bool;
    hand_vertices : (v, 3) float32, object frame, m; hand_faces : (f, 3) int32;
    joints : (21, 3) float64, object frame, m.
    """

    contact: np.ndarray
    observed: np.ndarray
    hand_vertices: np.ndarray
    hand_faces: np.ndarray
    joints: np.ndarray

    def groups(self) -> dict[str, dict[str, np.ndarray]]:
        return {
            "contact": {"values": self.contact, "observed": self.observed},
            "hand_mesh": {"vertices": self.hand_vertices, "faces": self.hand_faces,
                          "joints": self.joints},
        }


@dataclass(frozen=True)
class ObjectMesh:
    """vertices : (n, 3) float32, object frame, m; faces : (m, 3) int32."""

    vertices: np.ndarray
    faces: np.ndarray


def mesh_group(mesh: ObjectMesh, owner: str) -> tuple[str, dict[str, np.ndarray]]:
    """The content digest of ``mesh`` and its checked arrays (the session ``owner``'s)."""
    checked = check_arrays("object_mesh", {"vertices": mesh.vertices, "faces": mesh.faces},
                           owner=owner)
    return array_digest("object_mesh", checked), checked


@dataclass(frozen=True)
class BuildCommit:
    """Everything one build writes: its lineage, rows and arrays.

    ``sessions`` and ``frames`` are batches (``pyarrow.Table``, a mapping of columns or a list
    of row dicts) of the catalog schemas; the three ``*_digest`` columns may be left out, they
    are filled from ``session_arrays`` (by session id) and ``object_meshes``. Every session has
    its own object mesh (the input contract): ``object_meshes`` is keyed by session id; a key
    that is an object id instead serves the sessions of that object that have no entry of their
    own (a shorthand where each object has one mesh). Meshes are content-addressed, so equal
    meshes are stored once, and each session's contact map is checked against its own mesh.
    Every session in ``sessions`` replaces its previous row and frames; sessions in ``remove``
    leave the catalog.
    """

    build: BuildInfo
    sessions: Batch
    frames: Batch
    session_arrays: Mapping[str, SessionArrays] = field(default_factory=dict)
    object_meshes: Mapping[str, ObjectMesh] = field(default_factory=dict)
    remove: tuple[str, ...] = ()


def _pause(point: str) -> None:
    if os.environ.get(PAUSE_ENV) != point:
        return
    signal_file = os.environ.get(PAUSE_SIGNAL_ENV)
    if signal_file:
        Path(signal_file).write_text(f"{os.getpid()} {point}\n")
    time.sleep(3600)


@contextmanager
def writer_lock(layout: CatalogLayout, timeout_s: float) -> Iterator[None]:
    """Hold the catalog's exclusive writer lock; wait up to ``timeout_s``, then fail clearly."""
    layout.require_local("writing to a catalog")
    with writing(layout.lock_file):
        fh = open(layout.lock_file, "a+")  # noqa: SIM115 (closed below, after the yield)
    with fh:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    fh.seek(0)
                    holder = fh.read().strip() or "unknown"
                    raise CatalogLockTimeout(
                        f"another writer ({holder}) has held the lock {layout.lock_file} for "
                        f"more than {timeout_s:g} s; retry when its build is done, or raise "
                        "lock_timeout_s") from None
                time.sleep(0.05)
        try:
            with writing(layout.lock_file):
                fh.seek(0)
                fh.truncate()
                fh.write(f"pid {os.getpid()} since {datetime.now(UTC).isoformat()}")
                fh.flush()
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


VERSION_KEY = "graspcap.catalog_version"
"""Commit metadata of every table commit a build makes: the catalog version it was made for."""
BUILD_KEY = "graspcap.build_id"


def _marked(version: int, build_id: str, **more: Any) -> CommitProperties:
    return CommitProperties(custom_metadata={VERSION_KEY: str(version), BUILD_KEY: build_id,
                                             **{k: str(v) for k, v in more.items()}})


def last_version_row(layout: CatalogLayout) -> dict | None:
    """The newest ``versions`` row, or None for an empty catalog."""
    versions = read_latest(layout, "versions")
    if versions.num_rows == 0:
        return None
    i = int(pc.index(versions["version"], pc.max(versions["version"])).as_py())
    return versions.slice(i, 1).to_pylist()[0]


def read_published(layout: CatalogLayout) -> dict | None:
    """``published.json``: ``{"version": N, "table_versions": {...}}`` or None (absent, or
    unreadable: it is evidence only, the versions table stays the truth)."""
    try:
        record = json.loads(layout.published_file.read_text())
        return record if isinstance(record, dict) and type(record.get("version")) is int \
            else None
    except (OSError, ValueError, RecursionError):
        return None


def write_published(layout: CatalogLayout, row: Mapping[str, Any]) -> None:
    """Record ``row`` (a ``versions`` row) as published (temp file, then rename)."""
    record = {"version": int(row["version"]), "build_id": row["build_id"],
              "table_versions": json.loads(row["table_versions"])}
    tmp = layout.published_file.with_suffix(".json.tmp")
    try:
        with writing(layout.published_file):
            tmp.write_text(json.dumps(record, sort_keys=True) + "\n")
            os.replace(tmp, layout.published_file)
    finally:
        tmp.unlink(missing_ok=True)


def _commit_marks(dt: DeltaTable, start: int) -> list[tuple[int, int | None]]:
    """``(Delta version, catalog version it was made for or None)`` of commits ``start``..."""
    out = []
    for entry in dt.history(dt.version() - start + 1):
        mark = entry.get(VERSION_KEY)
        out.append((int(entry["version"]), int(mark) if mark is not None else None))
    return sorted(out)


def check_versions(layout: CatalogLayout) -> tuple[dict | None, list[str]]:
    """The last ``versions`` row and the problems that forbid writing on top of it.

    Problems: a table log with a gap or an unreadable entry; version numbers with a gap; a
    versions row pinning a Delta version its table no longer has; evidence that a version
    after the last row was published (``published.json``, a tag, a table commit or builds row
    made for a later version, a ``versions`` data file no log entry lists).
    """
    problems = [p for name in TABLE_SCHEMAS for p in log_problems(layout, name, parse=False)]
    if problems:
        return None, problems
    versions = read_latest(layout, "versions")
    numbers = sorted(versions["version"].to_pylist())
    row = last_version_row(layout)
    last = numbers[-1] if numbers else 0
    lost = sorted(set(range(1, last + 1)) - set(numbers))
    if lost:
        problems.append(f"{layout.table('versions')}: the versions table has no row for "
                        f"version(s) {lost} although later versions exist (rows deleted)")
    newest = {name: delta_version(layout, name) for name in TABLE_SCHEMAS}
    for r in versions.to_pylist():
        for name, pinned in table_versions_of(r).items():
            if pinned > newest[name]:
                problems.append(
                    f"{log_dir(layout, name)}: version {r['version']} pins table {name!r} at "
                    f"Delta version {pinned} but its log ends at {newest[name]} "
                    f"({lost_versions(list(range(newest[name] + 1, pinned + 1)))})")
    published = read_published(layout)
    if published is not None and published["version"] > last:
        problems.append(f"{layout.published_file}: version {published['version']} was "
                        f"published, but the versions table ends at version {last} (its "
                        "rows or log entries after that were lost)")
    tags = read_latest(layout, "tags")
    for tag, version in zip(tags["tag"].to_pylist(), tags["version"].to_pylist(), strict=True):
        if version > last:
            problems.append(f"{layout.table('tags')}: tag {tag!r} points at version {version} "
                            f"but the versions table ends at version {last}")
    changes = (read_latest(layout, "publications").select(["version", "state"]).to_pylist()
               if "publications" in TABLE_SCHEMAS else [])  # else: an older format's golden
    for version, state in ((c["version"], c["state"]) for c in changes):
        if version > last:
            problems.append(f"{layout.table('publications')}: version {version} was {state}, "
                            f"but the versions table ends at version {last}")
    expected = table_versions_of(row) if row else INITIAL_TABLE_VERSIONS
    for name in DATA_TABLES if row is not None and not problems else ():
        have = delta_table(layout, name, expected[name]).count()  # from the log's stats
        if have != row[f"rows_{name}"]:
            problems.append(
                f"{layout.table(name)}: table {name!r} at version {last} has {have} rows, but "
                f"version {last} was committed with {row[f'rows_{name}']}: a Delta log entry "
                "of it was altered")
    for name in DATA_TABLES:
        if newest[name] <= expected[name]:
            continue
        for delta_v, made_for in _commit_marks(delta_table(layout, name), expected[name] + 1):
            if made_for is not None and made_for > last + 1:
                problems.append(
                    f"{entry_path(layout, name, delta_v)}: table {name!r}: Delta version "
                    f"{delta_v} was made for catalog version {made_for}, so "
                    f"{_published(last + 1, made_for - 1)} published, but the versions table "
                    f"ends at {last}")
    builds = read_table(layout, "builds", newest["builds"], ["build_id", "catalog_version"])
    for build_id, made_for in zip(builds["build_id"].to_pylist(),
                                  builds["catalog_version"].to_pylist(), strict=True):
        if made_for > last + 1:
            problems.append(f"{layout.table('builds')}: build {build_id!r} was committed as "
                            f"version {made_for}, so {_published(last + 1, made_for - 1)} "
                            f"published, but the versions table ends at {last}")
    if published is None:  # no record (older catalog): look for a row whose log entry is lost
        listed = {str(Path(f).resolve()) for f in intact_files(layout, "versions")}
        for path in sorted(layout.table("versions").glob("*.parquet")):
            if str(path.resolve()) in listed:
                continue
            try:
                stray = pq.read_table(path, columns=["version"])["version"].to_pylist()
            except (OSError, pa.ArrowException):
                continue
            if any(v > last for v in stray):
                entry = entry_path(layout, "versions", newest["versions"] + 1)
                problems.append(f"{path}: holds the versions row of version(s) "
                                f"{sorted(v for v in stray if v > last)}, which no log entry "
                                f"lists (its log entry {entry} was lost, or a writer died "
                                "while appending it)")
    return row, problems


def _published(first: int, last: int) -> str:
    return f"version {first} was" if first == last else f"versions {first}-{last} were"


REPAIR_VERSIONS = (
    "when the lost or garbled files are the versions table's log entries, `graspcap catalog "
    "repair --catalog CATALOG` puts their rows back from the rows' own data files; "
    "else put the lost files back from a backup or snapshot of the catalog (the newest version "
    "stays unwritable until then: rolling the tables back would drop data a reader may have "
    "seen, and a new version would reuse a published number). Readers of the intact versions "
    "keep working; to go on without the lost version, rebuild into a new catalog (`graspcap "
    "build SESSIONS --catalog NEW`) or export a readable one (`graspcap catalog export VERSION "
    "--out DIR`)")


def recover(layout: CatalogLayout) -> dict[str, int]:
    """Roll back table commits no ``versions`` row could have published; return
    ``{table: rolled-back-from}``.

    Only commits of a writer that died between a table commit and its ``versions`` row are
    undone; when anything says a version after the last row was published (``check_versions``)
    nothing is rolled back and ``CatalogDamaged`` names what is missing. Call only under the
    writer lock.
    """
    row, problems = check_versions(layout)
    if problems:
        raise CatalogDamaged(layout.uri, problems, REPAIR_VERSIONS)
    last = row["version"] if row else 0
    expected = table_versions_of(row) if row else INITIAL_TABLE_VERSIONS
    rolled = {}
    for name in DATA_TABLES:
        dt = delta_table(layout, name)
        if dt.version() != expected[name]:
            rolled[name] = dt.version()
            with _table_write(layout, name):
                dt.restore(expected[name], commit_properties=_marked(
                    last, "recover", **{"graspcap.rolled_back_from": dt.version()}))
    if row is not None and (read_published(layout) or {}).get("version", 0) < last:
        write_published(layout, row)  # a writer died between its versions row and the record
    return rolled


def _landed(layout: CatalogLayout, version: int, build_id: str) -> bool:
    """Whether the versions row of ``version`` by ``build_id`` is committed."""
    try:
        row = last_version_row(layout)
    except CatalogError:
        return False
    return row is not None and row["version"] == version and row["build_id"] == build_id


@contextmanager
def _table_write(layout: CatalogLayout, name: str) -> Iterator[None]:
    """One Delta commit to table ``name``: ENOSPC names the table folder; any other deltalake
    error becomes a ``CatalogError`` naming the table, without the Rust backtrace."""
    try:
        with writing(layout.table(name)):
            yield
    except DeltaError as exc:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise CatalogError(
            f"writing table {name!r} ({layout.table(name)}) failed: {first[:500]}; nothing "
            "of this build is committed and every earlier version is intact") from None


def _as_list(values: Any) -> list:
    if values is None:
        return []
    if isinstance(values, pa.ChunkedArray | pa.Array):
        return values.to_pylist()
    return list(values)


def _prepare(commit: BuildCommit) -> tuple[pa.Table, pa.Table, dict[str, tuple[str, dict]]]:
    """Validate rows and arrays, fill the digest columns; no writes."""
    sessions = commit.sessions
    digest_cols = [g.digest_column for g in ZARR_LAYOUT.values()]
    if isinstance(sessions, pa.Table):
        sessions = {c: sessions[c] for c in sessions.column_names}
    elif not isinstance(sessions, Mapping):
        sessions = rows_to_columns("sessions", sessions)
    sessions = dict(sessions)
    ids = [str(s) for s in _as_list(sessions.get("session_id"))]
    objects = _as_list(sessions.get("object_id"))
    groups: dict[str, tuple[str, dict]] = {}
    filled = {c: [None] * len(ids) for c in digest_cols}
    for i, sid in enumerate(ids):
        arrays = commit.session_arrays.get(sid)
        if arrays is not None:
            for kind, group in arrays.groups().items():
                checked = check_arrays(kind, group, owner=sid)
                digest = array_digest(kind, checked)
                groups[digest] = (kind, checked)
                filled[ZARR_LAYOUT[kind].digest_column][i] = digest
        mesh = commit.object_meshes.get(sid)
        if mesh is None and i < len(objects):
            mesh = commit.object_meshes.get(objects[i])
        if mesh is not None:
            digest, checked = mesh_group(mesh, sid)
            groups[digest] = ("object_mesh", checked)
            filled["object_mesh_digest"][i] = digest
            if arrays is not None and len(arrays.contact) != len(checked["vertices"]):
                raise CatalogSchemaError("arrays/contact", "values", [sid],
                                         f"{len(arrays.contact)} contact values for the "
                                         f"session's object mesh of {len(checked['vertices'])} "
                                         f"vertices (object {objects[i]!r})")
    for col in digest_cols:
        if col not in sessions:
            sessions[col] = filled[col]
    sessions_t = to_table("sessions", sessions)
    frames_t = to_table("frames", commit.frames)
    stray = set(frames_t["session_id"].to_pylist()) - set(ids)
    if stray:
        raise CatalogSchemaError("frames", "session_id", sorted(stray),
                                 "frames of a session that is not in this build's sessions")
    return sessions_t, frames_t, groups


def _known(name: str, row: dict[str, Any]) -> dict[str, Any]:
    """``row`` without the keys table ``name``'s schema lacks (only the golden catalogs of
    older formats, ``tests/golden/make_golden.py``, write with fewer columns)."""
    names = set(TABLE_SCHEMAS[name].names)
    return {k: v for k, v in row.items() if k in names}


def _predicate(ids: list[str]) -> str:
    quoted = ", ".join("'" + s.replace("'", "''") + "'" for s in ids)
    return f"session_id IN ({quoted})"


def rows_by_version(layout: CatalogLayout) -> dict[int, dict]:
    """Every ``versions`` row by its version number."""
    return {int(r["version"]): r for r in read_latest(layout, "versions").to_pylist()}


def commit_build(layout: CatalogLayout, commit: BuildCommit, *, lock_timeout_s: float,
                 format_version: int = CATALOG_FORMAT_VERSION,
                 gates: AuditGates | None = None) -> int:
    """Run the commit protocol (module docstring); return the new catalog version.

    The version is written on top of the newest version that is not rejected (its *base*:
    when the newest is rejected, every data table is first restored to the base's pins, in
    commits marked for the new version, so a killed writer's restore is rolled back like any
    orphan). ``gates``: audit the version (``catalog.audit``) and record the outcome in its
    builds row; it is published when the audit passes (and ``gates.auto_publish``), else
    staged. Without gates it is published unless its base is not (then it is staged too: a
    commit never publishes unaudited rows by the back door).
    ``format_version`` goes into the versions row; only the golden catalog of an older format
    passes another one.
    """
    sessions, frames, groups = _prepare(commit)
    ids = sessions["session_id"].to_pylist()
    with writer_lock(layout, lock_timeout_s):
        _pause("after_lock")
        recover(layout)
        remove_temp_groups(layout)  # what a killed writer left; no live writer holds the lock
        last = last_version_row(layout)
        version = (last["version"] if last else 0) + 1
        by_version = rows_by_version(layout)
        states = version_states(layout)
        base = base_of(states)
        row = by_version[base] if base is not None else None
        previous = table_versions_of(row) if row else INITIAL_TABLE_VERSIONS
        for name in DATA_TABLES:  # the newest versions are rejected: start from the base
            dt = delta_table(layout, name)
            if dt.version() != previous[name]:
                with _table_write(layout, name):
                    dt.restore(previous[name], commit_properties=_marked(
                        version, commit.build.build_id, **{"graspcap.base_version": base}))
        missing = set(sessions["contact_digest"].drop_null().to_pylist()
                      + sessions["hand_mesh_digest"].drop_null().to_pylist()
                      + sessions["object_mesh_digest"].drop_null().to_pylist()) - set(groups)
        absent = [d for d in missing if not layout.array_group(d).is_dir()]
        if absent:
            raise CatalogSchemaError("sessions", "*_digest", [], f"no array group {absent[0]} "
                                     "in this build or the catalog")
        with writing(layout.arrays_dir), \
                ThreadPoolExecutor(max_workers=ARRAY_WRITERS) as pool:  # zarr waits on I/O
            list(pool.map(lambda item: write_group(layout, item[1][0], item[1][1], item[0]),
                          groups.items()))
        _pause("after_arrays")

        old = read_table(layout, "sessions", previous["sessions"])
        touched = sorted(set(ids) | set(commit.remove))
        diff = diff_sessions(old.filter(pc.is_in(old["session_id"], pa.array(touched,
                                                                              pa.string()))),
                             sessions, ignore=("build_id",))
        marked = _marked(version, commit.build.build_id)
        if touched:
            with _table_write(layout, "sessions"):
                write_deltalake(str(layout.table("sessions")), sessions, mode="overwrite",
                                predicate=_predicate(touched), commit_properties=marked)
        _pause("after_sessions")
        if touched:
            with _table_write(layout, "frames"):
                write_deltalake(str(layout.table("frames")), frames, mode="overwrite",
                                predicate=_predicate(touched), commit_properties=marked)
        _pause("after_frames")

        published = published_of(states)
        audit = None
        if gates is not None:
            audit = audit_version(
                layout, {n: delta_version(layout, n) for n in ("sessions", "frames")}
                | {"builds": previous["builds"]},
                (published, table_versions_of(by_version[published]))
                if published is not None else None, gates, commit.remove)
            state = VersionState.PUBLISHED if audit.passed and gates.auto_publish \
                else VersionState.STAGED
        else:
            state = VersionState.PUBLISHED if base is None or base == published \
                else VersionState.STAGED
        now = datetime.now(UTC)
        status = sessions["status"].to_pylist()
        errors = sessions["error"].to_pylist()
        build_row = {
            "build_id": commit.build.build_id, "catalog_version": version, "time_utc": now,
            "code_version": commit.build.code_version,
            "config_digest": commit.build.config_digest,
            "parameters_json": json.dumps(dict(commit.build.parameters), sort_keys=True,
                                          default=str),
            "sessions_added": diff.added,
            "sessions_changed": sorted(diff.changed),
            "sessions_unchanged": sorted(set(commit.build.sessions_unchanged)
                                         | (set(ids) - set(diff.added) - set(diff.changed))),
            "sessions_removed": sorted(set(commit.remove) & set(old["session_id"].to_pylist())),
            "sessions_failed": [{"session_id": s, "error": e} for s, st, e
                                in zip(ids, status, errors, strict=True) if st == Status.FAILED],
            "audit_passed": None if audit is None else audit.passed,
            "audit_reasons": None if audit is None else audit.reasons,
            "audit_json": None if audit is None else audit.to_json(),
        }
        build_row = _known("builds", build_row)
        with _table_write(layout, "builds"):
            write_deltalake(str(layout.table("builds")), to_table("builds", [build_row]),
                            mode="append", commit_properties=marked)
        _pause("after_builds")

        pinned = {name: delta_version(layout, name) for name in DATA_TABLES}
        counts = {name: delta_table(layout, name).count() for name in DATA_TABLES}
        versions_row = {
            "version": version, "time_utc": now, "build_id": commit.build.build_id,
            "format_version": format_version,
            "table_versions": json.dumps(pinned, sort_keys=True),
            **{f"rows_{name}": counts[name] for name in DATA_TABLES},
            "state": state.value,
        }
        try:
            with _table_write(layout, "versions"):
                write_deltalake(str(layout.table("versions")),
                                to_table("versions", [_known("versions", versions_row)]),
                                mode="append",
                                commit_properties=marked)
        except CatalogError as exc:  # a failure after the row landed (a checkpoint) is no loss
            if not _landed(layout, version, commit.build.build_id):
                raise
            log.warning("version %d is committed; %s", version, exc)
        try:  # evidence for recovery; the version is committed whatever happens here
            write_published(layout, versions_row)
        except CatalogDiskFull as exc:
            log.warning("version %d is committed; %s", version, exc)
    return version
