"""Free space: delete Parquet files and array groups that no kept catalog version needs.

Kept versions are the newest ``keep`` ones plus every tagged one and the published one
(readers' default, which may be older than the newest when those are staged). A file survives
when any kept version's pinned Delta version lists it, or the newest Delta version of its table
does (so the tables stay writable); an array group survives when a kept version's sessions
reference it.
Everything else under the tables' folders (files of older versions, of crashed or rolled-back
commits) and under ``arrays/`` (groups of dropped versions, half-written temp groups) goes.
Runs under the writer lock. Delta logs are kept: the versions stay listed. A version not kept
whose files all survive (each is also a kept version's) still reads; one that lost a file is
recorded in ``vacuum.jsonl`` as dropped: ``catalog versions`` marks it, and reading it fails
with a message saying it was vacuumed.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from graspcap.catalog.arrays import all_digests, remove_temp_groups
from graspcap.catalog.commit import writer_lock
from graspcap.catalog.delta import delta_version, table_files
from graspcap.catalog.errors import writing
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.recovery import recover
from graspcap.schemas.tables import DATA_TABLES, TABLE_SCHEMAS, ZARR_LAYOUT

if TYPE_CHECKING:
    from graspcap.catalog.store import Catalog


@dataclass(frozen=True)
class VacuumReport:
    """What vacuum kept and removed."""

    kept_versions: list[int]
    dropped_versions: list[int]
    """Versions that are still listed but can no longer be read (a file or array group they
    need was removed)."""
    removed_files: int
    removed_arrays: int
    freed_bytes: int
    readable_versions: list[int] = field(default_factory=list)
    """Versions not kept that still read: every file and array group they need is also a kept
    version's (or the tables' newest state's), so nothing of theirs was removed."""
    removed_by_table: dict[str, int] = field(default_factory=dict)
    """Parquet files removed, by table (only tables that lost any)."""
    removed_temp_groups: int = 0
    """Half-written array groups of killed writers removed from ``arrays/.tmp``."""

    def text(self, keep: int) -> str:
        """One line for a person: exactly what was kept and removed."""
        def versions(vs: list[int]) -> str:
            return ", ".join(map(str, vs))

        out = [f"kept version(s) {versions(self.kept_versions)} (the newest {keep}, every "
               "tagged one and the published one)"]
        if self.dropped_versions:
            out.append(f"version(s) {versions(self.dropped_versions)} can no longer be read "
                       "(files they need were removed; they stay listed)")
        if self.readable_versions:
            out.append(f"version(s) {versions(self.readable_versions)} not kept but still "
                       "readable (they share every file with kept ones)")
        tables = ", ".join(f"{n} {k}" for n, k in self.removed_by_table.items())
        removed = (f"removed {self.removed_files} table file(s)"
                   + (f" ({tables})" if tables else "")
                   + f", {self.removed_arrays} array group(s)")
        if self.removed_temp_groups:
            removed += f", {self.removed_temp_groups} unfinished temporary array group(s)"
        out.append(f"{removed}: {self.freed_bytes / 1e6:.2f} MB freed")
        return "; ".join(out)


def _size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def vacuum_catalog(catalog: Catalog, keep: int) -> VacuumReport:
    """See the module docstring; ``keep`` >= 1."""
    if keep < 1:
        raise ValueError("keep must be >= 1: the newest version is always kept")
    layout = catalog.layout
    with writer_lock(layout, catalog.lock_timeout_s):
        recover(layout)
        all_versions = catalog.versions()["version"].to_pylist()
        published = catalog.published_version()  # readers' default is always kept
        kept = sorted(set(all_versions[-keep:]) | set(catalog.tags().values())
                      | ({published} if published is not None else set()))
        needed: set[str] = set()
        for name in DATA_TABLES:
            needed.update(table_files(layout, name, delta_version(layout, name)))
            for v in kept:
                needed.update(table_files(layout, name, catalog._pinned(v)[name]))
        for name in TABLE_SCHEMAS:
            if name not in DATA_TABLES:
                needed.update(table_files(layout, name, delta_version(layout, name)))
        needed = {str(Path(f).resolve()) for f in needed}
        digest_cols = [g.digest_column for g in ZARR_LAYOUT.values()]
        live: set[str] = set()
        for v in kept:
            sessions = catalog.table("sessions", v, columns=digest_cols)
            for col in digest_cols:
                live.update(sessions[col].drop_null().to_pylist())

        removed_files = freed = 0
        by_table: dict[str, int] = {}
        for name in TABLE_SCHEMAS:
            for path in layout.table(name).rglob("*.parquet"):
                if "_delta_log" in path.parts or str(path.resolve()) in needed:
                    continue
                freed += _size(path)
                path.unlink()
                removed_files += 1
                by_table[name] = by_table.get(name, 0) + 1
        removed_arrays = 0
        for digest in all_digests(layout) - live:
            group = layout.array_group(digest)
            freed += _size(group)
            shutil.rmtree(group)
            removed_arrays += 1
        temp_groups = 0
        if layout.arrays_tmp.is_dir():
            before = _size(layout.arrays_tmp)
            temp_groups = len(remove_temp_groups(layout))  # killed writers' (not a live one's)
            freed += before - _size(layout.arrays_tmp)
        not_kept = sorted(set(all_versions) - set(kept))
        dropped = [v for v in not_kept if not _readable(catalog, v)]
        line = json.dumps({"time_utc": datetime.now(UTC).isoformat(timespec="seconds"),
                           "kept": kept, "dropped": dropped}) + "\n"
        with writing(layout.vacuum_log), open(layout.vacuum_log, "a") as fh:
            fh.write(line)
    catalog._tables.clear()
    return VacuumReport(kept, dropped, removed_files, removed_arrays, freed,
                        readable_versions=[v for v in not_kept if v not in dropped],
                        removed_by_table=by_table, removed_temp_groups=temp_groups)


def _readable(catalog: Catalog, version: int) -> bool:
    """Whether every table file and array group ``version`` needs is on disk."""
    layout = catalog.layout
    pins = catalog._pinned(version)
    for name in DATA_TABLES:
        if not all(Path(f).exists() for f in table_files(layout, name, pins[name])):
            return False
    digest_cols = [g.digest_column for g in ZARR_LAYOUT.values()]
    sessions = catalog.table("sessions", version, columns=digest_cols)
    return all(layout.array_group(d).is_dir() for col in digest_cols
               for d in sessions[col].drop_null().to_pylist())


def vacuumed_versions(layout: CatalogLayout) -> dict[int, str]:
    """``{version: time (UTC) of the vacuum that dropped it}`` from ``vacuum.jsonl``."""
    out: dict[int, str] = {}
    try:
        lines = layout.vacuum_log.read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return out
    for line in lines:
        try:
            record = json.loads(line)
            for v in record["dropped"]:
                out.setdefault(int(v), str(record["time_utc"]))
        except (ValueError, KeyError, TypeError, RecursionError):
            continue  # a torn last line of a vacuum that was killed
    return out
