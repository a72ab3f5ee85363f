"""One build = one catalog version, atomic across every table and array.

Protocol (under the writer lock):

1. read the last ``versions`` row: the Delta version every data table must be at;
2. roll back any table that is newer (a writer died after a table commit, before its versions
   row) with ``DeltaTable.restore``;
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
from deltalake import DeltaTable, write_deltalake

from graspcap.catalog.arrays import (
    array_digest,
    check_arrays,
    remove_temp_groups,
    write_group,
)
from graspcap.catalog.delta import (
    INITIAL_TABLE_VERSIONS,
    delta_version,
    read_latest,
    read_table,
    table_versions_of,
)
from graspcap.catalog.diff import diff_sessions
from graspcap.catalog.errors import CatalogLockTimeout, CatalogSchemaError
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.validate import Batch, rows_to_columns, to_table
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION, DATA_TABLES, ZARR_LAYOUT, Status

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
    with open(layout.lock_file, "a+") as fh:
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
            fh.seek(0)
            fh.truncate()
            fh.write(f"pid {os.getpid()} since {datetime.now(UTC).isoformat()}")
            fh.flush()
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def last_version_row(layout: CatalogLayout) -> dict | None:
    """The newest ``versions`` row, or None for an empty catalog."""
    versions = read_latest(layout, "versions")
    if versions.num_rows == 0:
        return None
    i = int(pc.index(versions["version"], pc.max(versions["version"])).as_py())
    return versions.slice(i, 1).to_pylist()[0]


def recover(layout: CatalogLayout) -> dict[str, int]:
    """Roll back table commits no ``versions`` row covers; return ``{table: rolled-back-from}``.

    Call only under the writer lock.
    """
    row = last_version_row(layout)
    expected = table_versions_of(row) if row else INITIAL_TABLE_VERSIONS
    rolled = {}
    for name in DATA_TABLES:
        dt = DeltaTable(str(layout.table(name)))
        if dt.version() != expected[name]:
            rolled[name] = dt.version()
            dt.restore(expected[name])
    return rolled


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
            checked = check_arrays("object_mesh", {"vertices": mesh.vertices,
                                                    "faces": mesh.faces}, owner=sid)
            digest = array_digest("object_mesh", checked)
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


def _predicate(ids: list[str]) -> str:
    quoted = ", ".join("'" + s.replace("'", "''") + "'" for s in ids)
    return f"session_id IN ({quoted})"


def commit_build(layout: CatalogLayout, commit: BuildCommit, *, lock_timeout_s: float,
                 format_version: int = CATALOG_FORMAT_VERSION) -> int:
    """Run the commit protocol (module docstring); return the new catalog version.

    ``format_version`` goes into the versions row; only the golden catalog of an older format
    passes another one.
    """
    sessions, frames, groups = _prepare(commit)
    ids = sessions["session_id"].to_pylist()
    with writer_lock(layout, lock_timeout_s):
        _pause("after_lock")
        recover(layout)
        remove_temp_groups(layout)  # what a killed writer left; no live writer holds the lock
        row = last_version_row(layout)
        previous = table_versions_of(row) if row else INITIAL_TABLE_VERSIONS
        version = (row["version"] if row else 0) + 1
        missing = set(sessions["contact_digest"].drop_null().to_pylist()
                      + sessions["hand_mesh_digest"].drop_null().to_pylist()
                      + sessions["object_mesh_digest"].drop_null().to_pylist()) - set(groups)
        absent = [d for d in missing if not layout.array_group(d).is_dir()]
        if absent:
            raise CatalogSchemaError("sessions", "*_digest", [], f"no array group {absent[0]} "
                                     "in this build or the catalog")
        with ThreadPoolExecutor(max_workers=ARRAY_WRITERS) as pool:  # zarr waits on I/O
            list(pool.map(lambda item: write_group(layout, item[1][0], item[1][1], item[0]),
                          groups.items()))
        _pause("after_arrays")

        old = read_table(layout, "sessions", previous["sessions"])
        touched = sorted(set(ids) | set(commit.remove))
        diff = diff_sessions(old.filter(pc.is_in(old["session_id"], pa.array(touched,
                                                                              pa.string()))),
                             sessions, ignore=("build_id",))
        if touched:
            write_deltalake(str(layout.table("sessions")), sessions, mode="overwrite",
                            predicate=_predicate(touched))
        _pause("after_sessions")
        if touched:
            write_deltalake(str(layout.table("frames")), frames, mode="overwrite",
                            predicate=_predicate(touched))
        _pause("after_frames")

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
        }
        write_deltalake(str(layout.table("builds")), to_table("builds", [build_row]),
                        mode="append")
        _pause("after_builds")

        pinned = {name: delta_version(layout, name) for name in DATA_TABLES}
        counts = {name: DeltaTable(str(layout.table(name))).count() for name in DATA_TABLES}
        versions_row = {
            "version": version, "time_utc": now, "build_id": commit.build.build_id,
            "format_version": format_version,
            "table_versions": json.dumps(pinned, sort_keys=True),
            **{f"rows_{name}": counts[name] for name in DATA_TABLES},
        }
        write_deltalake(str(layout.table("versions")), to_table("versions", [versions_row]),
                        mode="append")
    return version
