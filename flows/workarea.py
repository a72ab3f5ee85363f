"""The build work area: stage results stored by cache key, file digests remembered.

Stage results can hold big arrays, so they never travel through Prefect's
result store: a stage's result is pickled (protocol 5, numpy buffers written
as they are) into ``<root>/results/<stage>/<key>.pkl`` and tasks hand each
other a small :class:`ResultRef` (path + content digest). Writes are atomic
(temporary file, then rename) and the result's small JSON record
(``<key>.json``: digest, size, build, seconds, modules, types) is written after the pickle, so a
killed build never leaves a half result that a later lookup would trust (a lookup also
takes a result only when its pickle has the size its record names). The record lists the
modules the pickle names (classes, functions); a result whose modules cannot be imported any
more (a module moved, as in the ``tasks/`` sub-package layout) is a cache miss, not a crash,
and so is a record from before the list. The record also names every dataclass and pydantic
type in the result (``module:qualname``) with its field set: a type that is gone or whose
fields changed (renamed, moved, a field added the code would expect) is a miss with a note
(:meth:`WorkArea.check`), never a result missing a field. Temporary
files are named ``.tmp-<host>-<pid>-*``; those of a writer that is gone (same host, pid not
running, or older than ``STALE_TEMP_S``) are removed when a process first opens the area.

A deterministic failure (a ``StageError``) is remembered too, as ``<key>.failed.json`` (its
reason): running the same stage version and config on the same bytes fails the same way, so an
unchanged rebuild replays it instead of running the stage again; ``--retry-failed`` ignores it.

File digests (the inputs of every cache key) are remembered by (path, size, mtime_ns, inode)
in ``<root>/digests/``, one JSON memo per folder of input files (:meth:`WorkArea.file_digest`):
an unchanged session costs a new process one ``stat`` per file, no hashing.

``executions.jsonl`` is the side channel of stage-body executions: one JSON line per
attempt (stage, session, key, build, seconds, CPU seconds, pid, ok, error), appended with
``O_APPEND`` in one ``write``, so lines from concurrent workers never interleave.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import io
import json
import os
import pickle
import shutil
import socket
import tempfile
import threading
import time
import types
import uuid
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from graspcap.catalog.errors import writing

_CHUNK = 1 << 20
EXECUTIONS = "executions.jsonl"
BUILDS_LOG = "builds.jsonl"
"""The work area's log of builds, one JSON record a line (``graspcap status``)."""
RACY_S = 2.0
"""A file modified less than this long before it is hashed may change again within the same
mtime tick (a coarse file-system clock): its digest is used but not remembered (git's
"racily clean" rule)."""


def is_racy(mtime_ns: int) -> bool:
    """True for a file modified less than ``RACY_S`` ago: use its digest, do not remember it."""
    return time.time_ns() - mtime_ns < RACY_S * 1e9


STALE_TEMP_S = 6 * 3600.0
"""A temporary file this old is a killed writer's, whatever host wrote it."""
TEMP_PREFIX = ".tmp-"
DIGEST_MEMO_FORMAT = 1
"""Format of the folder memos under ``<root>/digests/`` (``dir-<sha of folder>.json``)."""


