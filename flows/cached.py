"""One stage run through the work area's cache (no Prefect here; the ``@task`` wraps this).

The cache key of a stage run is ours, not Prefect's::

    key = sha256(stage.version, config.digest(),
                 digests of the bytes of the session files in ``stage.reads``,
                 canonical JSON of the ``session.json`` fields in ``stage.fields``,
                 code digest (``flows/code_digest.py``: the AST of every graspcap module on
                 the stage's import path and its glue, versions of computing libraries),
                 content digests of the upstream results but ``load_session``'s)

A stage reads the session only through its roles and fields (the session its glue gets
raises on any other manifest field: ``manifest_guard.restricted``), so ``load_session``'s result
digest, which changes with every file, is in no downstream key.

so a changed algorithm (its code, or its ``STAGE_VERSION`` for what the code cannot show), a
changed library, a changed parameter, a changed input file or a changed upstream result each
give a new key, and nothing else does. On a hit the stored
:class:`ResultRef` is returned and no stage body runs; on a miss the stage runs, its result is
stored and every attempt is appended to ``executions.jsonl``.

A :class:`StageError` is deterministic, so it is remembered under the key too, and a later run
with the same key raises it again without running the stage body (an unchanged rebuild of a
failed session runs nothing). ``replay_failures=False`` (``--retry-failed``) runs it again.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import os
import re
import stat
import threading
import time
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated

from graspcap.flows.code_digest import stage_code
from graspcap.flows.workarea import ResultRef, WorkArea, _atomic_write, is_racy
from graspcap.schemas.session import DEFAULT_LIMITS, SESSION_ID_RE, SessionManifest
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.session.files import JsonSyntaxError, load_json
from graspcap.tasks.session.load_session import MANIFEST, Session

_FILES: OrderedDict[str, dict[str, list[Path]]] = OrderedDict()
"""File lists by role, remembered per manifest identity or ``load_session`` result digest:
listing them resolves every path (~130 per session, measured 0.2 s a session under load), and
every stage task of every build needs the list for its key."""
_FILES_LOCK = threading.Lock()
_FILES_MAX = 512


def _remembered(key: str, make) -> dict[str, list[Path]] | None:
    with _FILES_LOCK:
        if key in _FILES:
            _FILES.move_to_end(key)
            return {role: list(paths) for role, paths in _FILES[key].items()}
    files = make()
    if files is not None:
        with _FILES_LOCK:
            _FILES[key] = files
            while len(_FILES) > _FILES_MAX:
                _FILES.popitem(last=False)
        files = {role: list(paths) for role, paths in files.items()}
    return files


def _listing(session_dir: Path, names: bool) -> dict[str, list] | None:
    """The files of a session by role, read from its manifest without validating the session:
    resolved paths, or (``names``) the names the manifest gives; None when the manifest cannot
    say (then ``load_session`` runs and reports why). Remembered by the manifest's (path,
    size, mtime_ns, inode)."""

    def make():
        raw = _manifest(Path(session_dir))
        if not isinstance(raw, dict):
            return None
        try:  # the model bounds count and views, so listing the files is bounded too
            manifest = SessionManifest.model_validate(raw)
            if names:
                from graspcap.flows.session_roles import manifest_names

                return manifest_names(manifest)
            return Session(Path(session_dir).resolve(), manifest).input_files()
        except Exception:  # noqa: BLE001 - anything wrong here is load_session's to report
            return None

    try:
        path = os.path.abspath(Path(session_dir) / MANIFEST)
        st = os.stat(path)
    except OSError:
        return None
    kind = "n" if names else "m"
    return _remembered(f"{kind}|{path}|{st.st_size}|{st.st_mtime_ns}|{st.st_ino}", make)


def session_files(session_dir: Path) -> dict[str, list[Path]] | None:
    """The files of a session by role, resolved (:func:`_listing`)."""
    return _listing(session_dir, names=False)


def session_names(session_dir: Path) -> dict[str, list[str]] | None:
    """The files of a session by role, as the manifest names them (:func:`_listing`)."""
    return _listing(session_dir, names=True)


def loaded_session_files(ref: ResultRef, work: WorkArea | None = None
                         ) -> dict[str, list[Path]]:
    """The files of the session a ``load_session`` result holds, remembered by its digest:
    in this process, and with ``work`` in its ``digests/files-<digest>.json`` for the next
    process (content-addressed: a result's digest names its file list, so the memo cannot go
    stale; it spares a new process unpickling every session's result, ~23 ms a session under
    load). A read-only work area (``--plan``) reads the memo and writes none."""

    def make() -> dict[str, list[Path]]:
        memo = None if work is None else work.root / "digests" / f"files-{ref.digest}.json"
        if memo is not None:
            try:
                raw = json.loads(memo.read_bytes())
                return {str(role): [Path(p) for p in paths]
                        for role, paths in raw["files"].items()}
            except (OSError, ValueError, KeyError, TypeError, AttributeError):
                pass
        files = WorkArea.load(ref).input_files()
        if memo is not None and not work.readonly:
            try:
                _atomic_write(memo, json.dumps({"files": {
                    role: [str(p) for p in paths] for role, paths in files.items()}}).encode())
            except OSError:
                pass  # an aid: the next process unpickles the result
        return files

    return _remembered(f"r|{ref.digest}", make)


def _manifest(session_dir: Path) -> object | JsonSyntaxError:
    """The parsed ``session.json`` of a session, read as the validator reads it: a regular
    file only (never a FIFO), within the size and nesting limits; never raises."""
    return load_json(Path(session_dir) / MANIFEST, DEFAULT_LIMITS.max_manifest_bytes,
                     DEFAULT_LIMITS.max_json_depth)


def session_id_of(session_dir: Path) -> str:
    """The manifest's ``session_id`` when it is a valid id (the contract's character set and
    length), else the folder name: a manifest that cannot be read (not a regular file, too
    large, nested too deep, bad JSON) or an invalid id never raises here, and never reaches a
    path; ``load_session`` then fails that session naming the file and field. Never raises."""
    raw = _manifest(Path(session_dir))
    sid = raw.get("session_id") if isinstance(raw, dict) else None
    if isinstance(sid, str) and re.search(SESSION_ID_RE, sid):
        return sid
    return Path(session_dir).name


def stage_key(version: str, config: StageConfig, reads_digest: str,
              upstream: Mapping[str, ResultRef], code_digest: str = "") -> str:
    """The cache key of one stage run (module docstring)."""
    h = hashlib.sha256()
    for part in (version, _config_digest(config), reads_digest, code_digest):
        h.update(part.encode())
        h.update(b"\0")
    for name in sorted(upstream):
        h.update(f"{name}={upstream[name].digest}\0".encode())
    return h.hexdigest()


_CONFIG_DIGESTS: dict[int, tuple[StageConfig, str]] = {}
"""``config.digest()`` by the config object's id, the object kept so its id is not reused: a
build keys every stage of every session with the same few (frozen) configs."""


def _config_digest(config: StageConfig) -> str:
    found = _CONFIG_DIGESTS.get(id(config))
    if found is not None and found[0] is config:
        return found[1]
    digest = config.digest()
    with _FILES_LOCK:
        if len(_CONFIG_DIGESTS) >= _FILES_MAX:
            _CONFIG_DIGESTS.clear()
        _CONFIG_DIGESTS[id(config)] = (config, digest)
    return digest


class NotARegularFile(OSError):
    """A session file that is a directory, FIFO, device or socket: never opened for a digest
    (a FIFO would block the read forever); ``load_session`` reports it."""


def _regular(paths: list[Path]) -> list[Path]:
    """``paths``, after an ``os.stat`` of each shows a regular file; raises
    :class:`NotARegularFile` (or the stat's ``OSError``) otherwise."""
    for path in paths:
        mode = os.stat(path).st_mode
        if not stat.S_ISREG(mode):
            code = errno.EISDIR if stat.S_ISDIR(mode) else errno.EINVAL
            raise NotARegularFile(code, "not a regular file", str(path))
    return paths


def reads_digest(work: WorkArea, files: Mapping[str, list[Path]], roles: tuple[str, ...],
                 role_digests: dict[str, str] | None = None) -> str:
    """Digest of the bytes of every file of ``roles`` (role names and file order kept);
    ``role_digests`` (role -> digest) is filled and reused when given (one session's stages
    share their roles within one planning pass). Raises ``OSError`` (never blocks) when a
    file is missing or not a regular file."""
    h = hashlib.sha256()
    for role in roles:
        if role_digests is None or role not in role_digests:
            paths = _regular(list(files.get(role, [])))
            digest = (work.files_digest(paths) if role != MANIFEST_ROLE else _digest_of(
                [(str(p), manifest_digest(work, p)) for p in paths]))
            if role_digests is not None:
                role_digests[role] = digest
        else:
            digest = role_digests[role]
        h.update(f"{role}:{digest}\0".encode())
    return h.hexdigest()


MANIFEST_ROLE = "manifest"
"""The role of ``session.json``: digested by meaning (:func:`manifest_digest`), not bytes."""
_MANIFEST_DIGESTS: OrderedDict[str, str] = OrderedDict()


def _digest_of(pairs: list[tuple[str, str]]) -> str:
    h = hashlib.sha256()
    for name, digest in pairs:
        h.update(name.encode())
        h.update(digest.encode())
    return h.hexdigest()


def manifest_digest(work: WorkArea, path: Path) -> str:
    """sha256 of ``session.json`` as canonical JSON (keys sorted, no whitespace), so
    re-indenting or re-ordering it changes no key; its byte digest when it does not parse
    (then ``load_session`` reports why). Remembered by (path, size, mtime_ns, inode)."""
    try:
        st = os.stat(path)
    except OSError:
        return work.file_digest(path)
    ident = f"{os.path.abspath(path)}|{st.st_size}|{st.st_mtime_ns}|{st.st_ino}"
    with _FILES_LOCK:
        if (found := _MANIFEST_DIGESTS.get(ident)) is not None:
            return found
    raw = load_json(Path(path), DEFAULT_LIMITS.max_manifest_bytes, DEFAULT_LIMITS.max_json_depth)
    if isinstance(raw, JsonSyntaxError):
        return work.file_digest(path)
    digest = hashlib.sha256(("json:" + json.dumps(
        raw, sort_keys=True, separators=(",", ":"), ensure_ascii=False)).encode()).hexdigest()
    if is_racy(st.st_mtime_ns):
        return digest  # may change again within the same mtime tick: not remembered
    with _FILES_LOCK:
        _MANIFEST_DIGESTS[ident] = digest
        while len(_MANIFEST_DIGESTS) > _FILES_MAX:
            _MANIFEST_DIGESTS.popitem(last=False)
    return digest


def cache_key(stage_name: str, session_dir: Path | str, config: StageConfig,
              upstream: Mapping[str, ResultRef], work: WorkArea,
              role_digests: dict[str, str] | None = None) -> str | None:
    """The cache key of ``stage_name`` for one session given its upstream refs (those of
    ``Stage.key_upstream``: ``load_session``'s is not needed); None when the session's files
    cannot be listed or one is missing (then the stage runs, uncached, and ``load_session``
    reports what is wrong)."""
    from graspcap.tasks.pipeline import STAGES

    stage = STAGES[stage_name]
    known = role_digests is not None and all(r in role_digests for r in stage.reads)
    files = {} if known else _stage_files(stage_name, session_dir, upstream, work)
    fields = manifest_fields(Path(session_dir), stage.fields)
    if files is None or fields is None:
        return None
    try:
        reads = reads_digest(work, files, stage.reads, role_digests)
    except OSError:  # missing, not a regular file, a symlink loop: load_session says which
        return None
    return stage_key(stage.version, config, f"{reads}:{_fields_digest(fields)}",
                     {k: upstream[k] for k in stage.key_upstream}, _code(stage, work).digest)


_ABSENT = {"(absent)": True}
"""A declared manifest field the manifest does not hold, in a key."""
_MANIFESTS: OrderedDict[str, object] = OrderedDict()


def _parsed_manifest(session_dir: Path) -> dict | None:
    """The parsed ``session.json`` (None when it is not a JSON object), remembered by (path,
    size, mtime_ns, inode) as :func:`manifest_digest` is."""
    path = os.path.abspath(Path(session_dir) / MANIFEST)
    try:
        st = os.stat(path)
    except OSError:
        return None
    ident = f"{path}|{st.st_size}|{st.st_mtime_ns}|{st.st_ino}"
    with _FILES_LOCK:
        if ident in _MANIFESTS:
            found = _MANIFESTS[ident]
            return found if isinstance(found, dict) else None
    raw = _manifest(Path(session_dir))
    if not is_racy(st.st_mtime_ns):
        with _FILES_LOCK:
            _MANIFESTS[ident] = raw
            while len(_MANIFESTS) > _FILES_MAX:
                _MANIFESTS.popitem(last=False)
    return raw if isinstance(raw, dict) else None


@functools.cache
def _label_type(name: str):
    """A pydantic ``TypeAdapter`` of the manifest field ``name`` (its type and constraints)."""
    from pydantic import TypeAdapter

    info = SessionManifest.model_fields[name]
    return TypeAdapter(Annotated[info.annotation, *info.metadata])


def _label_key(name: str, value: object) -> object:
    """A label (``pipeline.LABEL_FIELDS``) as ``load_session``'s key takes it: only that it is
    valid (no stage reads it), or the value itself when it is not (its problem line names it)."""
    from pydantic import ValidationError

    try:
        _label_type(name).validate_python(value)
    except ValidationError:
        return value
    return "(a valid label)"


def manifest_fields(session_dir: Path, fields: tuple[str, ...]) -> dict[str, object] | None:
    """The values of the manifest ``fields`` (dotted paths) a stage's key takes, as parsed
    from the session's current ``session.json``, with ``session_id`` (every stage may read it,
    ``manifest_guard.ALWAYS_FIELDS``); a field the manifest lacks is ``_ABSENT``. ``("*",)``:
    every top-level field, labels by validity only (:func:`_label_key`). None when the
    manifest is not a JSON object."""
    from graspcap.tasks.pipeline import LABEL_FIELDS, WHOLE_MANIFEST
    from graspcap.tasks.session.manifest_guard import ALWAYS_FIELDS

    raw = _parsed_manifest(session_dir)
    if raw is None:
        return None
    if tuple(fields) == WHOLE_MANIFEST:
        return {k: _label_key(k, v) if k in LABEL_FIELDS else v for k, v in raw.items()}
    out: dict[str, object] = {}
    for name in (*ALWAYS_FIELDS, *fields):
        value: object = raw
        for part in name.split("."):
            value = value.get(part, _ABSENT) if isinstance(value, dict) else _ABSENT
        out[name] = value
    return out


def _canonical(value: object) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=False)


