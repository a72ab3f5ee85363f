"""The Delta tables underneath a catalog: create them, and read one at a pinned Delta version.

Reads go through the version's file list (``DeltaTable(uri, version=k).file_uris()``) and
``pyarrow.parquet.read_table``: the same bytes deltalake would read, at the speed of plain
Parquet. Delta stores fixed-size lists as plain lists, so what comes back is cast to the
catalog schema (a metadata-only change) and gets the schema's field metadata back. The files
are read *as* the catalog schema, so the files of one version may differ in columns: a nullable
column added by a migration reads as null from files written before it (schema evolution on
read, here and nowhere else; without the explicit schema pyarrow would take the first file's
columns and silently drop the new one).
Table URIs and ``storage_options`` come from the layout, so the same calls read a local folder
and an object store (deltalake has its own stores for s3, gs and az).
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from urllib.parse import unquote

import pyarrow as pa
import pyarrow.parquet as pq
from deltalake import DeltaTable
from deltalake.exceptions import DeltaError, TableNotFoundError
from pyarrow.fs import FSSpecHandler, PyFileSystem

from graspcap.catalog.errors import CatalogDamaged, CatalogError, writing
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import DATA_TABLES, DELTA_TABLE_PROPERTIES, TABLE_SCHEMAS

LOG_ENTRY = re.compile(r"(\d{20})\.json")
"""A Delta commit file in ``_delta_log``: its number is the Delta version it makes."""
CHECKPOINT = re.compile(r"(\d{20})\.checkpoint(\.\d+\.\d+)?\.parquet")
REPAIR_LOG = (
    "for log entries of the versions table, `graspcap catalog repair --catalog CATALOG` puts "
    "their rows back from the rows' own data files; else put the named files back from a "
    "backup or snapshot of the catalog; graspcap does not "
    "guess what a missing or unreadable log entry held. Versions that do not need them still "
    "read; to go on without them, rebuild into a new catalog (`graspcap build SESSIONS "
    "--catalog NEW`) or export a readable version (`graspcap catalog export VERSION --out DIR`)")


def delta_table(layout: CatalogLayout, name: str, version: int | None = None) -> DeltaTable:
    """The Delta table ``name`` (at ``version``, default the newest).

    A table whose log is gone, has a gap or an unreadable entry fails with ``CatalogDamaged``
    naming the files (never deltalake's raw error and backtrace).
    """
    try:
        return DeltaTable(layout.table_uri(name), version=version,
                          storage_options=layout.storage_options or None)
    except (DeltaError, OSError, ValueError) as exc:
        raise _log_error(layout, name, version, exc) from None
    except BaseException as exc:  # pyo3's PanicException derives from BaseException
        if type(exc).__name__ != "PanicException":
            raise
        raise _log_error(layout, name, version, exc) from None


def _log_error(layout: CatalogLayout, name: str, version: int | None,
               exc: BaseException) -> CatalogError:
    where = f"table {name!r}" + ("" if version is None else f" at Delta version {version}")
    problems = log_problems(layout, name) if layout.is_local else []
    commits = log_entries(layout, name)[0] if layout.is_local else []
    if not problems and commits and version is not None and version > commits[-1]:
        gone = lost_versions(list(range(commits[-1] + 1, version + 1)))
        problems = [f"{entry_path(layout, name, version)}: {where} is needed but the log ends "
                    f"at Delta version {commits[-1]} ({gone})"]
    if isinstance(exc, TableNotFoundError) and not problems:
        problems = [f"{log_dir(layout, name)}: {where} has no Delta log (a table folder or its "
                    "_delta_log was deleted)"]
    if not problems:
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        problems = [f"{layout.table_uri(name)}/_delta_log: {where} cannot be loaded: "
                    f"{first[:300]}"]
    return CatalogDamaged(layout.uri, problems, REPAIR_LOG)


def log_dir(layout: CatalogLayout, name: str) -> Path:
    return layout.table(name) / "_delta_log"


def log_entries(layout: CatalogLayout, name: str) -> tuple[list[int], list[int]]:
    """``(commit numbers, checkpoint numbers)`` present in table ``name``'s local log."""
    commits, checkpoints = [], []
    try:
        names = [e.name for e in os.scandir(log_dir(layout, name))]
    except (FileNotFoundError, NotADirectoryError):
        return [], []
    for entry in names:
        if m := LOG_ENTRY.fullmatch(entry):
            commits.append(int(m.group(1)))
        elif m := CHECKPOINT.fullmatch(entry):
            checkpoints.append(int(m.group(1)))
    return sorted(commits), sorted(checkpoints)


def entry_path(layout: CatalogLayout, name: str, number: int) -> Path:
    return log_dir(layout, name) / f"{number:020d}.json"


def entry_actions(path: Path) -> list[dict]:
    """The actions of one log entry; ``ValueError`` naming what is wrong with it."""
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"not UTF-8 text (byte {exc.start})") from None
    actions = []
    for i, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            action = json.loads(line)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise ValueError(f"line {i} is not JSON ({exc})") from None
        if not isinstance(action, dict) or len(action) != 1:
            raise ValueError(f"line {i} is not a Delta action (one-key JSON object)")
        [(kind, body)] = action.items()
        if not isinstance(body, dict):
            raise ValueError(f"line {i}: action {kind[:40]!r} is not a JSON object")
        if kind in ("add", "remove") and not isinstance(body.get("path"), str):
            raise ValueError(f"line {i}: {kind} action without a file path")
        actions.append(action)
    if not actions:
        raise ValueError("empty")
    return actions


