"""``Catalog``: list, read (by version number or tag), compare, commit to and vacuum a catalog.

A catalog version is a row of the ``versions`` table pinning a Delta version of each data table;
everything a version shows is read at those pins, so versions are immutable and reads are cached
per version. ``Catalog`` holds only its root and settings: it pickles cheaply into DataLoader
workers and reopens lazily there.
"""

from __future__ import annotations

import json
import re
import uuid
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
from deltalake import write_deltalake

from graspcap.catalog.arrays import read_group
from graspcap.catalog.audit import AuditGates
from graspcap.catalog.commit import BuildCommit, BuildInfo, commit_build, writer_lock
from graspcap.catalog.delta import (
    REPAIR_LOG,
    MissingFiles,
    create_tables,
    log_problems,
    read_files,
    read_latest,
    table_files,
    table_versions_of,
)
from graspcap.catalog.diff import diff_sessions
from graspcap.catalog.errors import CatalogDamaged, CatalogError, VersionNotFound, writing
from graspcap.catalog.layout import CatalogLayout, check_format, write_format_file
from graspcap.catalog.recovery import REPAIR_VERSIONS, check_versions
from graspcap.catalog.states import base_of, published_of, version_states
from graspcap.catalog.vacuum import VacuumReport, vacuum_catalog, vacuumed_versions
from graspcap.catalog.validate import to_table
from graspcap.schemas.tables import DATA_TABLES, VersionState

_TAG = re.compile(r"[A-Za-z][A-Za-z0-9._-]*")


class TagExists(CatalogError):
    """A tag already points at another version (moving it needs ``force``)."""

    def __init__(self, name: str, current: int, wanted: int):
        self.name, self.current, self.wanted = name, current, wanted
        super().__init__(f"tag {name!r} already points at version {current}; to move it to "
                         f"version {wanted}, pass --force (Catalog.tag(..., force=True))")


def open(uri: str | Path, *, create: bool = False, lock_timeout_s: float = 60.0,  # noqa: A001
         storage_options: dict[str, str] | None = None) -> Catalog:
    """Open the catalog at ``uri``; ``create`` makes it when absent (local folders only).

    ``uri`` is a local path, a ``file://`` URL, or an object-store URL deltalake serves
    (``s3://``, ``gs://``, ``az://``, ...; read-only here, credentials in ``storage_options``).
    Fails with ``CatalogFormatError`` naming the way forward when the folder holds a catalog of
    another format version.
    """
    layout = CatalogLayout.from_uri(uri, storage_options)
    if create and layout.is_local and not layout.format_file.exists():
        with writing(layout.root):
            layout.root.mkdir(parents=True, exist_ok=True)
        with writer_lock(layout, lock_timeout_s):  # two creators at once: one creates
            if not layout.format_file.exists():
                create_tables(layout)
                write_format_file(layout)  # last: a half-created catalog has no stamp
    check_format(layout)
    return Catalog(layout, lock_timeout_s=lock_timeout_s)