def _fields_digest(fields: Mapping[str, object]) -> str:
    return hashlib.sha256(("fields:" + _canonical(dict(fields))).encode()).hexdigest()


def _stage_files(stage_name: str, session_dir: Path | str,
                 upstream: Mapping[str, ResultRef], work: WorkArea | None = None
                 ) -> dict[str, list[Path]] | None:
    if stage_name == "load_session" or "load_session" not in upstream:
        return session_files(Path(session_dir))
    return loaded_session_files(upstream["load_session"], work)


def key_parts(stage_name: str, session_dir: Path | str, config: StageConfig,
              upstream: Mapping[str, ResultRef], work: WorkArea) -> dict | None:
    """What the key of ``stage_name`` is made of, for a person (the key manifest): the
    stage version, the config's fields, the digest of every file it reads by role (names
    relative to the session), the digest of every module of its code, the versions of its
    libraries, and the digests of the upstream results given (all of them, or some when a plan
    does not know the others). None when the session's files cannot be listed or read."""
    from graspcap.tasks.pipeline import STAGES

    stage = STAGES[stage_name]
    files = _stage_files(stage_name, session_dir, upstream, work)
    fields = manifest_fields(Path(session_dir), stage.fields)
    if files is None or fields is None:
        return None
    base = Path(session_dir).resolve()
    try:
        by_role = {role: {_relative(p, base): (manifest_digest(work, p) if role == MANIFEST_ROLE
                                               else work.file_digest(p))
                          for p in _regular(list(files.get(role, [])))}
                   for role in stage.reads}
    except OSError:
        return None
    return {"version": stage.version, "config": json.loads(config.canonical_json()),
            "files": by_role,
            "fields": {k: hashlib.sha256(_canonical(v).encode()).hexdigest()[:16]
                       for k, v in fields.items()},
            **_code(stage, work).as_dict(),
            "upstream": {k: upstream[k].digest for k in stage.key_upstream if k in upstream}}