def log_problems(layout: CatalogLayout, name: str, *, parse: bool = True) -> list[str]:
    """What is wrong with table ``name``'s local Delta log, one line per problem naming the
    file: no log, a missing entry (a gap), and (``parse``) an entry that is not Delta JSON."""
    folder = log_dir(layout, name)
    commits, checkpoints = log_entries(layout, name)
    if not commits:
        return [f"{folder}: table {name!r} has no Delta log entries (deleted?)"]
    problems = []
    first = commits[0] if checkpoints and checkpoints[0] <= commits[0] else 0
    present = set(commits)
    missing = [n for n in range(first, commits[-1] + 1) if n not in present]
    if missing:
        shown = ", ".join(entry_path(layout, name, n).name for n in missing[:5])
        more = f" (+{len(missing) - 5} more)" if len(missing) > 5 else ""
        problems.append(f"{folder}: table {name!r} lacks log entr"
                        f"{'y' if len(missing) == 1 else 'ies'} {shown}{more} (its log runs "
                        f"{first}-{commits[-1]} with a gap: {lost_versions(missing)})")
    last_checkpoint = folder / "_last_checkpoint"
    if parse and last_checkpoint.exists():
        try:
            if not isinstance(json.loads(last_checkpoint.read_bytes()), dict):
                raise ValueError("not a JSON object")
        except (ValueError, RecursionError, OSError) as exc:
            problems.append(f"{last_checkpoint}: table {name!r}: unreadable ({exc}); deleting "
                            "it is safe (Delta then reads the log from its entries)")
    for n in commits if parse else ():
        try:
            entry_actions(entry_path(layout, name, n))
        except (ValueError, OSError) as exc:
            problems.append(f"{entry_path(layout, name, n)}: table {name!r}: the log entry "
                            f"for Delta version {n} is unreadable: {exc}")
    return problems


def lost_versions(numbers: list[int]) -> str:
    """'Delta version 3 is lost', 'Delta versions 2-4, 7 are lost'."""
    many = len(numbers) > 1
    return f"Delta version{'s' if many else ''} {_ranges(numbers)} {'are' if many else 'is'} lost"


def _ranges(numbers: list[int]) -> str:
    out, start = [], numbers[0]
    for a, b in zip(numbers, [*numbers[1:], None], strict=True):
        if b != a + 1:
            out.append(str(start) if start == a else f"{start}-{a}")
            start = b
    return ", ".join(out)


def intact_files(layout: CatalogLayout, name: str) -> list[str]:
    """The data files the readable log entries of an append-only table add and do not remove:
    what a reader can still trust of a table (``versions``, ``tags``) whose log is damaged."""
    added: dict[str, None] = {}
    removed: set[str] = set()
    for n in log_entries(layout, name)[0]:
        try:
            actions = entry_actions(entry_path(layout, name, n))
        except (ValueError, OSError):
            continue
        for action in actions:
            if "add" in action:
                added[unquote(action["add"]["path"])] = None
            elif "remove" in action:
                removed.add(unquote(action["remove"]["path"]))
    return [str(layout.table(name) / p) for p in added if p not in removed]


def create_tables(layout: CatalogLayout,
                  properties: dict[str, str] | None = DELTA_TABLE_PROPERTIES) -> None:
    """Create every table that does not exist yet (each at Delta version 0, empty); call it
    under the writer lock (``store.open`` does), else two creators race on one table.

    ``properties`` are the Delta table properties of the current format; only the golden
    catalog of an older format passes others (``tests/golden/make_golden.py``).
    """
    layout.require_local("creating a catalog")
    for name, schema in TABLE_SCHEMAS.items():
        uri = layout.table_uri(name)
        if not DeltaTable.is_deltatable(uri):
            with writing(layout.table(name)):
                layout.table(name).mkdir(parents=True, exist_ok=True)
                DeltaTable.create(uri, schema, name=name, configuration=properties or None)