@dataclass(frozen=True)
class ResultRef:
    """Where a stage result lives and what its bytes hash to."""

    stage: str
    key: str
    path: str
    digest: str
    build_id: str
    """The build whose run produced the result (differs from the current build on a cache hit)."""
    cached: bool = False
    """True when the task found the result in the work area and ran no stage body."""
    seconds: float = 0.0
    """Wall time of the stage body that produced the result."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


class WorkArea:
    """Results and digests under one root folder (default: the catalog's ``work/``).

    Every worker of a build must be able to read and write ``root`` (a local folder, or a
    shared file system mounted at the same path on every machine).
    """

    _loaded: OrderedDict[str, Any] = OrderedDict()
    """Results by content digest, most recently used last: the ones this process saved or
    loaded, so a downstream task does not unpickle what an upstream task just wrote."""
    _loaded_lock = threading.Lock()
    _LOADED_MAX = 64
    _memo: dict[str, str] = {}
    """File digests by (path, size, mtime_ns, inode), for every work area of this process."""
    _MEMO_MAX = 200_000
    _folders: dict[tuple[str, str], dict[str, list]] = {}
    """Folder memos read or added to by this process, by (digest index, folder)."""
    _FOLDERS_MAX = 50_000
    _dirty: dict[int, set[str]] = {}
    """Folders whose memo a thread added digests to and has not written yet, by thread."""
    _memo_lock = threading.Lock()
    _swept: set[Path] = set()
    """Roots whose stale temporary files this process has removed."""
    readonly: bool = False
    """True for :meth:`reader`: nothing is written (a build plan writes nothing)."""

    def __init__(self, root: Path | str):
        self.root = Path(root).expanduser().resolve()
        with writing(self.root):
            (self.root / "results").mkdir(parents=True, exist_ok=True)
            self._digest_index = self.root / "digests"
            self._digest_index.mkdir(exist_ok=True)
        if self.root not in self._swept:
            self._swept.add(self.root)
            self.remove_stale_temp()

    @classmethod
    def reader(cls, root: Path | str) -> WorkArea:
        """The work area at ``root`` opened to read only: no folder is made, no temporary file
        swept, no digest remembered on disk (``graspcap build --plan``)."""
        work = cls.__new__(cls)
        work.root = Path(root).expanduser().resolve()
        work._digest_index = work.root / "digests"
        work.readonly = True
        return work

    def remove_stale_temp(self) -> list[Path]:
        """Delete the temporary files of writers that are gone (killed builds); return them."""
        removed = []
        folders = [self.root, self._digest_index,
                   *(p for p in (self.root / "results").iterdir() if p.is_dir())]
        now = time.time()
        for folder in folders:
            try:
                entries = list(os.scandir(folder))
            except OSError:
                continue
            for entry in entries:
                if not entry.name.startswith(TEMP_PREFIX):
                    continue
                try:
                    age = now - entry.stat(follow_symlinks=False).st_mtime
                except FileNotFoundError:
                    continue
                if age > STALE_TEMP_S or not _writer_alive(entry.name):
                    if entry.is_dir(follow_symlinks=False):  # a killed build's Spill
                        shutil.rmtree(entry.path, ignore_errors=True)
                    else:
                        Path(entry.path).unlink(missing_ok=True)
                    removed.append(Path(entry.path))
        return removed

    def __getstate__(self) -> dict:
        return {"root": str(self.root)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["root"])

    @property
    def executions_file(self) -> Path:
        return self.root / EXECUTIONS

    # --- file digests -----------------------------------------------------------------------
    def file_digest(self, path: Path) -> str:
        """sha256 of a file's bytes, remembered by (path, size, mtime_ns, inode) so unchanged
        files are not hashed again on every build (a file replaced by a rename, even with the
        same size and mtime, has a new inode): in this process's memory, and for files of any
        size in one memo per folder under ``<root>/digests/`` (:meth:`_folder_memo`), so a new
        process settles an unchanged session with a ``stat`` of each file and one small read
        per folder. A file modified less than ``RACY_S`` before it is hashed is not remembered
        (git's "racily clean" rule). The known risk, the one Make, git and DVC take too: a file
        rewritten with the same size, the same mtime_ns and the same inode (a tool that writes
        in place and then restores the old mtime) keeps its old digest; ``touch`` it."""
        digest = self._digest(path)
        self._flush_memos()
        return digest

    def files_digest(self, paths: list[Path]) -> str:
        """One digest over many files (names and their order kept)."""
        h = hashlib.sha256()
        for p in paths:
            h.update(str(p).encode())
            h.update(self._digest(p).encode())
        self._flush_memos()
        return h.hexdigest()

    def _digest(self, path: Path) -> str:
        st = os.stat(path)
        full = os.path.abspath(path)
        ident = f"{full}|{st.st_size}|{st.st_mtime_ns}|{st.st_ino}"
        if (digest := self._memo.get(ident)) is not None:
            return digest
        folder, name = os.path.split(full)
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        memo = self._folder_memo(folder)
        found = memo.get(name)
        if found is not None and found[:3] == stamp and isinstance(found[3], str):
            digest = found[3]
        else:
            digest = sha256_file(Path(path))
            if is_racy(st.st_mtime_ns):
                return digest  # may change again within the same mtime tick: not remembered
            with self._memo_lock:
                memo[name] = [*stamp, digest]
                self._dirty.setdefault(threading.get_ident(), set()).add(folder)
        if len(self._memo) >= self._MEMO_MAX:
            self._memo.clear()
        self._memo[ident] = digest
        return digest

    def _memo_file(self, folder: str) -> Path:
        return self._digest_index / ("dir-" + hashlib.sha256(folder.encode()).hexdigest()[:32]
                                     + ".json")

    def _folder_memo(self, folder: str) -> dict[str, list]:
        """The digests remembered for the files of ``folder`` (``name -> [size, mtime_ns,
        inode, sha256]``), read once per process and work area."""
        key = (str(self._digest_index), folder)
        with self._memo_lock:
            if (memo := self._folders.get(key)) is not None:
                return memo
        memo = self._read_memo(folder)
        with self._memo_lock:
            if len(self._folders) >= self._FOLDERS_MAX:
                self._folders.clear()
            return self._folders.setdefault(key, memo)

    def _read_memo(self, folder: str) -> dict[str, list]:
        try:
            raw = json.loads(self._memo_file(folder).read_bytes())
        except (OSError, ValueError):
            return {}
        if not isinstance(raw, dict) or raw.get("format") != DIGEST_MEMO_FORMAT \
                or raw.get("folder") != folder or not isinstance(raw.get("files"), dict):
            return {}  # another format, or a hash collision of two folders' names
        return {n: v for n, v in raw["files"].items() if isinstance(v, list) and len(v) == 4}

    def _flush_memos(self) -> None:
        """Write the folder memos this thread added digests to (merged with what another
        process wrote meanwhile; the last writer of an entry wins, a lost entry is only hashed
        again). A read-only work area writes nothing."""
        with self._memo_lock:
            folders = self._dirty.pop(threading.get_ident(), set())
            wanted = {f: dict(self._folders.get((str(self._digest_index), f), {}))
                      for f in folders}
        if self.readonly:
            return
        for folder, files in wanted.items():
            merged = {**self._read_memo(folder), **files}
            try:
                _atomic_write(self._memo_file(folder), json.dumps(
                    {"format": DIGEST_MEMO_FORMAT, "folder": folder, "files": merged},
                    separators=(",", ":")).encode())
            except OSError:
                pass  # a memo is an aid: the next process hashes these files again

    # --- results ----------------------------------------------------------------------------
    def result_path(self, stage: str, key: str) -> Path:
        return self.root / "results" / stage / f"{key}.pkl"

    def save(self, stage: str, key: str, result: Any, build_id: str,
             seconds: float = 0.0) -> ResultRef:
        """Store ``result`` under ``(stage, key)``; the record is written last. The result
        stays in this process's memory under its digest (``load`` of its ref needs no read)."""
        data, modules, result_types = _pickle_with_modules(result)
        path = self.result_path(stage, key)
        _atomic_write(path, data)
        ref = ResultRef(stage, key, str(path), hashlib.sha256(data).hexdigest(), build_id,
                        cached=False, seconds=seconds)
        record = {"digest": ref.digest, "bytes": len(data), "build_id": build_id,
                  "seconds": seconds, "modules": modules, "types": result_types}
        _atomic_write(path.with_suffix(".json"), canonical_json(record).encode())
        self._remember(ref.digest, result)
        return ref

    def lookup(self, stage: str, key: str) -> ResultRef | None:
        """The stored result of ``(stage, key)`` as a cached ref, or None: also when the
        record is unreadable, or the pickle has another size than it records (a build was
        killed between replacing the pickle and its record), or its types do not load as
        the current code defines them (:meth:`check` says why)."""
        return self.check(stage, key)[0]

    def check(self, stage: str, key: str) -> tuple[ResultRef | None, str | None]:
        """:meth:`lookup`'s ref, and when a stored result exists but cannot be used, why
        (a note for the plan and the build record): a miss, never a crash."""
        path = self.result_path(stage, key)
        record_path = path.with_suffix(".json")
        try:
            record = json.loads(record_path.read_bytes())
            ref = ResultRef(stage, key, str(path), str(record["digest"]),
                            str(record["build_id"]), cached=True,
                            seconds=float(record.get("seconds", 0.0)))
            pickled = path.stat()
        except FileNotFoundError:
            return None, None
        except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError):
            return None, f"the stored {stage} result's record is unreadable"
        if "bytes" in record and record["bytes"] != pickled.st_size:
            return None, f"the stored {stage} result is incomplete"
        if not _importable(record.get("modules")):  # a module moved: a miss, not a crash
            return None, f"the stored {stage} result names modules that no longer import"
        if (why := type_problem(record.get("types"))) is not None:
            return None, f"the stored {stage} result cannot be used: {why}"
        return ref, None

    @classmethod
    def load(cls, ref: ResultRef) -> Any:
        """The result ``ref`` points to: from memory when this process saved or loaded a
        result with the same content digest lately, else read from ``ref.path``."""
        with cls._loaded_lock:
            if ref.digest in cls._loaded:
                cls._loaded.move_to_end(ref.digest)
                return cls._loaded[ref.digest]
        with open(ref.path, "rb") as f:
            data = f.read()
        result = pickle.loads(data)
        if hashlib.sha256(data).hexdigest() == ref.digest:  # never remember it under a wrong one
            cls._remember(ref.digest, result)
        return result

    @classmethod
    def _remember(cls, digest: str, result: Any) -> None:
        with cls._loaded_lock:
            cls._loaded[digest] = result
            cls._loaded.move_to_end(digest)
            while len(cls._loaded) > cls._LOADED_MAX:
                cls._loaded.popitem(last=False)

    def save_failure(self, stage: str, key: str, stage_name: str, reason: str,
                     session: str | None, build_id: str) -> None:
        """Remember that ``(stage, key)`` failed deterministically (a ``StageError``)."""
        record = {"stage": stage_name, "reason": reason, "session": session,
                  "build_id": build_id}
        _atomic_write(self._failure_path(stage, key), canonical_json(record).encode())

    def lookup_failure(self, stage: str, key: str) -> dict | None:
        """The remembered deterministic failure of ``(stage, key)`` (stage, reason, session,
        build_id), or None."""
        try:
            return json.loads(self._failure_path(stage, key).read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def forget_failure(self, stage: str, key: str) -> None:
        self._failure_path(stage, key).unlink(missing_ok=True)

    def _failure_path(self, stage: str, key: str) -> Path:
        return self.root / "results" / stage / f"{key}.failed.json"

    # --- key manifests: what the latest key of (stage, session) was made of ----------------
    def save_manifest(self, stage: str, session_id: str, record: dict) -> None:
        """Remember the key manifest of the latest run of ``stage`` for ``session_id`` (key,
        parts, ok, build): what the next plan diffs the current parts against. The file is
        named by a digest of the id (ids never reach a path)."""
        _atomic_write(self._manifest_path(stage, session_id), canonical_json(record).encode())

    def latest_manifest(self, stage: str, session_id: str) -> dict | None:
        """The key manifest :meth:`save_manifest` last stored for (stage, session), or None."""
        try:
            record = json.loads(self._manifest_path(stage, session_id).read_text())
        except (OSError, ValueError):
            return None
        return record if isinstance(record, dict) else None

    def _manifest_path(self, stage: str, session_id: str) -> Path:
        name = hashlib.sha256(session_id.encode()).hexdigest()[:32]
        return self.root / "results" / stage / "latest" / f"{name}.json"

    # --- the side channel of executions -----------------------------------------------------
    def record_execution(self, **fields: Any) -> None:
        """Append one JSON line to ``executions.jsonl`` (one ``write`` on an O_APPEND fd)."""
        line = (canonical_json(fields) + "\n").encode()
        fd = os.open(self.executions_file, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
        finally:
            os.close(fd)

    def executions(self, build_id: str | None = None) -> list[dict]:
        """The recorded executions, all or of one build (a torn last line is skipped)."""
        try:
            lines = self.executions_file.read_text().splitlines()
        except FileNotFoundError:
            return []
        out = []
        needle = None if build_id is None else f'"build_id":{json.dumps(build_id)}'
        for line in lines:
            if needle is not None and needle not in line:
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            if build_id is None or rec.get("build_id") == build_id:
                out.append(rec)
        return out


class _ModulePickler(pickle.Pickler):
    """A pickler that notes the module of every class and function its output names, and the
    qualified name and field set of every dataclass and pydantic model instance in it."""

    def __init__(self, file: io.BytesIO):
        super().__init__(file, protocol=5)
        self.modules: set[str] = set()
        self.types: dict[str, list[str]] = {}

    def reducer_override(self, obj: Any) -> Any:
        named = isinstance(obj, type | types.FunctionType | types.BuiltinFunctionType)
        module = getattr(obj, "__module__", None) if named else type(obj).__module__
        if isinstance(module, str):
            self.modules.add(module)
        if not named and (fields := _field_names(type(obj))) is not None:
            self.types.setdefault(_type_name(type(obj)), fields)
        return NotImplemented


def _type_name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _field_names(cls: type) -> list[str] | None:
    """The sorted field names of a dataclass or pydantic model class; None for other types."""
    fields = getattr(cls, "__dataclass_fields__", None)
    if not isinstance(fields, dict):
        fields = getattr(cls, "__pydantic_fields__", None)
    return sorted(fields) if isinstance(fields, dict) else None


def _pickle_with_modules(result: Any) -> tuple[bytes, list[str], dict[str, list[str]]]:
    """``result`` pickled (protocol 5), the modules unpickling it imports, and the field sets
    of its dataclass and pydantic types by qualified name (``module:qualname``)."""
    buf = io.BytesIO()
    pickler = _ModulePickler(buf)
    pickler.dump(result)
    return buf.getvalue(), sorted(pickler.modules), dict(sorted(pickler.types.items()))


def type_problem(stored: object) -> str | None:
    """Why the result types a record names (``{"module:qualname": [fields]}``) do not match
    the current code: a type that is gone, or whose field set changed (a field the current
    code expects missing from the stored one, or one it no longer has); None when they all
    match. A record without the list predates it and is not trusted."""
    if not isinstance(stored, dict):
        return "its record predates the result type check"
    for name, fields in sorted(stored.items()):
        module, _, qualname = str(name).partition(":")
        try:
            obj: Any = importlib.import_module(module)
            for part in qualname.split("."):
                obj = getattr(obj, part)
        except Exception:  # noqa: BLE001 - any failure to find the type means it is gone
            return f"its type {module}.{qualname} no longer exists"
        current = _field_names(obj) if isinstance(obj, type) else None
        if current is None:
            return f"{module}.{qualname} is no longer a dataclass or pydantic model"
        if current != sorted(fields):
            missing = sorted(set(current) - set(fields))
            extra = sorted(set(fields) - set(current))
            what = ([f"lacks field(s) {', '.join(missing)}"] if missing else []) + (
                [f"has field(s) {', '.join(extra)} the code no longer has"] if extra else [])
            return f"its type {module}.{qualname} {' and '.join(what)}"
    return None


def _importable(modules: list[str] | None) -> bool:
    """True when every module a stored result needs can be imported. A record without the list
    predates it (and the tasks/ sub-package layout, whose results name modules that are gone):
    it is not trusted."""
    if not isinstance(modules, list):
        return False
    for name in modules:
        if not isinstance(name, str):
            return False
        if name in _IMPORTABLE:
            continue
        try:
            if importlib.util.find_spec(name) is None:
                return False
        except (ImportError, ValueError):
            return False
        _IMPORTABLE.add(name)
    return True


_IMPORTABLE: set[str] = set()
"""Modules :func:`_importable` found, in this process (a module found stays found)."""


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to a temporary file beside ``path``, then rename it; ENOSPC raises
    ``CatalogDiskFull`` naming ``path``."""
    with writing(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=_temp_prefix())
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


class Spill(Mapping[str, Any]):
    """Values by key, pickled into a temporary folder of the work area until they are read
    (each read unpickles again; a key whose value was None is absent). A build assembles every
    session's arrays and mesh into one and its commit reads them one session at a time, so
    the build does not hold all sessions' arrays in memory (``flows/assemble.py``). The folder
    goes when the object does; a killed process's is swept with its other temporary files."""

    def __init__(self, work: WorkArea):
        self._dir = tempfile.TemporaryDirectory(dir=work.root, prefix=_temp_prefix())
        self._files: dict[str, Path] = {}

    def put(self, key: str, value: Any) -> None:
        if value is None:
            self._files.pop(key, None)
            return
        path = Path(self._dir.name) / f"{len(self._files)}-{uuid.uuid4().hex[:8]}.pkl"
        path.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
        self._files[key] = path

    def __getitem__(self, key: str) -> Any:
        return pickle.loads(self._files[key].read_bytes())

    def __contains__(self, key: object) -> bool:
        return key in self._files

    def __iter__(self) -> Iterator[str]:
        return iter(self._files)

    def __len__(self) -> int:
        return len(self._files)


def _temp_prefix() -> str:
    return f"{TEMP_PREFIX}{socket.gethostname()}-{os.getpid()}-"


def _writer_alive(name: str) -> bool:
    """Whether the writer of temporary file ``name`` may still be writing it: True unless
    it was written on this host by a process that no longer runs."""
    host, sep, rest = name[len(TEMP_PREFIX):].rpartition("-")[0].rpartition("-")
    if not sep or host != socket.gethostname() or not rest.isdigit():
        return True
    try:
        os.kill(int(rest), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def canonical_json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
