"""Crash recovery: roll back table commits that no ``versions`` row covers.

A build (``commit.commit_build``), a compaction (``optimize``), a migration or a vacuum makes
one Delta commit per data table, then appends the ``versions`` row that publishes them. A writer
killed in between leaves table commits no version pins; the next writer, under the writer lock,
calls ``recover``: ``check_versions`` first rules out evidence that a version after the last
row *was* published (then nothing is rolled back and ``CatalogDamaged`` names what is missing),
and each table newer than the last row's pin is restored to it with ``DeltaTable.restore`` in a
commit marked ``graspcap.rolled_back_from``. Every table commit carries the catalog version it
was made for (commit metadata ``VERSION_KEY``), and ``published.json`` records the newest
published version after each versions row: the evidence that tells a killed writer's orphans
from a published version whose row was lost.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from deltalake import CommitProperties, DeltaTable
from deltalake.exceptions import DeltaError

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
from graspcap.catalog.errors import CatalogDamaged, CatalogError, writing
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import DATA_TABLES, TABLE_SCHEMAS

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
