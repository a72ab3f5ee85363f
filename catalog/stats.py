"""Normalisation statistics of an export: count, mean, std, min, max, p01, p99 per quantity.

Quantities are taken from a table's numeric columns, chosen by the field's ``shape`` metadata
(``schemas/tables.py``):

- a scalar column (int, float, bool as 0/1): one value per row;
- a pose (``4x4 row-major``): its translation part, per coordinate (``x``, ``y``, ``z``);
- ``21x3`` joints / ``21x2`` keypoints: per coordinate, pooled over the 21 joints;
- any other fixed vector (``20`` joint angles, ``21`` confidences): per element.

Nulls and NaN are left out (``count`` says how many values each statistic covers). Statistics
are computed one column at a time, streaming over the column's chunks of the table the export
already holds in memory (mean and variance merged chunk by chunk, Chan et al.); only the
percentiles need the column's values at once, so at most one column is copied beside the
table. ``std`` is the population standard deviation (numpy's ``ddof=0``); percentiles are
numpy's linear ones.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

POSE_SHAPE = "4x4 row-major"
_TRANSLATION = [3, 7, 11]
_XYZ = ["x", "y", "z"]
_UV = ["u", "v"]


@dataclass
class Accumulator:
    """Per-dimension running count, mean, M2, min, max; values kept for the percentiles."""

    dims: int
    count: np.ndarray = field(init=False)
    mean: np.ndarray = field(init=False)
    m2: np.ndarray = field(init=False)
    lo: np.ndarray = field(init=False)
    hi: np.ndarray = field(init=False)
    parts: list[np.ndarray] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.count = np.zeros(self.dims, np.int64)
        self.mean = np.zeros(self.dims)
        self.m2 = np.zeros(self.dims)
        self.lo = np.full(self.dims, np.inf)
        self.hi = np.full(self.dims, -np.inf)

    def update(self, values: np.ndarray) -> None:
        """Merge a chunk of shape (n, dims) (NaN = missing)."""
        values = np.asarray(values, np.float64).reshape(-1, self.dims)
        if values.shape[0] == 0:
            return
        self.parts.append(values)
        valid = ~np.isnan(values)
        n = valid.sum(axis=0)
        has = n > 0
        safe = np.where(valid, values, 0.0)
        mean = np.divide(safe.sum(axis=0), n, out=np.zeros(self.dims), where=has)
        m2 = np.where(valid, (values - mean) ** 2, 0.0).sum(axis=0)
        total = self.count + n
        delta = mean - self.mean
        frac = np.divide(n, total, out=np.zeros(self.dims), where=total > 0)
        self.mean = self.mean + delta * frac
        self.m2 = self.m2 + m2 + delta ** 2 * self.count * frac
        self.count = total
        self.lo = np.where(has, np.fmin(self.lo, np.nanmin(np.where(valid, values, np.inf),
                                                           axis=0)), self.lo)
        self.hi = np.where(has, np.fmax(self.hi, np.nanmax(np.where(valid, values, -np.inf),
                                                           axis=0)), self.hi)

    def result(self) -> dict[str, list]:
        """Per dimension; statistics of a dimension without values are None."""
        empty = self.count == 0
        if self.parts:
            values = np.concatenate(self.parts)
            with np.errstate(all="ignore"):
                p = np.full((2, self.dims), np.nan)
                for d in np.flatnonzero(~empty):
                    col = values[:, d]
                    p[:, d] = np.percentile(col[~np.isnan(col)], [1, 99])
        else:
            p = np.full((2, self.dims), np.nan)
        std = np.sqrt(np.divide(self.m2, self.count, out=np.zeros(self.dims),
                                where=~empty))

        def out(a: np.ndarray) -> list:
            return [None if e else float(v) for v, e in zip(a, empty, strict=True)]

        return {"count": [int(c) for c in self.count], "mean": out(self.mean), "std": out(std),
                "min": out(self.lo), "max": out(self.hi), "p01": out(p[0]), "p99": out(p[1])}


def _shape(f: pa.Field) -> str:
    return (f.metadata or {}).get(b"shape", b"").decode()


def _unit(f: pa.Field) -> str:
    return (f.metadata or {}).get(b"unit", b"").decode()


def _flat_values(chunk: pa.Array) -> np.ndarray:
    """A (fixed-size) list chunk's values as (rows, width) float64; null rows dropped."""
    chunk = chunk.drop_null()
    while pa.types.is_list(chunk.type) or pa.types.is_fixed_size_list(chunk.type) or \
            pa.types.is_large_list(chunk.type):
        chunk = chunk.flatten()
    return chunk.to_numpy(zero_copy_only=False).astype(np.float64, copy=False)


