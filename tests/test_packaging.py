"""Packaging and layering: one import root, and Prefect only inside flows/."""

from __future__ import annotations

import ast
import fcntl
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.conftest import REPO

PREFECT_FREE = ["tasks", "schemas", "catalog", "graspcap"]


def _imports_prefect(path: Path) -> list[int]:
    tree = ast.parse(path.read_text(), filename=str(path))
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names = [node.module or ""]
        else:
            continue
        if any(n == "prefect" or n.startswith(("prefect.", "prefect_")) for n in names):
            lines.append(node.lineno)
    return lines


def test_prefect_is_imported_only_in_flows():
    offenders = []
    for folder in PREFECT_FREE:
        for path in sorted((REPO / folder).rglob("*.py")):
            offenders += [f"{path.relative_to(REPO)}:{n}" for n in _imports_prefect(path)]
    assert not offenders, f"prefect imported outside flows/: {offenders}"


def test_the_scanner_sees_a_prefect_import(tmp_path):
    bad = tmp_path / "x.py"
    bad.write_text("import os\nfrom prefect import task\n")
    assert _imports_prefect(bad) == [2]


def test_stage_modules_do_not_pull_in_prefect_at_run_time():
    code = (
        "import importlib, pkgutil, sys\n"
        "import graspcap.tasks, graspcap.schemas, graspcap.catalog\n"
        "for pkg in (graspcap.tasks, graspcap.schemas, graspcap.catalog):\n"
        "    for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + '.'):\n"
        "        importlib.import_module(m.name)\n"
        "print(sorted(k for k in sys.modules if k.split('.')[0] == 'prefect'))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd="/"
    )
    assert out.stdout.strip() == "[]"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built once per test process. pytest-xdist may run this module's tests in
    two workers at once, and two ``pip wheel`` runs on one source tree clash in its ``build/``
    folder: a lock beside the workers' temporary folders makes them take turns."""
    out = tmp_path_factory.mktemp("wheel")
    lock = tmp_path_factory.getbasetemp().parent / "graspcap-wheel.lock"
    with open(lock, "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        built = subprocess.run(
            [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
             "-w", str(out), str(REPO)],
            capture_output=True, text=True,
        )
    assert built.returncode == 0, built.stderr[-3000:]
    return next(out.glob("graspcap-*.whl"))


def test_wheel_installs_one_import_root(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"graspcap", next(t for t in top if t.endswith(".dist-info"))}
    for sub in ("flows", "tasks", "schemas", "catalog"):
        assert f"graspcap/{sub}/__init__.py" in names
    for package in _source_packages():  # every sub-package, with all of its modules
        folder = package.replace(".", "/")
        assert f"{folder}/__init__.py" in names, f"{package} is not in the wheel"
    for name, path in _source_modules().items():
        assert name.replace(".", "/") + (
            "/__init__.py" if path.name == "__init__.py" else ".py") in names, name
    assert "graspcap/schemas/session.schema.json" in names


def test_regular_install_imports_catalog(wheel, tmp_path):
    target = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target),
         str(wheel)],
        check=True, capture_output=True,
    )
    installed = {p.name for p in target.iterdir() if not p.name.endswith(".dist-info")}
    assert installed - {"bin"} == {"graspcap"}  # bin/ holds the console script
    code = (
        f"import sys; sys.path.insert(0, {str(target)!r})\n"
        "import graspcap.catalog, graspcap.tasks.core.geometry as g\n"
        "print(graspcap.catalog.__file__)\n"
        "import importlib.util as u\n"
        "print([m for m in ('tasks', 'catalog', 'schemas', 'flows') if u.find_spec(m)])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path
    )
    catalog_file, leaked = out.stdout.strip().splitlines()
    assert catalog_file.startswith(str(target))
    assert leaked == "[]"


# --- layering ---------------------------------------------------------------------------------

ROOTS = {"graspcap": "graspcap", "graspcap.flows": "flows", "graspcap.tasks": "tasks",
         "graspcap.schemas": "schemas", "graspcap.catalog": "catalog"}

SECTIONS: dict[str, set[str]] = {
    # sub-package of tasks/ -> the sub-packages it may import (docs/architecture.md)
    "core": set(),
    "session": {"core"},
    "keypoints": {"core", "session"},
    "hand": {"core"},
    "hand_sfm": {"core", "hand"},
    "object_pose.registration": {"core"},
    "object_pose": {"core", "hand", "object_pose.registration"},
    "contact": {"core", "object_pose.registration"},
    "outputs": {"core", "hand", "object_pose", "object_pose.registration"},
}
"""``tasks/pipeline.py`` (the stage table) sits above them all and may import any; none of
them imports it."""