def _code(stage, work: WorkArea):
    """``stage_code`` remembered in the work area's ``digests/`` across processes (read only
    for a read-only work area)."""
    return stage_code(stage, work.root / "digests", write=not work.readonly)


def _relative(path: Path, base: Path) -> str:
    try:
        return str(Path(path).relative_to(base))
    except ValueError:
        return str(path)


REASONS = ("new session", "not run before", "changed input file", "changed config", "changed code",
           "changed library", "changed stage version", "upstream changed", "failed last time",
           "stored result unusable", "stored result gone")
"""The reasons a plan gives for a stage that runs, in the order its summary counts them."""


def diff_parts(old: Mapping, new: Mapping) -> list[tuple[str, str]]:
    """Why the key made of ``new`` differs from the one made of ``old`` (key manifests):
    (reason, detail) pairs, a reason from :data:`REASONS`; parts ``new`` lacks (an upstream
    digest a plan does not know) are not compared."""
    out: list[tuple[str, str]] = []
    if old.get("version") != new.get("version"):
        out.append(("changed stage version", f"{old.get('version')} -> {new.get('version')}"))
    for field in _changed_fields(old.get("config"), new.get("config")):
        out.append(("changed config", field))
    old_files, new_files = old.get("files") or {}, new.get("files") or {}
    for role in sorted(set(old_files) | set(new_files)):
        was, now = old_files.get(role) or {}, new_files.get(role) or {}
        for name in sorted(set(was) | set(now)):
            if was.get(name) != now.get(name):
                what = "new" if name not in was else "gone" if name not in now else "changed"
                out.append(("changed input file", f"{role}: {name} ({what})"))
    old_fields, new_fields = old.get("fields") or {}, new.get("fields") or {}
    for name in sorted(set(old_fields) | set(new_fields)):
        if old_fields.get(name) != new_fields.get(name):
            out.append(("changed input file", f"{MANIFEST}: field {name}"))
    old_code, new_code = old.get("modules") or {}, new.get("modules") or {}
    for module in sorted(set(old_code) | set(new_code)):
        if old_code.get(module) != new_code.get(module):
            what = ("new" if module not in old_code else "no longer used"
                    if module not in new_code else "changed")
            out.append(("changed code", f"{module}" + ("" if what == "changed" else f" ({what})")))
    old_libs, new_libs = old.get("libraries") or {}, new.get("libraries") or {}
    for lib in sorted(set(old_libs) | set(new_libs)):
        if old_libs.get(lib) != new_libs.get(lib):
            out.append(("changed library",
                        f"{lib} {old_libs.get(lib, 'absent')} -> {new_libs.get(lib, 'absent')}"))
    old_up = old.get("upstream") or {}
    for name, digest in sorted((new.get("upstream") or {}).items()):
        if old_up.get(name) != digest:
            out.append(("upstream changed", name))
    return out