@dataclass(frozen=True)
class Quantity:
    """How one column becomes the values of a statistics entry."""

    column: str
    key: str
    names: list[str] | None
    """Per-dimension names; None for a scalar column."""
    unit: str
    what: str
    pick: tuple[int, ...] | None = None
    """Row-vector indices to keep (a pose's translation); None keeps all."""
    width: int = 1
    """Values per row before ``pick`` (16 for a pose)."""


def quantities(schema: pa.Schema) -> list[Quantity]:
    """The statistics entries of a table's numeric columns (module docstring)."""
    out = []
    for f in schema:
        t = f.type
        if pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_boolean(t):
            out.append(Quantity(f.name, f.name, None, _unit(f), "per row"))
            continue
        if not pa.types.is_fixed_size_list(t) or not (
                pa.types.is_floating(t.value_type) or pa.types.is_integer(t.value_type)):
            continue
        shape, width = _shape(f), t.list_size
        if shape == POSE_SHAPE:
            out.append(Quantity(f.name, f"{f.name}.translation", _XYZ, _unit(f),
                                "translation of the pose, per coordinate", tuple(_TRANSLATION),
                                width))
        elif "x" in shape and shape.split("x")[-1] in ("2", "3"):
            k = int(shape.split("x")[-1])
            out.append(Quantity(f.name, f.name, _XYZ if k == 3 else _UV, _unit(f),
                                f"per coordinate over the {shape.split('x')[0]} rows", None, k))
        else:
            out.append(Quantity(f.name, f.name, [str(i) for i in range(width)], _unit(f),
                                "per element", None, width))
    return out


def _chunks(table: pa.Table | pa.RecordBatch, column: str) -> Iterable[pa.Array]:
    col = table.column(column)
    return col.chunks if isinstance(col, pa.ChunkedArray) else [col]


def column_stats(table: pa.Table, q: Quantity) -> dict:
    """One entry of ``stats.json`` for quantity ``q`` of ``table``."""
    dims = len(q.names) if q.names else 1
    acc = Accumulator(dims)
    for chunk in _chunks(table, q.column):
        if pa.types.is_boolean(chunk.type):
            chunk = pc.cast(chunk, pa.int8())
        values = _flat_values(chunk)
        if q.pick is not None:
            values = values.reshape(-1, q.width)[:, list(q.pick)]
        acc.update(values.reshape(-1, dims))
    res = acc.result()
    entry: dict = {"unit": q.unit, "values": q.what}
    if q.names is None:
        entry.update({k: v[0] for k, v in res.items()})
    else:
        entry["names"] = q.names
        entry.update(res)
    return entry


def table_stats(table: pa.Table) -> dict[str, dict]:
    """Every numeric quantity of ``table``, by key."""
    return {q.key: column_stats(table, q) for q in quantities(table.schema)}


def array_stats(kind: str, table: pa.Table, units: dict[str, str]) -> dict[str, dict]:
    """Statistics of one array kind's export table (one row per group, arrays as list
    columns): values pooled over every group; ``(n, 3)`` arrays per coordinate; index
    arrays (``faces``) left out."""
    out = {}
    for f in table.schema:
        if f.name in ("digest", "faces"):
            continue
        inner = f.type.value_type
        k = inner.list_size if pa.types.is_fixed_size_list(inner) else 1
        names = _XYZ if k == 3 else None
        q = Quantity(f.name, f.name, names, units.get(f.name, ""),
                     "per coordinate over every group's rows" if names else
                     "over every group's elements (bool as 0/1)")
        acc = Accumulator(k)
        for chunk in _chunks(table, f.name):
            flat = chunk.flatten()
            while pa.types.is_fixed_size_list(flat.type) or pa.types.is_list(flat.type):
                flat = flat.flatten()
            if pa.types.is_boolean(flat.type):
                flat = pc.cast(flat, pa.int8())
            acc.update(flat.to_numpy(zero_copy_only=False).reshape(-1, k))
        res = acc.result()
        entry: dict = {"unit": q.unit, "values": q.what, "groups": table.num_rows}
        if names is None:
            entry.update({key: v[0] for key, v in res.items()})
        else:
            entry["names"] = names
            entry.update(res)
        out[f"{kind}.{f.name}"] = entry
    return out


__all__ = ["Quantity", "array_stats", "column_stats", "quantities", "table_stats"]
