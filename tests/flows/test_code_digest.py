"""The code part of a stage's cache key (flows/code_digest.py): found from the import graph,
blind to docstrings, comments and formatting, the same in every process."""

from __future__ import annotations

import ast
import json
import subprocess
import sys

import pytest

from graspcap.flows import code_digest
from graspcap.flows.code_digest import ast_digest, stage_code
from graspcap.tasks.pipeline import STAGES
from tests.conftest import REPO

HELPER = "graspcap.tasks.object_pose.registration.engine"

SOURCE = '''
"""Module docstring."""
import numpy as np

SCALE = 2.0
"""An attribute docstring."""


def f(x):
    """Docstring."""
    # a comment
    return np.asarray(x) * SCALE
'''


def _code(src: str) -> str:
    return ast_digest(ast.parse(src))


def test_docstrings_comments_and_formatting_do_not_count_but_code_does():
    reformatted = SOURCE.replace('"""Docstring."""', '"""Another text, longer."""').replace(
        "# a comment", "# another comment\n\n").replace("np.asarray(x) * SCALE",
                                                       "(np.asarray( x )\n            * SCALE)")
    reformatted = reformatted.replace('"""Module docstring."""', "").replace(
        '"""An attribute docstring."""', "")
    assert _code(reformatted) == _code(SOURCE)
    assert _code(SOURCE.replace("* SCALE", "* SCALE + 1")) != _code(SOURCE)
    # a function whose whole body is its docstring still digests (as ``pass``)
    assert _code('def g():\n    """Only this."""\n') == _code("def g():\n    pass\n")


def test_each_stage_covers_its_import_graph_and_its_own_glue_only():
    modules = {name: dict(stage_code(stage).modules) for name, stage in STAGES.items()}
    registration = {n for n, mods in modules.items() if HELPER in mods}
    # the registration engine is imported by the object-pose stages, found from the imports
    assert {"register_object", "register_scan"} <= registration
    assert "detect_keypoints" not in registration and "fit_hand" not in registration
    for name, mods in modules.items():
        glue = [m for m in mods if m.startswith("graspcap.tasks.pipeline:")]
        assert glue == [f"graspcap.tasks.pipeline:{STAGES[name].run.__name__}"], name
        assert "graspcap.tasks.pipeline" not in mods, name  # not every stage's glue at once
        assert STAGES[name].run.__module__ == "graspcap.tasks.pipeline"
    libs = {n: dict(stage_code(s).libraries) for n, s in STAGES.items()}
    assert "open3d" in libs["register_object"] and "open3d" not in libs["fit_hand"]
    assert "mediapipe" in libs["detect_keypoints"]
    assert "pycolmap" in libs["crosscheck_sfm"]


def test_stage_codes_are_the_same_in_another_process():
    here = {n: stage_code(s).digest for n, s in STAGES.items()}
    out = subprocess.run(
        [sys.executable, "-c",
         "import json; from graspcap.tasks.pipeline import STAGES; "
         "from graspcap.flows.code_digest import stage_code; "
         "print(json.dumps({n: stage_code(s).digest for n, s in STAGES.items()}))"],
        cwd=REPO, capture_output=True, text=True, check=True, env={"PYTHONHASHSEED": "123",
                                                                   **_env()})
    assert json.loads(out.stdout.strip().splitlines()[-1]) == here


def _env() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k != "PYTHONHASHSEED"}


@pytest.fixture
def restore_overrides():
    yield
    code_digest._OVERRIDES.clear()
    code_digest.forget()


def test_an_override_changes_exactly_the_stages_that_import_the_module(restore_overrides):
    before = {n: stage_code(s).digest for n, s in STAGES.items()}
    code_digest.override(HELPER, "changed")
    after = {n: stage_code(s).digest for n, s in STAGES.items()}
    changed = {n for n in STAGES if before[n] != after[n]}
    assert changed == {n for n, s in STAGES.items() if HELPER in dict(stage_code(s).modules)}
    code_digest.override(HELPER, None)
    code_digest.override("lib:open3d", "99.0")
    libs = {n for n, s in STAGES.items() if "open3d" in dict(stage_code(s).libraries)}
    assert {n for n, s in STAGES.items() if stage_code(s).digest != before[n]} == libs


