"""`graspcap` on bad input: one line naming the problem, exit 2, nothing created; presets and
every other fixed set of values offered as argparse choices; a pipe closed early ends quietly."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

import graspcap.catalog as gc
from graspcap.cli import EXIT_BROKEN_PIPE, build_parser, main
from graspcap.tasks.core.presets import PIPELINE_PRESETS
from tests.catalog_factory import make_build

FIXED_SETS = {"preset": list(PIPELINE_PRESETS), "difficulty": ["easy", "realistic", "hard"],
              "format": ["parquet", "csv", "lerobot"], "backend": ["mediapipe", "openpose_json"],
              "hand": ["right", "left"], "model_complexity": [0, 1]}
"""Options whose values are a fixed set, as the parser must offer them."""


def _options(parser: argparse.ArgumentParser, path: str = "graspcap"):
    """(command path, action) of every option of ``parser`` and its subcommands."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, f"{path} {name}")
        elif action.option_strings:
            yield path, action


def test_every_fixed_set_of_values_is_offered_as_choices():
    seen = set()
    for path, action in _options(build_parser()):
        if action.dest in FIXED_SETS:
            assert action.choices is not None, (path, action.dest)
            assert list(action.choices) == FIXED_SETS[action.dest], (path, action.dest)
            seen.add((path, action.dest))
    assert {("graspcap build", "preset"), ("graspcap serve", "preset"),
            ("graspcap catalog export", "format"), ("graspcap detect", "backend")} <= seen


def test_an_unknown_preset_is_refused_naming_the_choices(tmp_path, capsys):
    (tmp_path / "sessions").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main(["build", str(tmp_path / "sessions"), "--catalog", str(tmp_path / "c"),
              "--preset", "fsat"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert "argument --preset: invalid choice: 'fsat' (choose from 'default', 'fast'," in err
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("value, why", [
    ("local:0", "'local:0': local:N needs a number of worker processes >= 1"),
    ("local:two", "'local:two': local:N needs a number of worker processes >= 1"),
    ("localhost", "'localhost': give a Dask scheduler's address (tcp://HOST:PORT or HOST:PORT)"),
])
def test_a_malformed_dask_option_is_refused(tmp_path, capsys, value, why):
    (tmp_path / "sessions").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main(["build", str(tmp_path / "sessions"), "--catalog", str(tmp_path / "c"),
              "--dask", value])
    assert exit_.value.code == 2
    assert f"argument --dask: {why}" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_detect_names_a_missing_input(tmp_path, capsys):
    (tmp_path / "frames").mkdir()
    assert main(["detect", str(tmp_path / "frames"), str(tmp_path / "frame.png")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == (f"graspcap detect: {str(tmp_path / 'frame.png')!r} does not "
                                 "exist (no such file or folder)\n")


@pytest.mark.parametrize("command", ["build", "validate", "serve"])
def test_a_missing_root_is_named_and_nothing_is_created(tmp_path, capsys, command):
    good = tmp_path / "sessions"
    good.mkdir()
    argv = [command, str(good), str(tmp_path / "sesions")]
    if command != "validate":
        argv += ["--catalog", str(tmp_path / "c")]
    if command == "serve":
        argv += ["--cron", "0 2 * * *"]
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (f"graspcap {command}: {str(tmp_path / 'sesions')!r} does not exist (no such "
                   "file or folder); name folders that hold sessions\n")
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("when, why", [
    (["--cron", "every night"], "--cron 'every night' is not a cron schedule: give five fields"),
    (["--cron", "61 2 * * *"], "--cron '61 2 * * *' is not a cron schedule"),
    (["--cron", "H 2 * * *"], "--cron 'H 2 * * *' is not a cron schedule"),
    (["--interval", "0"], "--interval 0: give a number of seconds > 0"),
    (["--interval", "nan"], "--interval nan: give a number of seconds > 0"),
])
def test_serve_refuses_an_invalid_schedule_before_anything_starts(tmp_path, capsys,
                                                                   monkeypatch, when, why):
    monkeypatch.setattr(os, "environ", dict(os.environ))  # serve sets Prefect's defaults
    for key in ("PREFECT_API_URL", "PREFECT_HOME"):
        os.environ.pop(key, None)
    (tmp_path / "sessions").mkdir()
    code = main(["serve", str(tmp_path / "sessions"), "--catalog", str(tmp_path / "c"), *when])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.startswith(f"graspcap serve: {why}") and err.count("\n") == 1, err
    assert not (tmp_path / "c").exists()  # not even Prefect's home in its work area


def test_a_valid_cron_passes_the_check():
    from graspcap.flows.runtime import schedule_problem

    for cron in ("0 2 * * *", "*/15 * * * *", "0 2 * * mon-fri", "@daily"):
        assert schedule_problem(cron, None) is None, cron
    assert schedule_problem(None, 3600.0) is None


@pytest.mark.parametrize("make", ["nothing", "folder", "file"])
def test_status_on_a_path_that_is_not_a_catalog(tmp_path, capsys, make):
    path = tmp_path / "not-a-catalog"
    if make == "folder":
        path.mkdir()
    elif make == "file":
        path.write_text("hello\n")
    assert main(["status", "--catalog", str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and "Traceback" not in err
    assert err == (f"graspcap status: {path} is not a graspcap catalog (no catalog.json); "
                   "`graspcap build ... --catalog` creates one there (in Python: "
                   "graspcap.catalog.open(..., create=True))\n")
    assert path.exists() == (make != "nothing")


@pytest.fixture(scope="module")
def small_catalog(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cli") / "cat"
    cat = gc.open(root, create=True)
    cat.commit(make_build(["p01-mug-use-00", "p02-drill-use-00"], seed=1, build_id="b1"))
    return root


def test_catalog_option_before_or_after_the_subcommand(small_catalog, capsys, tmp_path,
                                                      monkeypatch):
    assert main(["catalog", "versions", "--catalog", str(small_catalog)]) == 0
    after = capsys.readouterr().out
    assert main(["catalog", "--catalog", str(small_catalog), "versions"]) == 0
    before = capsys.readouterr().out
    assert before == after and " b1 " in before
    # given twice, the subcommand's wins; given nowhere, the default catalog folder is used
    assert main(["catalog", "--catalog", str(tmp_path / "x"), "versions", "--catalog",
                 str(small_catalog)]) == 0
    assert capsys.readouterr().out == after
    monkeypatch.chdir(tmp_path)
    assert main(["catalog", "versions"]) == 2
    assert "graspcap-catalog is not a graspcap catalog" in capsys.readouterr().err


def test_a_pipe_closed_early_ends_quietly(small_catalog):
    """`graspcap catalog show | head -0`: the reader is gone before the first write."""
    proc = subprocess.Popen([sys.executable, "-m", "graspcap.cli", "catalog", "show",
                             "--catalog", str(small_catalog)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # long before the interpreter has imported graspcap
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == EXIT_BROKEN_PIPE
    assert err == ""
