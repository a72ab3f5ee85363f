"""Upgrade a catalog of an older format to the current one (``graspcap catalog migrate``).

What the formats changed (docs/data_changelog.md): format 2 gave every Delta table
``DELTA_TABLE_PROPERTIES`` (expired-log cleanup off, so Delta never deletes the log entries old
catalog versions are pinned to) and added ``sessions.keypoint_backend`` and
``keypoint_frames_detected``; format 3 added four ``qa_*`` columns to ``sessions``; format 4
added ``frames.camera_solved`` (whether reconstruct_hand solved the frame's camera or interpolated
it) and ``sessions.qa_flags`` and ``qa_notes`` (``list<string>``: QA's flag reasons and notes).
Every added column is nullable. One upgrade serves every older format, in one go: it sets the
properties where they differ, adds the columns the current schemas have and the Delta tables
lack, and brings the columns' field metadata (docs, units; format 3 reworded
``qa_contact_agreement``'s) up to date, so later commits validate; rows written before read
them as null (``graspcap.catalog.delta.read_files``). Setting a property or adding a column
is a Delta commit, and a catalog version pins Delta versions, so the migration of a catalog that has
versions appends one more catalog version (``build_id`` ``migrate-<from>-to-<to>``, same rows)
pinning the new Delta versions; every earlier version and tag still reads what it read before.
Format 5 (object meshes per session, content-addressed; array integrity) changed no column
but reworded the docs of ``sessions.object_id`` and ``object_mesh_digest`` (refreshed as above)
and gave every Zarr group a manifest of its files' sha256 with every chunk written
(``graspcap.catalog.arrays``): the upgrade checks each group on disk against its digest and
adds both in place (``add_manifest``); a group that does not match its digest is left as it
is and listed in the report (``graspcap catalog verify`` names the sessions using it).
Format 6 added the per-frame validity columns of ``frames`` (``camera_reason``, ``hand_used``,
``hand_reason``, ``object_supported``, ``object_reason``, ``object_depth_agreement``): added
as above, then the reason columns of the rows the catalog already has are set to
``NOT_RECORDED`` ("not recorded before format 6"; one Delta update of ``frames``, rewriting its
files: the versions pinned before keep reading the old files, where they are null) while the
flags stay null, which ``GraspDataset`` keeps.
Format 7 (write-audit-publish) added the nullable ``builds.audit_passed``, ``audit_reasons``,
``audit_json`` and ``versions.state`` (added as above: null reads as published, not audited) and
the ``publications`` table, which the upgrade creates first (``create_tables`` makes only the
tables that are missing).
An empty catalog's tables are simply created again. ``catalog.json`` is restamped last, under
the writer lock: a migration that dies half way leaves a catalog of the old format that
``migrate`` finishes (each change is idempotent).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import pyarrow as pa
from deltalake import DeltaTable, Field, write_deltalake

from graspcap.catalog.arrays import add_manifest, all_digests, remove_temp_groups
from graspcap.catalog.commit import writer_lock
from graspcap.catalog.delta import create_tables, delta_version
from graspcap.catalog.errors import CatalogError, CatalogFormatError
from graspcap.catalog.layout import (
    MIGRATIONS_FROM,
    CatalogLayout,
    read_format,
    write_format_file,
)
from graspcap.catalog.recovery import last_version_row, recover
from graspcap.catalog.validate import to_table
from graspcap.schemas.tables import (
    CATALOG_FORMAT_VERSION,
    DATA_TABLES,
    DELTA_TABLE_PROPERTIES,
    NOT_RECORDED,
    TABLE_SCHEMAS,
)


@dataclass(frozen=True)
class MigrationReport:
    """What ``migrate_catalog`` did."""

    root: Path
    """The migrated catalog (the copy when ``out`` was given)."""
    from_format: int
    to_format: int
    new_version: int | None
    """The catalog version the migration appended (None: nothing to pin, or already current)."""
    arrays_upgraded: int = 0
    """Array groups given their format-5 manifest."""
    damaged_arrays: dict[str, str] = dataclasses.field(default_factory=dict)
    """``{digest: problem}`` of groups that do not match their digest (left as they are)."""


def add_missing_columns(dt: DeltaTable, schema: pa.Schema) -> list[str]:
    """Add the columns of ``schema`` that Delta table ``dt`` lacks (one Delta commit, none when
    nothing is missing); return their names. Only nullable columns can be added: the table's
    existing rows read them as null."""
    have = {f.name for f in dt.schema().fields}
    missing = [f for f in schema if f.name not in have]
    strict = [f.name for f in missing if not f.nullable]
    if strict:
        raise CatalogFormatError(f"cannot add column(s) {strict} to existing rows: they must "
                                 "not be null (make them nullable, or rebuild the catalog)")
    if missing:
        dt.alter.add_columns([Field.from_arrow(f) for f in missing])
    return [f.name for f in missing]


def refresh_field_metadata(dt: DeltaTable, schema: pa.Schema) -> list[str]:
    """Give the columns of Delta table ``dt`` the field metadata (``doc``, ``unit``, ...) they
    have in ``schema`` (one Delta commit per column that differs); return their names. Delta
    refuses a write whose field metadata disagrees with the table's ("Cannot merge metadata"),
    so a format that rewords a column's doc refreshes it here."""
    have = {f.name: dict(f.metadata or {}) for f in dt.schema().fields}
    changed = []
    for field in schema:
        want = {k.decode(): v.decode() for k, v in (field.metadata or {}).items()}
        if field.name in have and any(have[field.name].get(k) != v for k, v in want.items()):
            dt.alter.set_column_metadata(field.name, want)
            changed.append(field.name)
    return changed