def _changed_fields(old: object, new: object, prefix: str = "") -> list[str]:
    """The dotted names of the config fields that differ between two config dumps."""
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new)):
            out += _changed_fields(old.get(k), new.get(k), f"{prefix}{k}.")
        return out
    return [] if old == new else [prefix.rstrip(".") or "(whole config)"]


def lookup_cached(stage_name: str, session_dir: Path | str, config: StageConfig,
                  upstream: Mapping[str, ResultRef], work: WorkArea, replay_failures: bool = True,
                  role_digests: dict[str, str] | None = None) -> ResultRef | StageError | None:
    """What the work area already holds for this stage run, without running anything: its
    stored result, its remembered deterministic failure (when ``replay_failures``), or None."""
    key = cache_key(stage_name, session_dir, config, upstream, work, role_digests)
    return _held(stage_name, key, work, replay_failures)


def _held(stage_name: str, key: str | None, work: WorkArea,
          replay_failures: bool) -> ResultRef | StageError | None:
    """The stored result under ``key``, its remembered failure (when ``replay_failures``), or
    None (also when there is no trustworthy key)."""
    if key is None:
        return None
    if (ref := work.lookup(stage_name, key)) is not None:
        return ref
    if replay_failures and (failure := work.lookup_failure(stage_name, key)) is not None:
        return StageError(failure["stage"], failure["reason"], session=failure["session"])
    return None


