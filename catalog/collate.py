"""Batches of ``GraspDataset`` items as numpy arrays, for any sessions and objects (no torch).

``collate_fn(items)`` is a ``DataLoader`` ``collate_fn``: per-item values are stacked along a
new first axis (``(B, ...)``) where every item has the same shape and a numeric dtype, and kept
as a list otherwise (strings, values with nulls, images of different sizes). The session's
arrays (meshes, contact maps: :data:`SESSION_ARRAYS`), which differ in length between objects
and are the same for every frame of a session, go once per session of the batch into
``batch["sessions"]``, zero-padded to the longest with the true lengths beside them:

    batch["session_index"]                  (B,) int64, row of each item in batch["sessions"]
    batch["sessions"]["session_id"]         list of S session ids, first appearance order
    batch["sessions"]["mesh_id"]            list of S object mesh digests
    batch["sessions"]["object_vertices"]    (S, N_max, 3) float32, zero past the count
    batch["sessions"]["object_vertices_count"]  (S,) int64 true lengths (same for each array)

Every array is a fresh, writable one. For tensors, ``torch.utils.data.default_convert(batch)``
(or ``torch.as_tensor`` per array) converts the arrays and leaves the lists as they are.
"""

from __future__ import annotations

from collections.abc import Sequence
from numbers import Number
from typing import Any

import numpy as np

SESSION_ARRAYS = ("contact", "contact_observed", "hand_vertices", "hand_faces", "hand_joints_o",
                  "object_vertices", "object_faces")
"""Item keys that hold a session's arrays (the same object for every frame of a session)."""
SESSION_KEYS = ("mesh_id",)
"""Other per-session item keys that go into ``batch["sessions"]`` as lists."""


def _stack(values: list[Any]) -> np.ndarray | list[Any]:
    """``values`` stacked when they are numeric arrays of one shape or numeric scalars
    (bool included); else the list."""
    if all(isinstance(v, np.ndarray) for v in values):
        first = values[0]
        if first.dtype.kind in "biuf" and all(v.shape == first.shape and v.dtype == first.dtype
                                              for v in values):
            return np.stack(values)
        return values
    if all(isinstance(v, (Number, np.bool_, np.number)) and v is not None for v in values):
        return np.array(values)
    return values


def _pad(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(S, N_max, ...)`` zero-padded along axis 0 of each array, and the ``(S,)`` lengths."""
    counts = np.array([len(a) for a in arrays], dtype=np.int64)
    first = arrays[0]
    out = np.zeros((len(arrays), int(counts.max(initial=0)), *first.shape[1:]), first.dtype)
    for row, a in zip(out, arrays, strict=True):
        row[:len(a)] = a
    return out, counts


def collate_fn(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One batch of ``items`` (``GraspDataset`` items): see the module docstring."""
    if not items:
        raise ValueError("collate_fn: an empty batch")
    keys = list(items[0])
    for n, item in enumerate(items[1:], start=1):
        if list(item) != keys:
            raise ValueError(f"collate_fn: item {n} has keys {sorted(item)}, item 0 "
                             f"{sorted(keys)}: items of one dataset only")
    per_session = [k for k in keys if k in SESSION_ARRAYS or k in SESSION_KEYS]
    sessions: dict[str, int] = {}
    first_item: list[dict[str, Any]] = []
    index = np.empty(len(items), dtype=np.int64)
    for n, item in enumerate(items):
        sid = item["session_id"]
        if sid not in sessions:
            sessions[sid] = len(sessions)
            first_item.append(item)
        index[n] = sessions[sid]
    batch: dict[str, Any] = {k: _stack([item[k] for item in items])
                             for k in keys if k not in per_session}
    batch["session_index"] = index
    group: dict[str, Any] = {"session_id": list(sessions)}
    for k in per_session:
        values = [item[k] for item in first_item]
        if k in SESSION_KEYS:
            group[k] = values
        else:
            group[k], group[f"{k}_count"] = _pad([np.asarray(v) for v in values])
    batch["sessions"] = group
    return batch
