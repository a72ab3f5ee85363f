"""What code a stage's result depends on: the part of its cache key that covers code.

A stage's result can change when any ``graspcap`` module on its path changes, or when a
third-party library that computes for it is upgraded. :func:`stage_code` finds both from the
import graph, never from a hand list:

- the stage's glue function in ``tasks/pipeline.py`` (``Stage.run``) and the module-level
  helpers and constants of that file it uses, transitively (``read_mesh``, ``_K``,
  ``final_pose`` ...): the
  glue of one stage is attributed to that stage only, so editing another stage's glue re-runs
  nothing here; the names the glue uses that the file imports lead to modules;
- every ``graspcap`` module reached from those, transitively through ``import`` and
  ``from ... import`` statements anywhere in a module (function-local imports included), with
  the ``__init__`` of every package on the way (Python runs them);
- the module of the stage's config type.

Each module is digested by its AST with every docstring and bare string statement removed and
no line numbers: comments, docstrings and formatting do not count. The versions
(``importlib.metadata``) of the libraries in :data:`COMPUTING_LIBRARIES` that those modules
import are part of it too. Everything is sorted by name (no ``id()``, no set order), so the
same code gives the same digest in every process (Dask workers); it is computed once per
process per stage, and remembered across processes in the work area by the module files'
(path, size, mtime_ns) (:func:`stage_code`): parsing ~70 modules costs a process 0.5 s idle
and ~16 s on a loaded machine, checking their stats a few ms.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.metadata
import importlib.util
import json
import sys
import threading
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import ModuleType

# RACY_S: a module file modified this recently is not trusted in a memo (git's "racily
# clean" rule), the same bound as for the input files
from graspcap.flows.workarea import RACY_S

ROOT_PACKAGE = "graspcap"
COMPUTING_LIBRARIES: dict[str, str] = {
    "open3d": "open3d", "gtsam": "gtsam", "pycolmap": "pycolmap", "numpy": "numpy",
    "scipy": "scipy", "cv2": "opencv-python-headless", "trimesh": "trimesh",
    "mediapipe": "mediapipe", "skimage": "scikit-image",
}  # fmt: skip
"""Top-level import name -> distribution, for the third-party packages that compute results
(a stage importing one gets its version in its key; I/O and orchestration libraries do not)."""

_LOCK = threading.RLock()
_OVERRIDES: dict[str, str] = {}
"""Digests to use instead of the computed ones (``module name -> digest``, or
``lib:<import name> -> version``); for tests that fake a code change or a library upgrade."""


@dataclass(frozen=True)
class StageCode:
    """The code part of one stage's key: digests by module (the glue as
    ``<module>:<function>``) and versions by library, both sorted by name."""

    modules: tuple[tuple[str, str], ...]
    libraries: tuple[tuple[str, str], ...]

    @functools.cached_property
    def digest(self) -> str:
        return hashlib.sha256(json.dumps([self.modules, self.libraries]).encode()).hexdigest()

    def as_dict(self) -> dict[str, dict[str, str]]:
        return {"modules": dict(self.modules), "libraries": dict(self.libraries)}


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    """``tree`` without bare string statements (docstrings, attribute docstrings)."""
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if not isinstance(body, list):
            continue
        kept = [s for s in body if not (isinstance(s, ast.Expr) and isinstance(
            s.value, ast.Constant) and isinstance(s.value.value, str))]
        if len(kept) != len(body):
            node.body = kept or [ast.Pass()]
    return tree


def ast_digest(tree: ast.AST) -> str:
    """sha256 of a parsed tree without docstrings, comments, line numbers or formatting."""
    return hashlib.sha256(
        ast.dump(_strip_docstrings(tree), include_attributes=False).encode()).hexdigest()


def _source(name: str) -> tuple[bytes, bool] | None:
    """The source of module ``name`` and whether it is a package; None when it has none."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin).read_bytes(), spec.submodule_search_locations is not None


@cache
def _parsed(name: str) -> tuple[ast.Module, bool] | None:
    """The AST of module ``name`` and whether it is a package; None when it has no source."""
    found = _source(name)
    return None if found is None else (ast.parse(found[0]), found[1])


@cache
def _module_digest(name: str) -> str:
    parsed = _parsed(name)
    return "no-source" if parsed is None else ast_digest(parsed[0])


def module_digest(name: str) -> str:
    """The AST digest of one module (an override when a test set one)."""
    return _OVERRIDES.get(name) or _module_digest(name)


