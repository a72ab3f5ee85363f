"""Put back ``versions`` rows whose Delta log entries were lost, from their own data files.

A ``versions`` row is one small Parquet file that the log entry of its append lists. When that
entry is deleted or garbled, the row's file is still there, unlisted: writers stop on it
(``recovery.check_versions``) and the version is invisible. ``repair_versions`` (under the writer
lock) moves a garbled entry aside (``<entry>.damaged``), fills every hole in the log with an
entry that changes nothing (a ``commitInfo`` only), and appends the unlisted rows whose version
numbers the table lacks, as one new commit. A row so restored pins table versions that were
committed before it (a row is only written after its tables' commits), so its version reads as
it did. Each row is checked against its tables' row counts first; one that does not match is
left out and named.

    graspcap catalog repair --catalog CATALOG    (or: python -m graspcap.catalog.repair CATALOG)
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from deltalake import write_deltalake

from graspcap.catalog.commit import writer_lock
from graspcap.catalog.delta import (
    delta_table,
    entry_actions,
    entry_path,
    intact_files,
    log_entries,
    read_files,
    table_versions_of,
)
from graspcap.catalog.errors import CatalogError, writing
from graspcap.catalog.layout import CatalogLayout, check_format
from graspcap.catalog.validate import to_table
from graspcap.schemas.tables import DATA_TABLES


@dataclass(frozen=True)
class RepairReport:
    """What ``repair_versions`` did."""

    moved_aside: list[Path]
    """Garbled log entries renamed to ``<entry>.damaged``."""
    filled: list[Path]
    """Log entries written to fill holes (they change nothing)."""
    restored: list[int]
    """Catalog versions whose rows were put back."""
    left_out: list[str]
    """Unlisted rows not put back, with the reason."""


def repair_versions(uri: str | Path, *, lock_timeout_s: float = 60.0) -> RepairReport:
    """See the module docstring."""
    layout = CatalogLayout.from_uri(uri)
    layout.require_local("repairing a catalog")
    check_format(layout)
    with writer_lock(layout, lock_timeout_s):
        moved, filled = _mend_log(layout)
        rows = read_files("versions", intact_files(layout, "versions"), None, layout)
        have = set(rows["version"].to_pylist())
        listed = {str(Path(f).resolve()) for f in intact_files(layout, "versions")}
        restored, left_out, candidates = [], [], []
        for path in sorted(layout.table("versions").glob("*.parquet")):
            if str(path.resolve()) in listed:
                continue
            try:
                stray = read_files("versions", [str(path)], None, layout).to_pylist()
            except CatalogError as exc:
                left_out.append(f"{path}: {exc}")
                continue
            candidates += [r for r in stray if r["version"] not in have]
        for row in sorted(candidates, key=lambda r: r["version"]):
            if row["version"] in have:
                continue
            reason = _mismatch(layout, row)
            if reason:
                left_out.append(f"version {row['version']}: {reason}")
                continue
            have.add(row["version"])
            restored.append(row)
        if restored:
            with writing(layout.table("versions")):
                write_deltalake(str(layout.table("versions")), to_table("versions", restored),
                                mode="append")
    return RepairReport(moved, filled, [r["version"] for r in restored], left_out)


def _mend_log(layout: CatalogLayout) -> tuple[list[Path], list[Path]]:
    """Move garbled ``versions`` log entries aside and fill the holes with empty commits."""
    commits, _ = log_entries(layout, "versions")
    moved = []
    for n in commits:
        path = entry_path(layout, "versions", n)
        try:
            entry_actions(path)
        except (ValueError, OSError):
            os.replace(path, path.with_name(path.name + ".damaged"))
            moved.append(path)
    present = set(log_entries(layout, "versions")[0])
    filled = []
    for n in range(max(commits, default=-1) + 1):
        if n in present:
            continue
        if n == 0:
            raise CatalogError(f"{entry_path(layout, 'versions', 0)}: the versions table's "
                               "first entry (its schema) is lost; put it back from a backup")
        info = {"commitInfo": {"timestamp": int(time.time() * 1000), "operation": "WRITE",
                               "operationParameters": {"mode": "Append"},
                               "graspcap.repair": "in place of a lost entry"}}
        path = entry_path(layout, "versions", n)
        with writing(path), open(path, "x") as fh:  # never over an entry that reappeared
            fh.write(json.dumps(info) + "\n")
        filled.append(path)
    return moved, filled


def _mismatch(layout: CatalogLayout, row: dict) -> str | None:
    """Why ``row`` cannot be put back (its pins are not its tables' state), or None."""
    try:
        pins = table_versions_of(row)
        for name in DATA_TABLES:
            count = delta_table(layout, name, pins[name]).count()
            if count != row[f"rows_{name}"]:
                return (f"table {name!r} at Delta version {pins[name]} has {count} rows, the "
                        f"row says {row[f'rows_{name}']}")
    except (CatalogError, ValueError, KeyError) as exc:
        return str(exc).splitlines()[0]
    return None


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m graspcap.catalog.repair CATALOG", file=sys.stderr)
        return 2
    try:
        report = repair_versions(args[0])
    except (CatalogError, OSError) as exc:
        for line in str(exc).splitlines():
            print(f"repair: {line}", file=sys.stderr)
        return 2
    for path in report.moved_aside:
        print(f"moved aside {path} (garbled) as {path.name}.damaged")
    for path in report.filled:
        print(f"filled {path} (an entry that changes nothing)")
    print(f"restored version(s) {report.restored or 'none'}")
    for line in report.left_out:
        print(f"left out {line}", file=sys.stderr)
    return 2 if report.left_out else 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())


__all__ = ["RepairReport", "main", "repair_versions"]
