"""Immutable, content-addressed Zarr v3 groups: write once under their digest, read by digest.

The digest is the sha256 of the group's kind and, per array in ``ZARR_LAYOUT`` order, its name,
dtype, shape and bytes: equal content gives the same group whatever the Zarr codecs, so a build
that reproduces a session's arrays reuses the group already there. A group is written under
``arrays/.tmp/`` and renamed into place when complete, so a reader never sees half a group.

Integrity (format 5): every chunk is written (also one holding only the fill value, which zarr
would otherwise skip and read back as the fill value), and the group's attributes carry
``chunks``, the sha256 of every file of the group but its root ``zarr.json`` (chunks and array
metadata). Every read checks the files of the arrays it reads against that manifest and fails
with :class:`DamagedArrayError` naming the group, the array and the file when one is missing
or altered, so a damaged chunk never reads as zeros. The root ``zarr.json`` itself (and groups
written before format 5, without a manifest) are checked only by :func:`verify_group`
(``graspcap catalog verify``), which decodes the whole group and compares its content with its
digest (costs: docs/catalog.md, "Integrity").

Reading is the hot path of training (one group per item), so it costs one pass over the group's
few small files and one decode: the files are read with the layout's fsspec filesystem (a local
folder or an object store, where ``cat`` fetches them concurrently) into a Zarr ``MemoryStore``
and decoded by zarr's async API on an event loop owned by the calling thread. Going through
zarr's synchronous API instead hands every metadata and chunk read to zarr's I/O thread and
back, which measured 3-10x slower on a loaded machine (``docs/architecture.md``). Writing
is the mirror image: zarr encodes a group into a ``MemoryStore`` on the same loop, and its
files are written out by plain Python.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import shutil
import threading
import uuid
import warnings
from collections.abc import Mapping

import numpy as np
import zarr.api.asynchronous as zarr_async
from zarr.core.buffer import cpu, default_buffer_prototype
from zarr.core.sync import sync as zarr_sync
from zarr.storage import MemoryStore

from graspcap.catalog.errors import CatalogError, CatalogSchemaError
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION, ZARR_LAYOUT

# The catalog writes consolidated metadata on purpose (one read per group) and says so in
# docs/architecture.md; zarr warns about it on every group, from writer threads too, where a
# catch_warnings block would not reach, so the filter is process-wide.
warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")


MANIFEST_ATTR = "chunks"
"""Group attribute: ``{file key: sha256 hex}`` of every file but the root ``zarr.json``."""
TMP_PID_SEP = "."
"""A temp group is ``arrays/.tmp/<digest>.<pid>.<random>.zarr``: the pid says who writes it."""


class DamagedArrayError(CatalogError):
    """An array group's file is missing or does not match the group's manifest or digest."""

    def __init__(self, digest: str, message: str, *, array: str | None = None,
                 file: str | None = None):
        self.digest = digest
        self.array = array
        self.file = file
        super().__init__(message)


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


_LOOPS = threading.local()


def _run(coro):
    """Run ``coro`` on this thread's own event loop (zarr's loop when one is running here)."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        pass
    else:  # called from async code (a notebook): hand over to zarr's I/O thread
        return zarr_sync(coro)
    loop = getattr(_LOOPS, "loop", None)
    if loop is None or _LOOPS.pid != os.getpid():  # a forked DataLoader worker gets its own
        loop = _LOOPS.loop = asyncio.new_event_loop()
        _LOOPS.pid = os.getpid()
    return loop.run_until_complete(coro)


def _group_files(layout: CatalogLayout, root: str, names: tuple[str, ...] | None
                 ) -> dict[str, bytes]:
    """The files of the group at ``root`` (the group's own and those of ``names``), by key."""
    if layout.is_local:
        out = {}
        tops = [root] if names is None else [os.path.join(root, n) for n in names]
        with open(os.path.join(root, "zarr.json"), "rb") as fh:
            out["zarr.json"] = fh.read()
        for top in tops:
            for folder, _, files in os.walk(top):
                for f in files:
                    path = os.path.join(folder, f)
                    with open(path, "rb") as fh:
                        out[os.path.relpath(path, root)] = fh.read()
        return out
    fs = layout.fs
    paths = fs.find(root) if names is None else [
        root + "/zarr.json", *[p for n in names for p in fs.find(f"{root}/{n}")]]
    return {p[len(root) + 1:]: data for p, data in fs.cat(paths).items()}


