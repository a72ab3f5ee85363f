"""Immutable, content-addressed Zarr v3 groups: write once under their digest, read by digest.

The digest is the sha256 of the group's kind and, per array in ``ZARR_LAYOUT`` order, its name,
dtype, shape and bytes: equal content gives the same group whatever the Zarr codecs, so a build
that reproduces a session's arrays reuses the group already there. A group is written under
``arrays/.tmp/`` and renamed into place when complete, so a reader never sees half a group.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import uuid
import warnings
from collections.abc import Mapping

import numpy as np
import zarr

from graspcap.catalog.errors import CatalogError, CatalogSchemaError
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION, ZARR_LAYOUT

# The catalog writes consolidated metadata on purpose (one read per group) and says so in
# docs/architecture.md; zarr warns about it on every group, from writer threads too, where a
# catch_warnings block would not reach, so the filter is process-wide.
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")


def check_arrays(kind: str, arrays: Mapping[str, np.ndarray], *, owner: str) -> dict:
    """``arrays`` as the dtypes and shapes of ``ZARR_LAYOUT[kind]``, or ``CatalogSchemaError``.

    Floats may be narrowed (float64 -> float32); anything else must already be of the kind.
    ``owner`` (the session or object id) goes into the message.
    """
    spec = ZARR_LAYOUT[kind]
    if set(arrays) != set(spec.arrays):
        raise CatalogSchemaError(f"arrays/{kind}", None, [owner],
                                 f"expected arrays {sorted(spec.arrays)}, got {sorted(arrays)}")
    out, sizes = {}, {}
    for name, a_spec in spec.arrays.items():
        a = np.asarray(arrays[name])
        if a.dtype != a_spec.dtype and not np.can_cast(a.dtype, a_spec.dtype, "same_kind"):
            raise CatalogSchemaError(f"arrays/{kind}", name, [owner],
                                     f"dtype {a.dtype} cannot be stored as {a_spec.dtype}")
        if a.ndim != len(a_spec.shape):
            raise CatalogSchemaError(f"arrays/{kind}", name, [owner],
                                     f"shape {a.shape} does not match {a_spec.shape}")
        for dim, want in zip(a.shape, a_spec.shape, strict=True):
            if isinstance(want, str):
                want = sizes.setdefault(want, dim)
            if dim != want:
                raise CatalogSchemaError(f"arrays/{kind}", name, [owner],
                                         f"shape {a.shape} does not match {a_spec.shape} "
                                         f"with {sizes}")
        out[name] = np.ascontiguousarray(a, dtype=a_spec.dtype)
    if "faces" in out and out["faces"].size:
        n = out["vertices"].shape[0]
        if out["faces"].min() < 0 or out["faces"].max() >= n:
            raise CatalogSchemaError(f"arrays/{kind}", "faces", [owner],
                                     f"face indices outside 0..{n - 1}")
    return out


def array_digest(kind: str, arrays: Mapping[str, np.ndarray]) -> str:
    """sha256 hex of a checked group (see :func:`check_arrays`)."""
    h = hashlib.sha256(f"graspcap-arrays/{kind}\n".encode())
    for name in ZARR_LAYOUT[kind].arrays:
        a = arrays[name]
        h.update(f"{name}|{a.dtype.str}|{a.shape}\n".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def write_group(layout: CatalogLayout, kind: str, arrays: Mapping[str, np.ndarray],
                digest: str) -> bool:
    """Write a checked group under ``digest`` unless it exists; True when written."""
    final = layout.array_group(digest)
    if final.is_dir():
        return False
    layout.arrays_tmp.mkdir(parents=True, exist_ok=True)
    tmp = layout.arrays_tmp / f"{digest}.{uuid.uuid4().hex}.zarr"
    group = zarr.open_group(str(tmp), mode="w", zarr_format=3, attributes={
        "kind": kind, "digest": digest, "format_version": CATALOG_FORMAT_VERSION})
    for name, a_spec in ZARR_LAYOUT[kind].arrays.items():
        a = arrays[name]
        chunks = (max(1, min(a.shape[0], a_spec.chunk_rows)), *a.shape[1:])
        group.create_array(name, data=a, chunks=chunks,
                           attributes={"unit": a_spec.unit, "doc": a_spec.doc})
    zarr.consolidate_metadata(str(tmp))
    final.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.rename(tmp, final)
    except OSError:  # written meanwhile by someone else: same digest, same content
        shutil.rmtree(tmp, ignore_errors=True)
        if not final.is_dir():
            raise
        return False
    return True


def read_group(layout: CatalogLayout, digest: str,
               names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The arrays of the group ``digest`` (all, or ``names`` in that order)."""
    path = layout.array_group(digest)
    if not path.is_dir():
        raise CatalogError(f"array group {digest} is missing from {layout.arrays_dir}; "
                           "it was removed by vacuum or the catalog is damaged")
    group = zarr.open_group(str(path), mode="r", zarr_format=3, use_consolidated=True)
    if names is None:
        names = tuple(ZARR_LAYOUT[group.attrs["kind"]].arrays)
    return {name: group[name][...] for name in names}


def all_digests(layout: CatalogLayout) -> set[str]:
    """Digests of every complete group on disk."""
    if not layout.arrays_dir.is_dir():
        return set()
    return {p.name.removesuffix(".zarr") for p in layout.arrays_dir.glob("??/*.zarr")}
