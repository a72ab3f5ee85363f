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
   published version whose row was lost. Version numbers are never reused (this step lives in
   ``catalog/recovery.py``);
3. write the arrays (content-addressed Zarr groups, temp name then rename; first remove what
   killed writers left under ``arrays/.tmp``);
4. per data table one Delta commit: replace the rows of the sessions the build touches
   (``mode="overwrite"`` with a ``session_id IN (...)`` predicate; rows sorted by session and
   ``frames`` in files of about ``FRAMES_FILE_BYTES``, so the commit rewrites only the files
   that hold a touched session), append the builds row;
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
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from deltalake import ColumnProperties, WriterProperties, write_deltalake

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
    read_latest,
    read_table,
    table_versions_of,
)
from graspcap.catalog.diff import diff_sessions
from graspcap.catalog.errors import (
    CatalogDiskFull,
    CatalogError,
    CatalogLockTimeout,
    CatalogSchemaError,
    writing,
)
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.recovery import (
    _marked,
    _table_write,
    last_version_row,
    recover,
    write_published,
)
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


def _landed(layout: CatalogLayout, version: int, build_id: str) -> bool:
    """Whether the versions row of ``version`` by ``build_id`` is committed."""
    try:
        row = last_version_row(layout)
    except CatalogError:
        return False
    return row is not None and row["version"] == version and row["build_id"] == build_id


def _as_list(values: Any) -> list:
    if values is None:
        return []
    if isinstance(values, pa.ChunkedArray | pa.Array):
        return values.to_pylist()
    return list(values)


GroupSource = Callable[[], dict[str, np.ndarray]]
"""Reads one checked array group again when it is written (``_prepare``)."""


def _session_group(arrays: Mapping[str, SessionArrays], sid: str, kind: str) -> GroupSource:
    return lambda: check_arrays(kind, arrays[sid].groups()[kind], owner=sid)


def _mesh_group(meshes: Mapping[str, ObjectMesh], key: str, owner: str) -> GroupSource:
    return lambda: mesh_group(meshes[key], owner)[1]


def _prepare(commit: BuildCommit) -> tuple[pa.Table, pa.Table, dict[str, tuple[str, GroupSource]]]:
    """Validate rows and arrays, fill the digest columns; no writes. Each array group's digest
    comes with the kind and a source that reads it again from the commit's mappings when it is
    written, so a commit of many sessions never holds all their arrays at once (a build hands
    mappings that read them from its work area: ``flows/assemble.py``)."""
    sessions = commit.sessions
    digest_cols = [g.digest_column for g in ZARR_LAYOUT.values()]
    if isinstance(sessions, pa.Table):
        sessions = {c: sessions[c] for c in sessions.column_names}
    elif not isinstance(sessions, Mapping):
        sessions = rows_to_columns("sessions", sessions)
    sessions = dict(sessions)
    ids = [str(s) for s in _as_list(sessions.get("session_id"))]
    objects = _as_list(sessions.get("object_id"))
    groups: dict[str, tuple[str, GroupSource]] = {}
    filled = {c: [None] * len(ids) for c in digest_cols}
    for i, sid in enumerate(ids):
        arrays = commit.session_arrays.get(sid)
        if arrays is not None:
            for kind, group in arrays.groups().items():
                digest = array_digest(kind, check_arrays(kind, group, owner=sid))
                groups[digest] = (kind, _session_group(commit.session_arrays, sid, kind))
                filled[ZARR_LAYOUT[kind].digest_column][i] = digest
        key, mesh = sid, commit.object_meshes.get(sid)
        if mesh is None and i < len(objects):
            key, mesh = objects[i], commit.object_meshes.get(objects[i])
        if mesh is not None:
            digest, checked = mesh_group(mesh, sid)
            if digest not in groups:
                groups[digest] = ("object_mesh", _mesh_group(commit.object_meshes, key, sid))
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


FRAMES_FILE_BYTES = 8 << 20
"""Target size of a ``frames`` Parquet file (``write_deltalake(target_file_size=...)``). With
the rows sorted by session the files hold disjoint ``session_id`` ranges, so a build that
replaces one session rewrites the one file that holds it (two when it straddles a boundary),
not the whole table; ``optimize`` compacts small files up to this size too. Files come out at
the first multiple of 1,024 rows past the target (~9 MB here: deltalake 1.6 slices a batch
into 1,024-row pieces and checks the size after each). The size trades the rewrite against
the per-file cost of a full read (docs/catalog.md, "The frames layout"; docs/benchmarks.md,
``bench/compaction.py --one-session``)."""


FRAMES_WRITER = WriterProperties(
    compression="SNAPPY",
    default_column_properties=ColumnProperties(dictionary_enabled=False),
    column_properties={c: ColumnProperties(dictionary_enabled=True) for c in
                       ("session_id", "build_id", "camera_reason", "hand_reason",
                        "object_reason")})
"""How ``frames`` files are written (builds and ``optimize``): dictionary encoding only for the
strings. Measured floats never repeat, and each file's failed dictionary attempt costs up to
1 MiB a column: 1,000 sessions in ~9 MB files took 105 MB with it, 90 MB without (one file:
91 MB; ``FRAMES_FILE_BYTES``)."""


def session_order(table: pa.Table) -> pa.Table:
    """``table``'s rows sorted by ``session_id`` (then ``frame``, when it has one), as one
    record batch: the form a build writes them in. One batch matters: deltalake spreads several
    batches over parallel writers, each file then holding every other batch (overlapping
    ranges), while it writes one batch's slices in order."""
    keys = [("session_id", "ascending")]
    if "frame" in table.column_names:
        keys.append(("frame", "ascending"))
    return table.sort_by(keys).combine_chunks()


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
            list(pool.map(lambda item: write_group(layout, item[1][0], item[1][1](), item[0]),
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
                write_deltalake(str(layout.table("sessions")), session_order(sessions),
                                mode="overwrite", predicate=_predicate(touched),
                                commit_properties=marked)
        _pause("after_sessions")
        if touched:
            with _table_write(layout, "frames"):
                write_deltalake(str(layout.table("frames")), session_order(frames),
                                mode="overwrite", predicate=_predicate(touched),
                                target_file_size=FRAMES_FILE_BYTES,
                                writer_properties=FRAMES_WRITER, commit_properties=marked)
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