def delta_version(layout: CatalogLayout, name: str) -> int:
    """The newest Delta version of table ``name``."""
    return delta_table(layout, name).version()


def table_files(layout: CatalogLayout, name: str, delta_version: int) -> list[str]:
    """The Parquet files (local paths or object-store URLs) of ``name`` at ``delta_version``."""
    return delta_table(layout, name, delta_version).file_uris()


def read_files(name: str, files: list[str], columns: list[str] | None = None,
               layout: CatalogLayout | None = None) -> pa.Table:
    """Read Parquet ``files`` of table ``name`` as its catalog schema.

    Columns a file lacks (written before a migration added them) read as nulls; a missing
    column that must not be null fails with ``CatalogError``. ``layout`` is needed only for an
    object store (its fsspec filesystem reads the files).
    """
    full = schema = TABLE_SCHEMAS[name]
    if columns is not None:
        schema = pa.schema([schema.field(c) for c in columns], metadata=schema.metadata)
    if not files:
        return schema.empty_table()
    filesystem = None
    if layout is not None and not layout.is_local:
        filesystem = PyFileSystem(FSSpecHandler(layout.fs))
        files = [layout.fs._strip_protocol(f) for f in files]
    try:
        table = pq.read_table(files, schema=full, columns=columns, filesystem=filesystem)
    except FileNotFoundError as exc:
        gone = [f for f in files if layout is None or layout.is_local
                if not Path(f).is_file()] or [exc.filename or str(exc)]
        raise MissingFiles(name, gone) from None
    except (OSError, pa.ArrowException) as exc:
        bad = []
        for f in files:  # which file: pyarrow's message often names none
            try:
                pq.read_metadata(f, filesystem=filesystem)
            except (OSError, pa.ArrowException) as file_exc:
                bad.append(f"{f} ({_first(file_exc)})")
        what = (f"file{'s' if len(bad) > 1 else ''} {', '.join(bad[:3])} of this version "
                f"{'are' if len(bad) > 1 else 'is'} not readable Parquet" if bad else
                f"the files of this version cannot be read: {_first(exc)}")
        raise CatalogError(f"table {name!r}: {what}; put {'them' if len(bad) > 1 else 'it'} "
                           "back from a backup") from None
    table = table.select(schema.names).cast(schema)
    for field in schema:  # validated on write, so a null here is a column the files lack
        if not field.nullable and table[field.name].null_count:
            raise CatalogError(
                f"table {name!r}: files of this version lack column {field.name!r}, which "
                "must not be null; only nullable columns can be added to existing rows")
    return table


def _first(exc: BaseException) -> str:
    return ((str(exc).strip().splitlines() or [type(exc).__name__])[0])[:300]


def read_table(layout: CatalogLayout, name: str, delta_version: int,
               columns: list[str] | None = None) -> pa.Table:
    """Table ``name`` as it was at ``delta_version``."""
    return read_files(name, table_files(layout, name, delta_version), columns, layout)


def read_latest(layout: CatalogLayout, name: str) -> pa.Table:
    """The bookkeeping tables (versions, tags) at their newest Delta version.

    When their log is damaged (a gap, an unreadable entry), the rows of the readable entries:
    both tables are append-only, so every row read is one that was committed, and readers of
    the versions whose rows survive keep working (writers stop: ``recovery.recover``).
    """
    try:  # one log load: the newest version's file list (not its number, then that version's)
        return read_files(name, delta_table(layout, name).file_uris(), None, layout)
    except CatalogDamaged:
        if not layout.is_local or name not in ("versions", "tags") \
                or not log_entries(layout, name)[0]:  # no log at all: nothing to trust
            raise
        return read_files(name, intact_files(layout, name), None, layout)


def table_versions_of(row: dict) -> dict[str, int]:
    """``{table: Delta version}`` of a ``versions`` row."""
    pinned = json.loads(row["table_versions"])
    return {name: int(pinned[name]) for name in DATA_TABLES}


class MissingFiles(CatalogError):
    """Parquet files a table version lists are gone; ``files`` names them."""

    def __init__(self, table: str, files: list[str], cause: str = ""):
        self.table = table
        self.files = list(files)
        shown = ", ".join(self.files[:3]) + (f" (+{len(files) - 3} more)"
                                             if len(files) > 3 else "")
        super().__init__(f"table {table!r}: file{'s' if len(files) > 1 else ''} {shown} "
                         f"of this version {'are' if len(files) > 1 else 'is'} missing"
                         + (f"; {cause}" if cause else ""))


INITIAL_TABLE_VERSIONS = dict.fromkeys(DATA_TABLES, 0)
"""Delta versions of the empty data tables right after ``create_tables``."""
