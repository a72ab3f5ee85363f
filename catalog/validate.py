"""Turn a writer's batch into an Arrow table of the catalog's schema, or say exactly what is wrong.

A batch is a ``pyarrow.Table``, a mapping of columns (numpy arrays or lists; a pose column may be
``(n, 4, 4)``), or a sequence of row dicts. Every problem raises ``CatalogSchemaError`` naming the
table, the column and the session(s).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from graspcap.catalog.errors import CatalogSchemaError
from graspcap.schemas.tables import TABLE_SCHEMAS, Status, required_unless_failed

Batch = pa.Table | Mapping[str, Any] | Sequence[Mapping[str, Any]]
STATUSES = frozenset(s.value for s in Status)


def _session_ids(columns: Mapping[str, Any], rows: np.ndarray | None = None) -> list[str]:
    ids = columns.get("session_id")
    if ids is None:
        return []
    ids = ids.to_pylist() if isinstance(ids, pa.Array | pa.ChunkedArray) else list(ids)
    if rows is not None:
        ids = [ids[i] for i in np.flatnonzero(rows)]
    return [str(s) for s in ids]


def _fixed_list(field: pa.Field, values: Any, n: int, fail) -> pa.Array:
    k = field.type.list_size
    if isinstance(values, np.ndarray) and values.dtype != object:
        if values.ndim == 0 or values.shape[0] != n or values.size != n * k:
            fail(None, f"expected {k} values per row, got an array of shape {values.shape}")
        flat = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        return pa.FixedSizeListArray.from_arrays(pa.array(flat), k)
    flat = np.zeros((n, k))
    mask = np.zeros(n, dtype=bool)
    for i, v in enumerate(values):
        if v is None:
            mask[i] = True
            continue
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            fail(i, f"not numbers: {exc}")
        if a.size != k:
            fail(i, f"expected {k} values, got shape {a.shape}")
        flat[i] = a.reshape(-1)
    return pa.FixedSizeListArray.from_arrays(
        pa.array(flat.reshape(-1)), k, mask=pa.array(mask) if mask.any() else None)


def _plain(field: pa.Field, values: Any, fail) -> pa.Array:
    values = list(values) if not isinstance(values, np.ndarray) else values
    try:
        return pa.array(values, type=field.type)
    except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError, OverflowError) as exc:
        for i, v in enumerate(values):
            try:
                pa.array([v], type=field.type)
            except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError, OverflowError):
                fail(i, f"{v!r} is not {field.type}")
        fail(None, f"cannot convert to {field.type}: {exc}")


def rows_to_columns(name: str, rows: Sequence[Mapping[str, Any]]) -> dict[str, list]:
    """Row dicts as columns; every row must have the same keys."""
    rows = list(rows)
    if not rows:
        return {k: [] for k in TABLE_SCHEMAS[name].names}
    keys = list(rows[0])
    for r in rows:
        if set(r) != set(keys):
            odd = sorted(set(r) ^ set(keys))[0]
            raise CatalogSchemaError(name, odd, [str(r.get("session_id"))],
                                     "row keys differ from the batch's first row "
                                     f"({'missing' if odd not in r else 'unexpected'} here)")
    return {k: [r[k] for r in rows] for k in keys}


def to_table(name: str, batch: Batch) -> pa.Table:
    """A validated table of ``TABLE_SCHEMAS[name]`` (field metadata attached) from ``batch``."""
    schema = TABLE_SCHEMAS[name]
    if isinstance(batch, pa.Table):
        return validate_table(name, batch)
    columns = dict(batch) if isinstance(batch, Mapping) else rows_to_columns(name, batch)
    _check_names(name, schema, list(columns), columns)
    lengths = {len(v) for v in columns.values()}
    if len(lengths) > 1:
        raise CatalogSchemaError(name, None, _session_ids(columns)[:1],
                                 f"columns differ in length: {sorted(lengths)}")
    n = lengths.pop() if lengths else 0
    arrays = []
    for field in schema:
        def fail(row, reason, _col=field.name):
            ids = _session_ids(columns)
            raise CatalogSchemaError(name, _col, [ids[row]] if row is not None else ids, reason)
        values = columns[field.name]
        if isinstance(values, pa.Array | pa.ChunkedArray):
            arrays.append(values)
        elif pa.types.is_fixed_size_list(field.type):
            arrays.append(_fixed_list(field, values, n, fail))
        elif pa.types.is_list(field.type):  # qa_flags: ["reason", ...], never "reason"
            for i, v in enumerate(values):
                if isinstance(v, str | bytes):
                    fail(i, f"expected a list of {field.type.value_type}, got the string {v!r}")
            arrays.append(_plain(field, values, fail))
        else:
            arrays.append(_plain(field, values, fail))
    return validate_table(name, pa.Table.from_arrays(arrays, names=schema.names))


def _check_names(name: str, schema: pa.Schema, got: list[str], columns: Mapping) -> None:
    missing = [c for c in schema.names if c not in got]
    extra = [c for c in got if c not in schema.names]
    if missing:
        raise CatalogSchemaError(name, missing[0], _session_ids(columns),
                                 f"missing column (missing: {missing})")
    if extra:
        raise CatalogSchemaError(name, extra[0], _session_ids(columns),
                                 f"unexpected column; the table's columns are {schema.names}")


def validate_table(name: str, table: pa.Table) -> pa.Table:
    """Check ``table`` against ``TABLE_SCHEMAS[name]``; return it cast to the schema."""
    schema = TABLE_SCHEMAS[name]
    columns = {c: table[c] for c in table.column_names}
    _check_names(name, schema, table.column_names, columns)
    for field in schema:
        got = table.schema.field(field.name).type
        if got != field.type:
            raise CatalogSchemaError(name, field.name, _session_ids(columns),
                                     f"expected type {field.type}, got {got}")
        if not field.nullable and table[field.name].null_count:
            nulls = table[field.name].is_null().to_numpy(zero_copy_only=False)
            raise CatalogSchemaError(name, field.name, _session_ids(columns, nulls),
                                     "null in a column that must always be set")
    table = table.select(schema.names).cast(schema)
    if "status" in schema.names:
        _check_status(name, table)
    _check_unique(name, table)
    return table


def _check_status(name: str, table: pa.Table) -> None:
    columns = {"session_id": table["session_id"]}
    status = table["status"].to_numpy(zero_copy_only=False).astype(str)
    bad = ~np.isin(status, sorted(STATUSES))
    if bad.any():
        raise CatalogSchemaError(name, "status", _session_ids(columns, bad),
                                 f"status {status[bad][0]!r} is not one of {sorted(STATUSES)}")
    failed = status == Status.FAILED
    error = table["error"]
    no_error = pc.fill_null(pc.equal(pc.utf8_length(error), 0), True).to_numpy(
        zero_copy_only=False).astype(bool)
    if (failed & no_error).any():
        raise CatalogSchemaError(name, "error", _session_ids(columns, failed & no_error),
                                 "a failed session needs an error a person can act on")
    with_error = ~failed & ~error.is_null().to_numpy(zero_copy_only=False)
    if with_error.any():
        raise CatalogSchemaError(name, "error", _session_ids(columns, with_error),
                                 "error must be null unless status is 'failed'")
    for col in required_unless_failed(table.schema):
        nulls = table[col].is_null().to_numpy(zero_copy_only=False) & ~failed
        if nulls.any():
            raise CatalogSchemaError(name, col, _session_ids(columns, nulls),
                                     "null on a session that did not fail")


def _check_unique(name: str, table: pa.Table) -> None:
    key = (table.schema.metadata or {}).get(b"key", b"").decode().split(",")
    if not key or key == [""] or table.num_rows == 0:
        return
    counts = table.group_by(key).aggregate([([], "count_all")])
    dup = counts.filter(pc.greater(counts["count_all"], 1))
    if dup.num_rows:
        first = {k: dup[k][0].as_py() for k in key}
        sessions = [str(first["session_id"])] if "session_id" in first else []
        raise CatalogSchemaError(name, ",".join(key), sessions, f"duplicate key {first}")


def check_commit(commit: Any) -> tuple[pa.Table, pa.Table]:
    """Every check ``Catalog.commit`` runs on a ``BuildCommit`` (rows, frames, arrays and
    meshes), without writing anything; raises the same ``CatalogSchemaError``. The build runs
    it per session before its commit, so a session that would make the commit raise fails on
    its own (``flows/build.py``). Returns the checked sessions table (its digest columns
    filled) and frames table."""
    from graspcap.catalog.commit import _prepare  # commit imports this module

    sessions, frames, _ = _prepare(commit)
    return sessions, frames