async def _decode(files: dict[str, bytes], names: tuple[str, ...] | None
                  ) -> dict[str, np.ndarray]:
    store = MemoryStore({k: cpu.Buffer.from_bytes(v) for k, v in files.items()})
    group = await zarr_async.open_group(store=store, mode="r", zarr_format=3)
    if names is None:
        names = tuple(ZARR_LAYOUT[group.attrs["kind"]].arrays)
    arrays = await asyncio.gather(*(group.getitem(n) for n in names))
    values = await asyncio.gather(*(a.getitem(...) for a in arrays))
    return dict(zip(names, values, strict=True))


async def _encode(kind: str, arrays: Mapping[str, np.ndarray], digest: str) -> dict[str, bytes]:
    """The files of a group (key -> bytes), encoded by zarr in memory."""
    store = MemoryStore()
    group = await zarr_async.open_group(store=store, mode="w", zarr_format=3, attributes={
        "kind": kind, "digest": digest, "format_version": CATALOG_FORMAT_VERSION})
    for name, a_spec in ZARR_LAYOUT[kind].arrays.items():
        a = arrays[name]
        chunks = (max(1, min(a.shape[0], a_spec.chunk_rows)), *a.shape[1:])
        codecs = {} if a_spec.compressed else {"compressors": None}
        # every chunk on disk, also an all-fill one: a missing chunk is then always damage
        array = await group.create_array(name, shape=a.shape, dtype=a.dtype, chunks=chunks,
                                         attributes={"unit": a_spec.unit, "doc": a_spec.doc},
                                         config={"write_empty_chunks": True}, **codecs)
        await array.setitem(Ellipsis, a)
    proto = default_buffer_prototype()
    files = {key: (await store.get(key, prototype=proto)).to_bytes()
             async for key in store.list()}
    manifest = {k: hashlib.sha256(v).hexdigest() for k, v in sorted(files.items())
                if k != "zarr.json"}
    await group.update_attributes({MANIFEST_ATTR: manifest})
    await zarr_async.consolidate_metadata(store)
    return {key: (await store.get(key, prototype=proto)).to_bytes()
            async for key in store.list()}


def write_group(layout: CatalogLayout, kind: str, arrays: Mapping[str, np.ndarray],
                digest: str) -> bool:
    """Write a checked group under ``digest`` unless it exists; True when written.

    zarr encodes the group into memory on this thread's loop (as reads decode, see the module
    docstring); its files are written under ``arrays/.tmp/`` and the folder renamed into place.
    """
    final = layout.array_group(digest)
    if final.is_dir():
        return False
    files = _run(_encode(kind, arrays, digest))
    layout.arrays_tmp.mkdir(parents=True, exist_ok=True)
    tmp = layout.arrays_tmp / f"{digest}.{os.getpid()}.{uuid.uuid4().hex}.zarr"
    for key, data in files.items():
        path = tmp / key
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
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
    root = layout.group_fs_path(digest)
    try:
        files = _group_files(layout, root, names)
    except FileNotFoundError:
        if layout.fs.isdir(root):
            raise DamagedArrayError(digest, f"array group {digest}: its zarr.json is missing "
                                    f"({root}/zarr.json); the catalog is damaged (`graspcap "
                                    "catalog verify`)", file="zarr.json") from None
        raise DamagedArrayError(digest, f"array group {digest} is missing from {layout.uri}/"
                                "arrays; it was removed by vacuum or the catalog is damaged "
                                "(`graspcap catalog verify` lists what is)") from None
    check_files(root, digest, files, names)
    try:
        return _run(_decode(files, names))
    except (ValueError, KeyError, RuntimeError, TypeError) as exc:  # zarr/numcodecs' own
        raise DamagedArrayError(digest, f"array group {root} cannot be decoded ({exc}); the "
                                "catalog is damaged (`graspcap catalog verify`)") from exc


def manifest_of(files: Mapping[str, bytes]) -> dict[str, str] | None:
    """The group's ``chunks`` manifest from its root ``zarr.json``; None before format 5."""
    try:
        meta = json.loads(files["zarr.json"])
    except (KeyError, ValueError):
        return None
    manifest = meta.get("attributes", {}).get(MANIFEST_ATTR) if isinstance(meta, dict) else None
    return manifest if isinstance(manifest, dict) else None


