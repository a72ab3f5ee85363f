"""Compare two ``sessions`` tables: sessions added, removed, and the columns that changed."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc


@dataclass(frozen=True)
class SessionsDiff:
    """Sessions of ``new`` not in ``old`` (added), the reverse (removed), and per session in both
    the columns whose values differ (changed; NaN equals NaN)."""

    added: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    changed: dict[str, list[str]] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"added": self.added, "removed": self.removed, "changed": self.changed}


def _column_equal(a: pa.ChunkedArray, b: pa.ChunkedArray) -> np.ndarray:
    """Row-wise equality of two aligned columns, nulls equal nulls, NaN equals NaN."""
    a, b = a.combine_chunks(), b.combine_chunks()
    null_a = a.is_null().to_numpy(zero_copy_only=False)
    null_b = b.is_null().to_numpy(zero_copy_only=False)
    if pa.types.is_fixed_size_list(a.type) or pa.types.is_floating(a.type):
        if pa.types.is_fixed_size_list(a.type):
            k = a.type.list_size
            va = a.values.to_numpy(zero_copy_only=False)[a.offset * k:(a.offset + len(a)) * k]
            vb = b.values.to_numpy(zero_copy_only=False)[b.offset * k:(b.offset + len(b)) * k]
            va, vb = va.reshape(len(a), k), vb.reshape(len(b), k)
        else:
            va = a.to_numpy(zero_copy_only=False)[:, None]
            vb = b.to_numpy(zero_copy_only=False)[:, None]
        same = ((va == vb) | (np.isnan(va) & np.isnan(vb))).all(axis=1)
    else:
        same = np.array([x == y for x, y in zip(a.to_pylist(), b.to_pylist(), strict=True)],
                        dtype=bool)
    return np.where(null_a | null_b, null_a & null_b, same)


def diff_sessions(old: pa.Table, new: pa.Table, ignore: tuple[str, ...] = ()) -> SessionsDiff:
    """Added, removed and changed sessions from ``old`` to ``new``, skipping ``ignore`` columns."""
    old_ids = set(old["session_id"].to_pylist())
    new_ids = set(new["session_id"].to_pylist())
    both = pa.array(sorted(old_ids & new_ids), pa.string())
    old_b = old.filter(pc.is_in(old["session_id"], both)).sort_by("session_id")
    new_b = new.filter(pc.is_in(new["session_id"], both)).sort_by("session_id")
    changed: dict[str, list[str]] = {}
    ids = new_b["session_id"].to_pylist()
    for col in new.column_names:
        if col in ignore or col not in old.column_names or not ids:
            continue
        for i in np.flatnonzero(~_column_equal(old_b[col], new_b[col])):
            changed.setdefault(ids[i], []).append(col)
    return SessionsDiff(sorted(new_ids - old_ids), sorted(old_ids - new_ids), changed)
