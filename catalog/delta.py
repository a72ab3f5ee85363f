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

import pyarrow as pa
import pyarrow.parquet as pq
from deltalake import DeltaTable
from pyarrow.fs import FSSpecHandler, PyFileSystem

from graspcap.catalog.errors import CatalogError
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import DATA_TABLES, DELTA_TABLE_PROPERTIES, TABLE_SCHEMAS


def delta_table(layout: CatalogLayout, name: str, version: int | None = None) -> DeltaTable:
    """The Delta table ``name`` (at ``version``, default the newest)."""
    return DeltaTable(layout.table_uri(name), version=version,
                      storage_options=layout.storage_options or None)


def create_tables(layout: CatalogLayout,
                  properties: dict[str, str] | None = DELTA_TABLE_PROPERTIES) -> None:
    """Create every table that does not exist yet (each at Delta version 0, empty).

    ``properties`` are the Delta table properties of the current format; only the golden
    catalog of an older format passes others (``tests/golden/make_golden.py``).
    """
    layout.require_local("creating a catalog")
    for name, schema in TABLE_SCHEMAS.items():
        uri = layout.table_uri(name)
        if not DeltaTable.is_deltatable(uri):
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
        raise CatalogError(
            f"table {name!r}: a file of this version is gone ({exc.filename}); the version "
            "was removed by vacuum (read a kept version, see Catalog.versions())") from exc
    table = table.select(schema.names).cast(schema)
    for field in schema:  # validated on write, so a null here is a column the files lack
        if not field.nullable and table[field.name].null_count:
            raise CatalogError(
                f"table {name!r}: files of this version lack column {field.name!r}, which "
                "must not be null; only nullable columns can be added to existing rows")
    return table


def read_table(layout: CatalogLayout, name: str, delta_version: int,
               columns: list[str] | None = None) -> pa.Table:
    """Table ``name`` as it was at ``delta_version``."""
    return read_files(name, table_files(layout, name, delta_version), columns, layout)


def read_latest(layout: CatalogLayout, name: str) -> pa.Table:
    """The bookkeeping tables (versions, tags) at their newest Delta version."""
    return read_table(layout, name, delta_version(layout, name))


def table_versions_of(row: dict) -> dict[str, int]:
    """``{table: Delta version}`` of a ``versions`` row."""
    pinned = json.loads(row["table_versions"])
    return {name: int(pinned[name]) for name in DATA_TABLES}


INITIAL_TABLE_VERSIONS = dict.fromkeys(DATA_TABLES, 0)
"""Delta versions of the empty data tables right after ``create_tables``."""