class Catalog:
    """A versioned Parquet + Zarr catalog (see ``docs/architecture.md``, "Catalog")."""

    def __init__(self, layout: CatalogLayout, *, lock_timeout_s: float = 60.0):
        self.layout = layout
        self.lock_timeout_s = lock_timeout_s
        self._pins: dict[int, dict[str, int]] = {}
        self._counts: dict[int, dict[str, int]] = {}
        """Rows per data table of each version, as its ``versions`` row recorded them."""
        self._files: dict[tuple[str, int], list[str]] = {}
        self._tables: dict[tuple[str, int], pa.Table] = {}
        self._index: dict[int, dict[str, dict]] = {}

    def __repr__(self) -> str:
        return f"Catalog({self.layout.uri!r})"

    def __getstate__(self) -> dict:
        # pins and file lists are small and immutable: a worker that has them reads tables with
        # pyarrow alone (deltalake's tokio runtime panics in a fork of a process that used it)
        return {"layout": self.layout, "lock_timeout_s": self.lock_timeout_s,
                "pins": self._pins, "counts": self._counts, "files": self._files}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["layout"], lock_timeout_s=state["lock_timeout_s"])
        self._pins.update(state.get("pins", {}))
        self._counts.update(state.get("counts", {}))
        self._files.update(state.get("files", {}))

    # versions and tags ------------------------------------------------------------------
    def _versions_raw(self) -> pa.Table:
        return read_latest(self.layout, "versions").sort_by("version")

    def tags(self) -> dict[str, int]:
        """``{tag: version}``; the latest row of each tag wins."""
        rows = read_latest(self.layout, "tags").sort_by("time_utc").to_pylist()
        return {r["tag"]: r["version"] for r in rows}

    def versions(self) -> pa.Table:
        """One row per version: version, time_utc, build_id, tags, row counts, table pins."""
        table = self._versions_raw()
        by_version: dict[int, list[str]] = {}
        for tag, v in sorted(self.tags().items()):
            by_version.setdefault(v, []).append(tag)
        tags = pa.array([by_version.get(v, []) for v in table["version"].to_pylist()],
                        pa.list_(pa.string()))
        states = version_states(self.layout, table)
        table = table.add_column(3, "tags", tags)
        current = pa.array([states[v].value for v in table["version"].to_pylist()], pa.string())
        return table.drop_columns(["state"]).append_column("state", current)

    def latest_version(self) -> int | None:
        """The newest committed version, published or not; None for an empty catalog
        (readers' default is :meth:`published_version`)."""
        versions = read_latest(self.layout, "versions")
        return None if versions.num_rows == 0 else int(pc.max(versions["version"]).as_py())

    def states(self) -> dict[int, VersionState]:
        """``{version: published | staged | rejected}`` (write-audit-publish). Reads the
        versions table once and keeps every version's pins (immutable) for the reads after."""
        versions = self._versions_raw()
        for row in versions.to_pylist():
            if row["version"] not in self._pins:
                self._counts[row["version"]] = {n: row[f"rows_{n}"] for n in DATA_TABLES}
                self._pins[row["version"]] = table_versions_of(row)
        return version_states(self.layout, versions)

    def published_version(self) -> int | None:
        """The newest published version: what ``table()``, ``GraspDataset`` and every reader
        read when no version is named; None when no version is published."""
        return published_of(self.states())

    def base_version(self) -> int | None:
        """The newest version that is not rejected: what the next build is written on top
        of (and plans against); None for an empty catalog."""
        return base_of(self.states())

    def resolve(self, version: int | str | None = None) -> int:
        """The version number of ``version`` (None = the newest published, str = tag)."""
        if version is None:
            states = self.states()
            published = published_of(states)
            if published is None:
                if not states:
                    raise VersionNotFound(f"catalog {self.layout.uri} has no version yet")
                staged = sorted(v for v, s in states.items() if s == VersionState.STAGED)
                raise VersionNotFound(
                    f"catalog {self.layout.uri} has no published version (staged: "
                    f"{staged or '-'}; `graspcap catalog versions` says why): read one by "
                    "number, or publish it with `graspcap catalog publish VERSION`")
            return published
        if isinstance(version, str):
            tags = self.tags()
            if version not in tags:
                raise VersionNotFound(f"no tag {version!r} (tags: {sorted(tags)})")
            return tags[version]
        version = int(version)
        self._pinned(version)
        return version

    def _pinned(self, version: int) -> dict[str, int]:
        if version not in self._pins:
            rows = self._versions_raw().filter(pc.equal(pc.field("version"), version))
            if rows.num_rows == 0:
                raise VersionNotFound(f"catalog {self.layout.uri} has no version {version} "
                                      f"(latest: {self.latest_version()})")
            row = rows.to_pylist()[0]
            self._counts[version] = {name: row[f"rows_{name}"] for name in DATA_TABLES}
            self._pins[version] = table_versions_of(row)
        return self._pins[version]

    def tag(self, version: int, name: str, *, force: bool = False) -> bool:
        """Point tag ``name`` at ``version``. A tag that points at another version moves only
        with ``force`` (else :class:`TagExists` names the version it points at); False when it
        already points at ``version`` (nothing written)."""
        if not _TAG.fullmatch(name):
            raise ValueError(f"tag {name!r}: use a letter then letters, digits, '.', '_', '-'")
        self._pinned(int(version))
        row = {"tag": name, "version": int(version), "time_utc": datetime.now(UTC)}
        with writer_lock(self.layout, self.lock_timeout_s):
            _, problems = check_versions(self.layout)  # writers stop on a damaged catalog
            if problems:
                raise CatalogDamaged(self.layout.uri, problems, REPAIR_VERSIONS)
            current = self.tags().get(name)
            if current == int(version):
                return False
            if current is not None and not force:
                raise TagExists(name, current, int(version))
            with writing(self.layout.table("tags")):
                write_deltalake(str(self.layout.table("tags")), to_table("tags", [row]),
                                mode="append")
        return True

    def publish(self, version: int, reason: str = "") -> bool:
        """Publish ``version`` by hand (whatever its audit said): readers' default becomes the
        newest published version. False when it already is published (nothing written)."""
        return self._set_state(int(version), VersionState.PUBLISHED, reason)

    def reject(self, version: int, reason: str = "") -> bool:
        """Reject ``version``: it is no reader's default and the next build is written on
        top of the newest version that is not rejected. It stays readable by number. A
        version with a newer version that is not rejected cannot be rejected (that one was
        written on top of it: reject it first). False when already rejected."""
        return self._set_state(int(version), VersionState.REJECTED, reason)

    def _set_state(self, version: int, state: VersionState, reason: str) -> bool:
        self._pinned(version)
        with writer_lock(self.layout, self.lock_timeout_s):
            _, problems = check_versions(self.layout)
            if problems:
                raise CatalogDamaged(self.layout.uri, problems, REPAIR_VERSIONS)
            states = self.states()
            if states[version] == state:
                return False
            if state == VersionState.REJECTED:
                later = [v for v, s in states.items() if v > version
                         and s != VersionState.REJECTED]
                if later:
                    raise CatalogError(
                        f"version(s) {later} were written on top of version {version} and hold "
                        f"its changes; reject them first (newest first), then version "
                        f"{version}")
            if state == VersionState.PUBLISHED and version in vacuumed_versions(self.layout):
                raise CatalogError(f"version {version} was vacuumed (files it needs are gone) "
                                   "and cannot be published")
            row = {"version": version, "state": state.value, "time_utc": datetime.now(UTC),
                   "reason": reason}
            with writing(self.layout.table("publications")):
                write_deltalake(str(self.layout.table("publications")),
                                to_table("publications", [row]), mode="append")
        return True

    def audit(self, version: int | str | None = None) -> dict | None:
        """The audit of the build that made ``version``: ``{"passed", "reasons",
        "compared_to", "measured", "gates"}``, None when it was committed without one."""
        v = self.resolve(version)
        rows = self.table("builds", v).filter(pc.equal(pc.field("catalog_version"), v))
        for row in rows.to_pylist():
            if row["audit_json"]:
                return json.loads(row["audit_json"])
        return None

    def problems(self) -> list[str]:
        """What a writer would stop on, one line per problem naming the file (empty for a
        healthy catalog): lost or unreadable Delta log entries, lost versions rows, pins past a
        table's log. Parquet files and arrays are not opened (``catalog verify`` does that)."""
        if not self.layout.is_local:
            return []
        try:
            return check_versions(self.layout)[1]
        except CatalogDamaged as exc:
            return exc.problems
        except CatalogError as exc:  # a file the check needs is gone or unreadable
            return [str(exc)]

    # tables -----------------------------------------------------------------------------
    def files(self, name: str, version: int | str | None = None) -> list[str]:
        """The Parquet files (local paths, or URLs on an object store) of table ``name`` at
        ``version``: hand them to ``pyarrow.parquet.read_table``, ``duckdb.read_parquet``,
        ``polars.read_parquet`` / ``scan_parquet`` or ``pandas.read_parquet`` to read exactly
        that version without graspcap (fixed-size lists come back as plain lists there)."""
        if name not in DATA_TABLES:
            raise ValueError(f"table {name!r}: one of {DATA_TABLES}")
        v = self.resolve(version)
        key = (name, v)
        if key not in self._files:  # versions are immutable: list each once
            self._files[key] = table_files(self.layout, name, self._pinned(v)[name])
        return list(self._files[key])

    def table(self, name: str, version: int | str | None = None,
              columns: list[str] | None = None) -> pa.Table:
        """Table ``name`` (sessions, frames, builds) as of ``version``."""
        if name not in DATA_TABLES:
            raise ValueError(f"table {name!r}: one of {DATA_TABLES} (versions(): the versions)")
        v = self.resolve(version)
        key = (name, v)
        if columns is None and key in self._tables:
            return self._tables[key]
        try:
            table = read_files(name, self.files(name, v), columns, self.layout)
        except MissingFiles as exc:
            raise MissingFiles(name, exc.files, self._missing_cause(name, v)) from None
        recorded = self._counts.get(v, {}).get(name)
        if recorded is not None and table.num_rows != recorded:  # never read wrong
            damage = log_problems(self.layout, name) if self.layout.is_local else []
            raise CatalogDamaged(self.layout.uri, [
                f"{self.layout.table_uri(name)}: table {name!r} at version {v} has "
                f"{table.num_rows} rows, but version {v} was committed with {recorded}: a Delta "
                "log entry or a data file of it was altered", *damage], REPAIR_LOG)
        if columns is None and name != "frames":
            self._tables[key] = table
        return table

    def _missing_cause(self, name: str, version: int) -> str:
        """Why files of ``name`` at ``version`` are gone: vacuumed, or deleted by hand."""
        dropped = vacuumed_versions(self.layout)
        if version in dropped:
            return (f"version {version} was dropped by `catalog vacuum` at {dropped[version]} "
                    "(read a kept version, see Catalog.versions())")
        return (f"version {version} was never vacuumed, so the files were deleted outside "
                "graspcap: put them back from a backup (`graspcap catalog verify` lists what "
                "every version lacks)")

    def to_pandas(self, name: str, version: int | str | None = None) -> pd.DataFrame:
        """``table(name, version)`` as a DataFrame (list columns become numpy arrays)."""
        return self.table(name, version).to_pandas()

    def diff(self, a: int | str, b: int | str) -> dict:
        """Sessions added, removed and changed (with the changed columns) from ``a`` to ``b``."""
        return diff_sessions(self.table("sessions", a), self.table("sessions", b)).as_dict()

    # arrays -----------------------------------------------------------------------------
    def _sessions_index(self, v: int) -> dict[str, dict]:
        if v not in self._index:
            cols = ["session_id", "object_id", "status", "contact_digest", "hand_mesh_digest",
                    "object_mesh_digest"]
            rows = self.table("sessions", v).select(cols).to_pylist()
            self._index[v] = {r["session_id"]: r for r in rows}
        return self._index[v]

    def _session_row(self, session_id: str, version: int | str | None) -> dict:
        v = self.resolve(version)
        row = self._sessions_index(v).get(session_id)
        if row is None:
            raise KeyError(f"session {session_id!r} is not in catalog version {v}")
        return row

    def _digest(self, session_id: str, version, column: str) -> str:
        row = self._session_row(session_id, version)
        if row[column] is None:
            raise CatalogError(f"session {session_id!r} has no arrays (status "
                               f"{row['status']!r})")
        return row[column]

    def contactmap(self, session_id: str, version: int | str | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """values : (n,) float32 in [0, 1] per object vertex; observed : (n,) bool."""
        g = read_group(self.layout, self._digest(session_id, version, "contact_digest"),
                       ("values", "observed"))
        return g["values"], g["observed"]

    def hand_mesh(self, session_id: str, version: int | str | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """vertices : (n, 3) float32 (object frame, m); faces : (m, 3) int32."""
        g = read_group(self.layout, self._digest(session_id, version, "hand_mesh_digest"),
                       ("vertices", "faces"))
        return g["vertices"], g["faces"]

    def hand_joints(self, session_id: str, version: int | str | None = None) -> np.ndarray:
        """(21, 3) float64: the refined hand's joints in the object frame (m)."""
        digest = self._digest(session_id, version, "hand_mesh_digest")
        return read_group(self.layout, digest, ("joints",))["joints"]

    def object_meshes(self, object_id: str, version: int | str | None = None
                      ) -> dict[str, list[str]]:
        """``{mesh digest: [session ids]}``: the object meshes the sessions of ``object_id``
        carry in ``version`` (one entry unless sessions of the object brought different
        meshes; the contract gives every session its own)."""
        v = self.resolve(version)
        out: dict[str, list[str]] = {}
        for sid, row in sorted(self._sessions_index(v).items()):
            if row["object_id"] == object_id and row["object_mesh_digest"]:
                out.setdefault(row["object_mesh_digest"], []).append(sid)
        return out

    def object_mesh(self, object_id: str | None = None, version: int | str | None = None, *,
                    session_id: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """vertices : (n, 3) float32 (object frame, m); faces : (m, 3) int32.

        ``session_id=``: that session's own mesh (the one its contact map indexes). An
        ``object_id`` alone: its mesh when every session of the object in ``version`` has the
        same one; where they differ this fails naming the sessions of each mesh (pass
        ``session_id``; ``object_meshes(object_id)`` lists them).
        """
        v = self.resolve(version)
        if session_id is not None:
            row = self._session_row(session_id, v)
            if object_id is not None and row["object_id"] != object_id:
                raise KeyError(f"session {session_id!r} is of object {row['object_id']!r}, "
                               f"not {object_id!r}")
            digest = self._digest(session_id, v, "object_mesh_digest")
        elif object_id is None:
            raise TypeError("object_mesh() needs an object_id or session_id=")
        else:
            meshes = self.object_meshes(object_id, v)
            if not meshes:
                raise KeyError(f"object {object_id!r} has no mesh in catalog version {v}")
            if len(meshes) > 1:
                which = "; ".join(f"mesh {d[:12]}: {', '.join(s)}" for d, s in meshes.items())
                raise CatalogError(
                    f"object {object_id!r} has {len(meshes)} different meshes in catalog "
                    f"version {v} ({which}); ask for one session's mesh with "
                    f"object_mesh(session_id=...)")
            digest = next(iter(meshes))
        g = read_group(self.layout, digest, ("vertices", "faces"))
        return g["vertices"], g["faces"]

    def session(self, session_id: str, version: int | str | None = None, *,
                session_root: str | Path | None = None):
        """A ContactPose-style view of one session (``object_pose(frame)``, ``hand_joints``,
        ``K``, ``P``, ``projected_hand_joints``, ``image_filenames``, ``frames``):
        :class:`graspcap.catalog.session_view.SessionView`. Images and intrinsics are read from
        the session folder the build recorded, which must still exist (or, moved, be under
        ``session_root`` by its folder name)."""
        from graspcap.catalog.session_view import SessionView

        return SessionView(self, session_id, version, session_root)

    # writing ----------------------------------------------------------------------------
    def commit(self, build: BuildCommit, gates: AuditGates | None = None) -> int:
        """Commit ``build`` as the next version, atomically; return its number. ``gates``:
        audit it and publish it only when it passes (``catalog.audit``); without, it is
        published at once unless it is written on top of a version that is not (see
        ``commit.commit_build``)."""
        return commit_build(self.layout, build, lock_timeout_s=self.lock_timeout_s,
                            gates=gates)

    def remove(self, session_ids: Sequence[str], reason: str = "", *,
               build_id: str | None = None) -> int:
        """Commit a new version without ``session_ids`` (their sessions and frames rows);
        return its number. The builds row records the removal and ``reason`` (its
        ``parameters_json``: ``{"command": "catalog remove", "reason": ..., "removed": [...]}``)
        and lists the sessions in ``sessions_removed``; older versions keep them. Raises
        ``ValueError`` naming ids the latest version does not hold."""
        ids = sorted(set(session_ids))
        if not ids:
            raise ValueError("name at least one session to remove")
        latest = self.base_version()
        if latest is None:
            raise ValueError(f"catalog {self.layout.uri} has no version to remove from")
        known = set(self.table("sessions", latest)["session_id"].to_pylist())
        unknown = [s for s in ids if s not in known]
        if unknown:
            raise ValueError(f"session(s) {unknown} not in catalog version {latest} (its "
                             f"sessions: {sorted(known)})")
        builds = self.table("builds", latest).sort_by("catalog_version")
        config = builds["config_digest"][-1].as_py() if builds.num_rows else ""
        from graspcap import __version__

        build_id = build_id or ("rm-" + datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
                                + "-" + uuid.uuid4().hex[:4])
        info = BuildInfo(build_id, __version__, config, parameters={
            "command": "catalog remove", "reason": reason, "removed": ids,
            "previous_version": latest})
        return self.commit(BuildCommit(build=info, sessions=[], frames=[], remove=tuple(ids)))

    def vacuum(self, keep: int) -> VacuumReport:
        """Delete files and arrays that neither the last ``keep`` versions nor a tag need."""
        return vacuum_catalog(self, keep)