def test_glue_counts_for_its_own_stage_and_a_shared_helper_for_its_users(monkeypatch,
                                                                         restore_overrides):
    """Edited copies of tasks/pipeline.py's source (the file itself is never touched)."""
    real = code_digest._source
    before = {n: stage_code(s).digest for n, s in STAGES.items()}

    def changed(edit) -> set[str]:
        def source(name):
            found = real(name)
            return (edit(found[0]), found[1]) if name == "graspcap.tasks.pipeline" else found

        monkeypatch.setattr(code_digest, "_source", source)
        code_digest.forget()
        return {n for n, s in STAGES.items() if stage_code(s).digest != before[n]}

    assert changed(lambda src: src.replace(b"def _pictures(session: Session, config, **up):",
                                           b"def _pictures(session: Session, config, **up):\n"
                                           b"    pass", 1)) == {"pictures"}
    users = {n for n, s in STAGES.items()
             if "_final_hand(" in __import__("inspect").getsource(s.run)}
    shared_changed = changed(lambda src: src.replace(
        b'up.get("refine_grasp"), up["estimate_adjustment"].T_w_o)',
        b'up.get("refine_grasp"), up["estimate_adjustment"].T_w_o * 1)', 1))
    assert users == {"propagate_poses", "qa_metrics", "pictures"} == shared_changed
    assert changed(lambda src: src.replace(b"# --- the DAG", b"# --- the graph", 1)) == set()


def test_a_memo_across_processes_is_used_only_while_every_module_file_is_as_recorded(
        tmp_path, monkeypatch, restore_overrides):
    """``stage_code(stage, memo_dir)``: a new process (``forget``) takes the memo without
    parsing a module while the files' (path, size, mtime_ns) and folders are as recorded; a
    changed file, a file of another checkout, or a file modified within ``RACY_S`` is not
    trusted."""
    stage = STAGES["register_object"]
    truth = stage_code(stage)
    code_digest.forget()
    assert stage_code(stage, tmp_path) == truth  # computed, then remembered
    memo = tmp_path / "code-register_object.json"
    record = json.loads(memo.read_text())
    assert {f[0] for f in record["files"]} >= {HELPER}

    parsed = []
    real = code_digest._source
    monkeypatch.setattr(code_digest, "_source", lambda n: parsed.append(n) or real(n))

    def fresh(memo_dir=tmp_path):
        code_digest.forget()  # as in a new process
        return stage_code(stage, memo_dir)

    assert fresh() == truth and parsed == []  # from the memo, nothing parsed
    # a memo with other digests is what a process takes while the stats match ...
    fake = {**record, "modules": [[m, "x" * 64] for m, _ in record["modules"]]}
    memo.write_text(json.dumps(fake))
    assert dict(fresh().modules)[HELPER] == "x" * 64
    # ... and never once one file's size (or mtime) differs: a changed module is parsed again
    for field, index in (("size", 2), ("mtime", 3)):
        files = [list(f) for f in fake["files"]]
        files[0][index] += 1
        memo.write_text(json.dumps({**fake, "files": files}))
        parsed.clear()
        assert fresh() == truth and parsed, field
    # a module listed under another checkout's path: not this process's code
    files = [list(f) for f in fake["files"]]
    files[0][1] = "/elsewhere/" + files[0][1].lstrip("/")
    memo.write_text(json.dumps({**fake, "files": files}))
    assert fresh() == truth
    # a folder whose mtime changed (a module added or removed)
    memo.write_text(json.dumps({**fake, "folders": [[p, m + 1] for p, m in fake["folders"]]}))
    assert fresh() == truth
    # racy: a module file modified within RACY_S of the recording is not remembered
    memo.unlink()
    monkeypatch.setattr(code_digest, "RACY_S", 1e12)
    assert fresh() == truth and not memo.exists()
    # read-only (``--plan``) and overrides neither write nor read it
    monkeypatch.setattr(code_digest, "RACY_S", 2.0)
    code_digest.forget()
    assert stage_code(stage, tmp_path, write=False) == truth and not memo.exists()
    assert fresh() == truth and memo.exists()
    code_digest.override(HELPER, "changed")
    assert dict(stage_code(stage, tmp_path).modules)[HELPER] == "changed"