@cache
def _is_module(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def _resolve(base: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    parts = base.split(".")
    parts = parts if is_package else parts[:-1]
    parts = parts[: len(parts) - (node.level - 1)]
    return ".".join(parts + ([node.module] if node.module else []))


@cache
def _imports(name: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The ``graspcap`` modules and the top-level third-party names module ``name`` imports
    (anywhere in it), sorted."""
    parsed = _parsed(name)
    if parsed is None:
        return (), ()
    tree, is_package = parsed
    ours: set[str] = set()
    others: set[str] = set()

    def note(module: str) -> None:
        if module == ROOT_PACKAGE or module.startswith(ROOT_PACKAGE + "."):
            ours.add(module)
        elif module:
            others.add(module.split(".")[0])

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                note(alias.name)
        elif isinstance(node, ast.ImportFrom):
            module = _resolve(name, is_package, node)
            note(module)
            if module.startswith(ROOT_PACKAGE):
                for alias in node.names:  # ``from pkg import submodule``
                    if alias.name != "*" and _is_module(f"{module}.{alias.name}"):
                        ours.add(f"{module}.{alias.name}")
    return tuple(sorted(ours)), tuple(sorted(others))


def _closure(roots: set[str]) -> tuple[set[str], set[str]]:
    """Every ``graspcap`` module reached from ``roots`` (with their parent packages) and the
    third-party top-level names they import."""
    seen: set[str] = set()
    libs: set[str] = set()
    todo = sorted(roots)
    while todo:
        name = todo.pop()
        if name in seen or not _is_module(name):
            continue
        seen.add(name)
        parts = name.split(".")
        parents = [".".join(parts[:i]) for i in range(1, len(parts))]
        ours, others = _imports(name)
        libs.update(others)
        todo.extend(m for m in (*ours, *parents) if m not in seen)
    return seen, libs


def _definitions(tree: ast.Module) -> dict[str, ast.AST]:
    """The module-level functions, classes and simple assignments of a module, by name."""
    out: dict[str, ast.AST] = {}
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            out[node.name] = node
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            for target in targets:
                if isinstance(target, ast.Name):
                    out[target.id] = node
    return out


def _glue(func) -> tuple[str, str, set[str], set[str]]:
    """The glue function ``func`` and the module-level definitions of its file that it uses
    (helpers, constants), transitively: (``module:function``, digest of their ASTs, the
    ``graspcap`` modules and third-party names its names lead to). A function that is not
    defined at module level (a lambda) counts its whole module instead."""
    module: ModuleType = sys.modules[func.__module__]
    tree = _parsed(module.__name__)[0]
    defs = _definitions(tree)
    glue_name = f"{module.__name__}:{func.__name__}"
    if func.__name__ not in defs or func.__name__ == "<lambda>":
        return glue_name, "", {module.__name__}, set()
    ours: set[str] = set()
    libs: set[str] = set()
    used: list[str] = []
    todo = [func.__name__]
    while todo:
        fname = todo.pop()
        if fname in used:
            continue
        used.append(fname)
        params: set[str] = set()
        if isinstance(defs[fname], ast.FunctionDef | ast.AsyncFunctionDef):
            args = defs[fname].args  # a parameter named like a module is not that module
            params = {a.arg for a in [*args.posonlyargs, *args.args, *args.kwonlyargs,
                                      *filter(None, [args.vararg, args.kwarg])]}
        for node in ast.walk(defs[fname]):
            if not isinstance(node, ast.Name) or node.id in params:
                continue
            if node.id in defs:
                todo.append(node.id)
                continue
            value = vars(module).get(node.id)
            origin = (value.__name__ if isinstance(value, ModuleType)
                      else getattr(value, "__module__", None))
            if not isinstance(origin, str) or origin == module.__name__:
                continue
            if origin.startswith(ROOT_PACKAGE):
                ours.add(origin)
            else:
                libs.add(origin.split(".")[0])
    h = hashlib.sha256()
    for fname in sorted(used):
        h.update(f"{fname}={ast_digest(defs[fname])}\0".encode())
    return glue_name, h.hexdigest(), ours, libs


def library_version(name: str) -> str:
    """The installed version of a computing library (an override when a test set one)."""
    if (fake := _OVERRIDES.get(f"lib:{name}")) is not None:
        return fake
    return _installed_version(COMPUTING_LIBRARIES[name])


@cache
def _installed_version(distribution: str) -> str:
    """``importlib.metadata.version``, once per process (it scans every installed
    distribution: ~10 ms a call on a loaded machine, 92 calls a build's 14 stages)."""
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return "absent"


_STAGE_CODE: dict[str, StageCode] = {}
CODE_MEMO_FORMAT = 1
MEMO_ENABLED = True
"""False: never read or write the cross-process memo (tests that hand the digest an edited
source in memory, which the files' stats cannot show)."""


def stage_code(stage, memo_dir: Path | None = None, write: bool = True) -> StageCode:
    """The code part of ``stage``'s key (a ``tasks.pipeline.Stage``), once per process.

    ``memo_dir`` (the work area's ``digests/``): the result is also remembered there across
    processes (``code-<stage>.json``), with the (path, size, mtime_ns) of every module file
    it digested and the mtime_ns of every folder holding one (a module added or removed
    changes its folder's). A new process takes it when every one of those is as recorded, so
    it parses nothing; the libraries' versions are looked up again. Not remembered while a
    test's :func:`override` is set, nor when a file was modified less than ``RACY_S`` before
    (git's rule); ``write=False`` reads a memo but writes none (``graspcap build --plan``).
    The known risk (as Make's, git's): a module rewritten with the same size and mtime_ns."""
    with _LOCK:
        if (found := _STAGE_CODE.get(stage.name)) is not None:
            return found
        use_memo = MEMO_ENABLED and memo_dir is not None and not _OVERRIDES
        glue_fn = f"{stage.run.__module__}:{getattr(stage.run, '__qualname__', '')}"
        config_module = type(stage.presets["default"]).__module__
        memo = Path(memo_dir) / f"code-{stage.name}.json" if use_memo else None
        code = _remembered(memo, glue_fn, config_module) if memo is not None else None
        if code is None:
            glue_name, glue_digest, roots, libs = _glue(stage.run)
            roots.add(config_module)
            modules, more = _closure(roots)
            libs |= more
            glue = [(glue_name, _OVERRIDES.get(glue_name) or glue_digest)] if glue_digest else []
            names = sorted(lib for lib in libs if lib in COMPUTING_LIBRARIES)
            code = StageCode(
                modules=tuple(sorted([*glue, *((m, module_digest(m)) for m in modules)])),
                libraries=tuple((lib, library_version(lib)) for lib in names),
            )
            if memo is not None and write:
                _remember(memo, glue_fn, config_module, code, sorted(modules))
        _STAGE_CODE[stage.name] = code
        return code


def _stamps(modules: list[str]) -> tuple[list, list] | None:
    """(module, path, size, mtime_ns) of each module's file and (path, mtime_ns) of each folder
    holding one; None when one is modified less than ``RACY_S`` ago or cannot be stat'ed."""
    import os
    import time

    files, folders = [], {}
    now = time.time_ns()
    for name in modules:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.origin or not spec.origin.endswith(".py"):
            continue
        try:
            st = os.stat(spec.origin)
            folder = os.path.dirname(spec.origin)
            folders[folder] = os.stat(folder).st_mtime_ns
        except OSError:
            return None
        if now - max(st.st_mtime_ns, folders[folder]) < RACY_S * 1e9:
            return None
        files.append([name, spec.origin, st.st_size, st.st_mtime_ns])
    return files, sorted([k, v] for k, v in folders.items())


def _origin(name: str) -> str | None:
    """The file module ``name`` is (or would be) imported from in this process."""
    module = sys.modules.get(name)
    spec = getattr(module, "__spec__", None) if module is not None else None
    if spec is None:
        spec = importlib.util.find_spec(name)
    return spec.origin if spec is not None else None


def _remember(memo: Path, glue_fn: str, config_module: str, code: StageCode,
              modules: list[str]) -> None:
    from graspcap.flows.workarea import _atomic_write

    stamps = _stamps(modules)
    if stamps is None:
        return
    record = {"format": CODE_MEMO_FORMAT, "glue": glue_fn, "config_module": config_module,
              "python": sys.version, "files": stamps[0], "folders": stamps[1],
              "modules": [list(m) for m in code.modules],
              "libraries": [name for name, _ in code.libraries]}
    try:
        memo.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write(memo, json.dumps(record, separators=(",", ":")).encode())
    except OSError:
        pass  # an aid: the next process digests the modules again


def _remembered(memo: Path, glue_fn: str, config_module: str) -> StageCode | None:
    """The memo's :class:`StageCode` when every file and folder it names is as recorded."""
    import os

    try:
        record = json.loads(memo.read_bytes())
        if (record.get("format"), record.get("glue"), record.get("config_module"),
                record.get("python")) != (CODE_MEMO_FORMAT, glue_fn, config_module,
                                          sys.version):
            return None
        for name, path, size, mtime_ns in record["files"]:
            if _origin(name) != path:  # another checkout's file: not this process's code
                return None
            st = os.stat(path)
            if (st.st_size, st.st_mtime_ns) != (size, mtime_ns):
                return None
        for path, mtime_ns in record["folders"]:
            if os.stat(path).st_mtime_ns != mtime_ns:
                return None
        return StageCode(
            modules=tuple((str(m), str(d)) for m, d in record["modules"]),
            libraries=tuple((lib, library_version(lib)) for lib in record["libraries"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def override(name: str, value: str | None) -> None:
    """Use ``value`` as the digest of module ``name`` (or, for ``lib:<import name>``, as that
    library's version) from now on in this process; None removes the override. For tests
    that fake a changed helper or an upgraded library without editing installed files."""
    with _LOCK:
        if value is None:
            _OVERRIDES.pop(name, None)
        else:
            _OVERRIDES[name] = value
        _STAGE_CODE.clear()


def forget() -> None:
    """Compute every stage's code again (after module files changed in this process)."""
    with _LOCK:
        _STAGE_CODE.clear()
        _parsed.cache_clear()
        _module_digest.cache_clear()
        _imports.cache_clear()
        _is_module.cache_clear()
