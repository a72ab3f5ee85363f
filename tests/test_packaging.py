"""Packaging and layering: one import root, and Prefect only inside flows/."""

from __future__ import annotations

import ast
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
        "    for m in pkgutil.iter_modules(pkg.__path__):\n"
        "        importlib.import_module(f'{pkg.__name__}.{m.name}')\n"
        "print(sorted(k for k in sys.modules if k.split('.')[0] == 'prefect'))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd="/"
    )
    assert out.stdout.strip() == "[]"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(out), str(REPO)],
        check=True, capture_output=True,
    )
    return next(out.glob("graspcap-*.whl"))


def test_wheel_installs_one_import_root(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"graspcap", next(t for t in top if t.endswith(".dist-info"))}
    for sub in ("flows", "tasks", "schemas", "catalog"):
        assert f"graspcap/{sub}/__init__.py" in names
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