def _cpu_clocks() -> tuple[float, float]:
    return time.process_time(), time.thread_time()


def _cpu_since(clocks: tuple[float, float]) -> dict:
    """CPU seconds of a stage body for its execution record: ``cpu_s`` of the whole process
    (with any native pool threads, and with whatever else the process ran meanwhile: another
    session's thread in the thread-pool runner, Prefect's and Dask's background threads) and
    ``thread_cpu_s`` of the body's own thread; ``pid`` says which process ran it."""
    return {"cpu_s": round(time.process_time() - clocks[0], 4),
            "thread_cpu_s": round(time.thread_time() - clocks[1], 4), "pid": os.getpid()}


def run_cached(stage_name: str, session_dir: Path | str, session_id: str, config: StageConfig,
               upstream: Mapping[str, ResultRef], work: WorkArea, build_id: str,
               replay_failures: bool = True) -> ResultRef:
    """The result of ``stage_name`` for one session: from the work area, or run and stored;
    a remembered deterministic failure is raised again unless ``replay_failures`` is False."""
    from graspcap.tasks.pipeline import STAGES, run_stage  # heavy: stage modules

    stage = STAGES[stage_name]
    missing = set(stage.upstream) - set(upstream)
    if missing:
        raise ValueError(f"{stage_name}: upstream results missing: {sorted(missing)}")
    key = cache_key(stage_name, session_dir, config, upstream, work)
    held = _held(stage_name, key, work, replay_failures)
    if isinstance(held, StageError):
        raise held
    if held is not None:
        return held
    parts = key_parts(stage_name, session_dir, config, upstream, work) if key else None
    why = run_reasons(work, stage_name, session_id, key, parts, replay_failures)
    results = {k: WorkArea.load(upstream[k]) for k in stage.upstream}
    t0, clocks = time.perf_counter(), _cpu_clocks()
    record = {"stage": stage_name, "session_id": session_id, "key": key, "build_id": build_id,
              "why": [f"{reason}: {detail}" if detail else reason for reason, detail in why]}
    try:
        result = run_stage(stage, session_dir, config, results)
    except BaseException as exc:
        work.record_execution(**record, seconds=round(time.perf_counter() - t0, 4), ok=False,
                              error=f"{type(exc).__name__}: {exc}"[:2000], **_cpu_since(clocks))
        if key is not None and isinstance(exc, StageError):
            work.save_failure(stage_name, key, exc.stage, exc.reason, exc.session, build_id)
            work.save_manifest(stage_name, session_id, {"key": key, "parts": parts, "ok": False,
                                                        "build_id": build_id})
        raise
    seconds = round(time.perf_counter() - t0, 4)
    work.record_execution(**record, seconds=seconds, ok=True, error=None, **_cpu_since(clocks))
    if key is None:  # no trustworthy key: never stored, but handed on
        key = "uncached-" + hashlib.sha256(f"{session_dir}{time.time_ns()}".encode()).hexdigest()
    ref = work.save(stage_name, key, result, build_id, seconds=seconds)
    if parts is not None:
        work.save_manifest(stage_name, session_id, {"key": key, "parts": parts, "ok": True,
                                                    "build_id": build_id})
    if not replay_failures:
        work.forget_failure(stage_name, key)
    return ref