def check_files(root: str, digest: str, files: Mapping[str, bytes],
                names: tuple[str, ...] | None) -> None:
    """Fail with :class:`DamagedArrayError` when a file of the arrays ``names`` (all: None)
    that the group's manifest lists is missing from ``files`` or has other bytes."""
    manifest = manifest_of(files)
    if manifest is None:  # written before format 5 (or a damaged root zarr.json): verify's job
        return
    for key, sha in manifest.items():
        array = key.split("/", 1)[0]
        if names is not None and array not in names:
            continue
        if key not in files:
            raise DamagedArrayError(
                digest, f"array group {digest}: file {key} of array {array!r} is missing "
                f"({root}/{key}); the catalog is damaged (`graspcap catalog verify`)",
                array=array, file=key)
        if hashlib.sha256(files[key]).hexdigest() != sha:
            raise DamagedArrayError(
                digest, f"array group {digest}: file {key} of array {array!r} does not match "
                f"the group's manifest ({root}/{key} was altered); the catalog is damaged "
                "(`graspcap catalog verify`)", array=array, file=key)


def verify_group(layout: CatalogLayout, digest: str, kind: str | None = None) -> list[str]:
    """What is wrong with the group ``digest`` (empty: nothing): every file the manifest lists
    present and matching, the whole group decodable, of ``kind`` (when given), its content
    matching its digest."""
    root = layout.group_fs_path(digest)
    try:
        files = _group_files(layout, root, None)
    except FileNotFoundError:
        if layout.fs.isdir(root):
            return [f"its zarr.json is missing ({root}/zarr.json)"]
        return [f"group {root} is missing"]
    problems = []
    manifest = manifest_of(files)
    for key, sha in (manifest or {}).items():
        if key not in files:
            problems.append(f"file {key} of array {key.split('/', 1)[0]!r} is missing")
        elif hashlib.sha256(files[key]).hexdigest() != sha:
            problems.append(f"file {key} of array {key.split('/', 1)[0]!r} was altered "
                            "(its sha256 differs from the manifest)")
    if problems:  # the decoded content would differ from the digest too: said once
        return problems
    try:
        arrays = _run(_decode(files, None))
        meta = json.loads(files["zarr.json"])
        found = meta["attributes"]["kind"]
        if kind is not None and found != kind:
            problems.append(f"it holds a {found!r} group where a {kind!r} one is referenced")
        elif array_digest(found, arrays) != digest:
            problems.append("its content does not match its digest (an altered or missing "
                            "chunk, or altered metadata)")
    except Exception as exc:  # noqa: BLE001 - any failure to decode is damage to report
        problems.append(f"cannot be decoded: {type(exc).__name__}: {exc}")
    return problems


def add_manifest(layout: CatalogLayout, digest: str) -> str | None:
    """Bring a group written before format 5 up to format 5 in place (call under the writer
    lock): its content is checked against its digest, then the chunks zarr skipped and the
    manifest are added. Every file is replaced atomically and the root ``zarr.json`` last, so
    a reader sees the group whole throughout. None when done (or already done); else what is
    wrong with the group, which is left as it is."""
    root = layout.array_group(digest)
    try:
        files = _group_files(layout, str(root), None)
    except FileNotFoundError:
        return f"group {root} is missing"
    if manifest_of(files) is not None:
        return None
    try:
        arrays = _run(_decode(files, None))
        kind = json.loads(files["zarr.json"])["attributes"]["kind"]
        if array_digest(kind, arrays) != digest:
            return "its content does not match its digest (an altered or missing chunk)"
    except Exception as exc:  # noqa: BLE001 - any failure to decode is damage to report
        return f"cannot be decoded: {type(exc).__name__}: {exc}"
    fresh = _run(_encode(kind, arrays, digest))
    for key in [*sorted(k for k in fresh if k != "zarr.json"), "zarr.json"]:
        if files.get(key) == fresh[key]:
            continue
        path = root / key
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_bytes(fresh[key])
        os.replace(tmp, path)
    return None


def all_digests(layout: CatalogLayout) -> set[str]:
    """Digests of every complete group on disk."""
    if not layout.arrays_dir.is_dir():
        return set()
    return {p.name.removesuffix(".zarr") for p in layout.arrays_dir.glob("??/*.zarr")}


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_temp_groups(layout: CatalogLayout) -> list[str]:
    """Delete what killed writers left in ``arrays/.tmp`` (call under the writer lock);
    return the names removed. A temp group of a live process (its pid in the name) is kept."""
    if not layout.arrays_tmp.is_dir():
        return []
    removed = []
    for path in layout.arrays_tmp.iterdir():
        parts = path.name.split(TMP_PID_SEP)
        pid = int(parts[1]) if len(parts) == 4 and parts[1].isdigit() else None
        if pid is not None and pid != os.getpid() and _pid_alive(pid):
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
        removed.append(path.name)
    return removed