def mark_not_recorded(dt: DeltaTable) -> bool:
    """Set the format-6 reason columns of the ``frames`` rows that have none yet and no
    verdict either (rows written before format 6) to ``NOT_RECORDED``: one Delta update, none
    when no row needs it (a rerun after a crash). Whether it committed."""
    before = dt.version()
    if dt.to_pyarrow_dataset().count_rows() == 0:
        return False
    unset = " AND ".join(f"{c} IS NULL" for c in ("hand_used", "hand_reason",
                                                  "object_supported", "object_reason"))
    if _count(dt, unset):
        dt.update(new_values={"hand_reason": NOT_RECORDED, "object_reason": NOT_RECORDED},
                  predicate=unset)
    # camera_solved (format 4) may be there: its reason only where it is not True
    camera = "camera_reason IS NULL AND (camera_solved IS NULL OR NOT camera_solved)"
    if _count(dt := DeltaTable(dt.table_uri), camera):
        dt.update(new_values={"camera_reason": NOT_RECORDED}, predicate=camera)
    return DeltaTable(dt.table_uri).version() != before


def _count(dt: DeltaTable, predicate: str) -> int:
    """Rows of ``dt`` where the SQL ``predicate`` holds."""
    from deltalake import QueryBuilder

    query = f"SELECT count(*) AS n FROM t WHERE {predicate}"
    return int(QueryBuilder().register("t", dt).execute(query).read_all()["n"][0].as_py())


def _upgrade(layout: CatalogLayout, found: int) -> int | None:
    """Format ``found`` -> current under the writer lock (module docstring); the appended
    version or None."""
    create_tables(layout)  # tables a newer format adds (format 7: publications)
    recover(layout)
    row = last_version_row(layout)
    if row is None:
        for name in TABLE_SCHEMAS:
            shutil.rmtree(layout.table(name))
        create_tables(layout)
        return None
    changed = False
    for name in TABLE_SCHEMAS:
        dt = DeltaTable(str(layout.table(name)))
        config = dt.metadata().configuration
        if any(config.get(k) != v for k, v in DELTA_TABLE_PROPERTIES.items()):
            dt.alter.set_table_properties(dict(DELTA_TABLE_PROPERTIES))
            changed = True
        changed |= bool(add_missing_columns(DeltaTable(str(layout.table(name))),
                                            TABLE_SCHEMAS[name]))
        changed |= bool(refresh_field_metadata(DeltaTable(str(layout.table(name))),
                                               TABLE_SCHEMAS[name]))
    changed |= mark_not_recorded(DeltaTable(str(layout.table("frames"))))
    pinned = {name: delta_version(layout, name) for name in DATA_TABLES}
    if not changed and pinned == json.loads(row["table_versions"]):
        return None
    version = row["version"] + 1
    new_row = {**row, "version": version, "time_utc": datetime.now(UTC),
               "build_id": f"migrate-{found}-to-{CATALOG_FORMAT_VERSION}",
               "format_version": CATALOG_FORMAT_VERSION,
               "table_versions": json.dumps(pinned, sort_keys=True)}
    write_deltalake(str(layout.table("versions")), to_table("versions", [new_row]),
                    mode="append")
    return version


def migrate_catalog(uri: str | Path, out: str | Path | None = None, *,
                    lock_timeout_s: float = 60.0) -> MigrationReport:
    """Upgrade the catalog at ``uri`` in place, or a copy of it at ``out`` (``uri`` untouched).

    Fails with ``CatalogFormatError`` for a format no step leads from, and with
    ``CatalogError`` when ``out`` exists or the catalog is not a local folder.
    """
    layout = CatalogLayout.from_uri(uri)
    layout.require_local("migrate")
    found = read_format(layout)["format_version"]
    if found > CATALOG_FORMAT_VERSION:
        raise CatalogFormatError(
            f"catalog {layout.uri} is format {found}, newer than this graspcap (format "
            f"{CATALOG_FORMAT_VERSION}); upgrade graspcap instead of migrating")
    if found < CATALOG_FORMAT_VERSION and found not in MIGRATIONS_FROM:
        raise CatalogFormatError(
            f"catalog {layout.uri} is format {found}; no migration leads from it (formats "
            f"{list(MIGRATIONS_FROM)} migrate): rebuild it with `graspcap build`")
    if out is not None:
        target = CatalogLayout.from_uri(out)
        target.require_local("migrate --out")
        if target.root.exists():
            raise CatalogError(f"{target.root} exists; --out must name a new folder")
        with writer_lock(layout, lock_timeout_s):  # a consistent copy: no writer meanwhile
            shutil.copytree(layout.root, target.root,
                            ignore=shutil.ignore_patterns(".lock", ".tmp"))
        layout = target
    new_version = None
    upgraded, damaged = 0, {}
    with writer_lock(layout, lock_timeout_s):
        current = read_format(layout)["format_version"]
        if current < CATALOG_FORMAT_VERSION:
            new_version = _upgrade(layout, current)
            remove_temp_groups(layout)
            for digest in sorted(all_digests(layout)):
                had = layout.array_group(digest) / "zarr.json"
                before = had.read_bytes() if had.is_file() else b""
                problem = add_manifest(layout, digest)
                if problem is not None:
                    damaged[digest] = problem
                elif had.is_file() and had.read_bytes() != before:
                    upgraded += 1
            write_format_file(layout, CATALOG_FORMAT_VERSION)
    return MigrationReport(layout.root, found, CATALOG_FORMAT_VERSION, new_version, upgraded,
                           damaged)