def first_run(work: WorkArea, session_id: str) -> tuple[str, str]:
    """Why a stage with no key manifest for ``session_id`` runs: "new session", or "not run
    before" when the session's ``load_session`` ran (an upstream failed until now)."""
    seen = work.latest_manifest("load_session", session_id) is not None
    return ("not run before", "") if seen else ("new session", "")


def run_reasons(work: WorkArea, stage_name: str, session_id: str, key: str | None,
                parts: dict | None, replay_failures: bool = True) -> list[tuple[str, str]]:
    """Why ``stage_name`` must run for ``session_id`` under ``key`` (its result is not held):
    (reason, detail) pairs from :data:`REASONS`, found by diffing ``parts`` against the key
    manifest of the stage's latest run for the session. Reads only."""
    if key is None or parts is None:
        return [("changed input file", "the session's files cannot all be read")]
    out: list[tuple[str, str]] = []
    _, note = work.check(stage_name, key)
    if note:
        out.append(("stored result unusable", note))
    if not replay_failures and (failure := work.lookup_failure(stage_name, key)):
        out.append(("failed last time", str(failure.get("reason", ""))))
    latest = work.latest_manifest(stage_name, session_id)
    if latest is None:
        return out or [first_run(work, session_id)]
    if latest.get("key") != key:
        out += diff_parts(latest.get("parts") or {}, parts)
    if not out:
        out.append(("stored result gone", f"{stage_name} result of build "
                                          f"{latest.get('build_id')} is no longer stored"))
    return out