LAYERS: dict[str, set[str]] = {
    # top-level package -> the graspcap packages it must never import
    "graspcap.schemas": {"graspcap.tasks", "graspcap.flows", "graspcap.catalog", "graspcap.cli",
                         "graspcap.synth"},
    "graspcap.catalog": {"graspcap.tasks", "graspcap.flows", "graspcap.synth"},
    "graspcap.tasks": {"graspcap.flows", "graspcap.catalog", "graspcap.cli", "graspcap.synth"},
}


def _source_modules() -> dict[str, Path]:
    """Dotted name -> file of every module of the installed packages (from the source tree)."""
    out = {}
    for dotted, folder in ROOTS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = path.relative_to(REPO / folder)
            if "__pycache__" in rel.parts or "golden" in rel.parts:
                continue
            parts = rel.with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((dotted, *parts))] = path
    return out


def _source_packages() -> list[str]:
    return [n for n, p in _source_modules().items() if p.name == "__init__.py"]


def _graspcap_imports(path: Path, package: str) -> list[tuple[int, str]]:
    """(line, dotted name) of every graspcap import of a file, relative ones resolved, lazy
    ones (inside functions) included."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            out.append((node.lineno, module))
            out += [(node.lineno, f"{module}.{a.name}") for a in node.names]
    return [(n, m) for n, m in out if m == "graspcap" or m.startswith("graspcap.")]


def _section(dotted: str) -> str | None:
    """The tasks sub-package of a dotted name (the longest match), 'pipeline', or None."""
    if not dotted.startswith("graspcap.tasks."):
        return None
    rest = dotted[len("graspcap.tasks."):]
    for section in sorted(SECTIONS, key=len, reverse=True):
        if rest == section or rest.startswith(section + "."):
            return section
    return rest.split(".")[0]


def _layer_offenders() -> list[str]:
    offenders = []
    modules = _source_modules()
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        own = _section(name)
        seen = set()  # one offence per import statement
        for line, target in _graspcap_imports(path, package):
            if line in seen:
                continue
            before = len(offenders)
            shown = path.relative_to(REPO) if path.is_relative_to(REPO) else path
            where = f"{shown}:{line} imports {target}"
            if own in SECTIONS:
                other = _section(target)
                if other is not None and other != own and other not in SECTIONS[own]:
                    offenders.append(f"{where} ({own} may import {sorted(SECTIONS[own])})")
            for layer, banned in LAYERS.items():
                if name == layer or name.startswith(layer + "."):
                    if any(target == b or target.startswith(b + ".") for b in banned):
                        offenders.append(f"{where} ({layer} is below it)")
            if len(offenders) > before:
                seen.add(line)
    return offenders


def test_sub_packages_import_only_below_them():
    assert not _layer_offenders()


def test_the_section_table_covers_every_sub_package_and_core_imports_none():
    found = {p[len("graspcap.tasks."):] for p in _source_packages()
             if p.startswith("graspcap.tasks.")}
    assert found == set(SECTIONS)
    assert SECTIONS["core"] == set()
    top = {p.name for p in (REPO / "tasks").glob("*.py")}
    assert top == {"__init__.py", "pipeline.py"}, "a stage or helper belongs in a sub-package"


def test_the_layer_check_sees_an_upward_import(tmp_path, monkeypatch):
    bad = REPO / "tasks" / "core" / "geometry.py"
    text = bad.read_text() + "\nfrom graspcap.tasks.hand.model import HandSide  # noqa\n"
    fake = tmp_path / "geometry.py"
    fake.write_text(text)
    real = _source_modules()
    monkeypatch.setattr(
        sys.modules[__name__], "_source_modules",
        lambda: {**real, "graspcap.tasks.core.geometry": fake},
    )
    offenders = _layer_offenders()
    assert len(offenders) == 1 and "imports graspcap.tasks.hand.model" in offenders[0]
    assert "(core may import [])" in offenders[0]


def test_schemas_do_not_import_tasks():
    for path in sorted((REPO / "schemas").rglob("*.py")):
        imported = [m for _, m in _graspcap_imports(path, "graspcap.schemas")]
        assert not [m for m in imported if m.startswith("graspcap.tasks")], path
