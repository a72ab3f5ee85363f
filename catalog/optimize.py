"""Compaction: rewrite the newest version's many small Parquet files into few, as a new version.

Every build adds files to ``sessions``, ``frames`` and ``builds`` (one overwrite or append per
table per build), so after many incremental builds a table is read from hundreds of small
files. ``optimize_catalog`` (``graspcap catalog optimize``, and a build every
``OPTIMIZE_EVERY`` versions) runs deltalake's ``DeltaTable.optimize.compact()`` on each data
table (``frames`` to the builds' target file size, ``TARGET_BYTES``: only files under it merge,
so a one-session build still rewrites one ~9 MB file afterwards), writes a Delta checkpoint of
every table (``create_checkpoint``: a reader replays the log from it instead of from the first
entry), compacts the bookkeeping tables (``versions``, ``tags``, ``publications``: one small
file per row, read whole by every reader that resolves a version) and appends one catalog
version (build id ``optimize-<time>``, the same rows and state as the version it compacts)
pinning the compacted Delta versions. Nothing older changes: compaction only adds files and a
Delta version (the replaced files are marked removed in the new Delta version, never deleted),
every older catalog version and tag still pins its old Delta versions and reads its old files,
and the tables keep ``delta.enableExpiredLogCleanup=false``, so the checkpoint deletes no log
entry.
Only ``catalog vacuum`` deletes files, and it keeps every file a kept version pins.
Runs under the writer lock, with the commit protocol's recovery: a compaction killed before its
versions row is rolled back by the next writer like any orphan.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import UTC, datetime

from deltalake import WriterProperties, write_deltalake

from graspcap.catalog.commit import FRAMES_FILE_BYTES, FRAMES_WRITER, writer_lock
from graspcap.catalog.delta import delta_table, table_versions_of
from graspcap.catalog.errors import CatalogError
from graspcap.catalog.recovery import (
    _marked,
    _table_write,
    last_version_row,
    recover,
    write_published,
)
from graspcap.catalog.states import base_of, version_states
from graspcap.catalog.store import Catalog
from graspcap.catalog.validate import to_table
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION, DATA_TABLES, TABLE_SCHEMAS

WRITER = WriterProperties(compression="SNAPPY")
"""The codec ``write_deltalake`` gives the build's files (optimize's default is ZSTD: in one
noisy check its ``frames`` of 20 sessions read in 7.8 ms warm against 4.4 ms;
docs/benchmarks.md)."""
TARGET_BYTES = {"frames": FRAMES_FILE_BYTES}
"""Compaction's target file size per table (others: deltalake's default, 100 MiB). ``frames``
keeps the builds' bound: ``compact`` merges only files under the target, in bins up to it, so
the large session-sorted files stay as they are, the small ones of incremental builds merge,
every session's rows stay in one or two files, and a later one-session build still rewrites
one file of at most ~1.4x the target (docs/catalog.md, "The frames layout")."""
MIN_FILES = 2
"""A table of fewer files than this is not compacted."""
BOOKKEEPING = ("versions", "tags", "publications")
"""Append-only tables no version pins, with one file per row: compacted with the data tables
(every reader reads them whole at their newest Delta version; a lost log entry's rows are
still in the old files, which ``catalog repair`` reads)."""


@dataclass(frozen=True)
class OptimizeReport:
    """What a compaction did."""

    version: int | None
    """The catalog version it appended (None: nothing to compact)."""
    compacted_version: int | None
    """The version whose tables it compacted (the newest; None for an empty catalog)."""
    files_before: int
    files_after: int
    by_table: dict[str, list[int]] = field(default_factory=dict)
    """``{table: [files before, files after]}`` of the data tables."""
    checkpoints: dict[str, int] = field(default_factory=dict)
    """``{table: Delta version}`` of the checkpoints written."""

    def text(self) -> str:
        if self.version is None:
            why = ("the catalog has no version" if self.compacted_version is None else
                   f"version {self.compacted_version}'s tables are already compact")
            return f"nothing compacted: {why}" + (
                f"; checkpoints written for {', '.join(self.checkpoints)}"
                if self.checkpoints else "")
        tables = ", ".join(f"{n} {a} -> {b}" for n, (a, b) in self.by_table.items())
        return (f"compacted version {self.compacted_version} into version {self.version}: "
                f"{self.files_before} -> {self.files_after} table file(s) ({tables}); the same "
                "rows; older versions and tags read their own files as before")


def optimize_catalog(catalog: Catalog, *, min_files: int = MIN_FILES) -> OptimizeReport:
    """Compact the newest version's data tables into a new version (module docstring)."""
    layout = catalog.layout
    with writer_lock(layout, catalog.lock_timeout_s):
        recover(layout)
        last = last_version_row(layout)
        if last is None:
            return OptimizeReport(None, None, 0, 0)
        states = version_states(layout)
        if base_of(states) != last["version"]:
            raise CatalogError(
                f"version {last['version']} is rejected; the next build starts from version "
                f"{base_of(states)}: compact after that build")
        version = last["version"] + 1
        build_id = "optimize-" + datetime.now(UTC).strftime("%Y%m%dT%H%M%S")
        pins = table_versions_of(last)
        by_table: dict[str, list[int]] = {}
        for name in DATA_TABLES:
            dt = delta_table(layout, name)
            before = len(dt.file_uris())
            after = before
            if before >= min_files:
                with _table_write(layout, name):
                    dt.optimize.compact(target_size=TARGET_BYTES.get(name),
                                        commit_properties=_marked(version, build_id),
                                        writer_properties=FRAMES_WRITER if name == "frames"
                                        else WRITER)
                dt = delta_table(layout, name)
                after = len(dt.file_uris())
            by_table[name] = [before, after]
            pins[name] = dt.version()
        compacted = pins != table_versions_of(last)
        if compacted:
            row = {**last, "version": version, "time_utc": datetime.now(UTC),
                   "build_id": build_id, "format_version": CATALOG_FORMAT_VERSION,
                   "table_versions": json.dumps(pins, sort_keys=True),
                   "state": states[last["version"]].value}
            with _table_write(layout, "versions"):
                write_deltalake(str(layout.table("versions")), to_table("versions", [row]),
                                mode="append", commit_properties=_marked(version, build_id))
            write_published(layout, row)
        for name in BOOKKEEPING if compacted else ():  # one small file per row each
            dt = delta_table(layout, name)
            if len(dt.file_uris()) >= min_files:
                with _table_write(layout, name):
                    dt.optimize.compact(commit_properties=_marked(version, build_id),
                                        writer_properties=WRITER)
        checkpoints = {}
        for name in TABLE_SCHEMAS:
            dt = delta_table(layout, name)
            if dt.version() > 0:
                with _table_write(layout, name):
                    dt.create_checkpoint()
                checkpoints[name] = dt.version()
    catalog._tables.clear()
    return OptimizeReport(version if compacted else None, last["version"],
                          sum(b for b, _ in by_table.values()),
                          sum(a for _, a in by_table.values()), by_table, checkpoints)
