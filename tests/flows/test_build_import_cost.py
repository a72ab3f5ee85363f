"""A fresh ``graspcap build`` process with nothing to run loads none of the stages' heavy libraries
(issue 21): not at import (``tests/tasks/test_import_cost.py``), nor while it settles every
stage, writes the build record and the report page."""

from __future__ import annotations

import json
import subprocess
import sys

from tests.flow_fixtures import PRESET, copy_catalog
from tests.tasks.test_import_cost import HEAVY


def test_an_unchanged_rebuild_in_a_fresh_process_loads_no_heavy_library(warm, synth_root,
                                                                        tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    argv = ["build", str(synth_root), "--catalog", str(catalog), "--preset", PRESET]
    code = ("import json, sys\nfrom graspcap.cli import main\n"
            f"rc = main({argv!r})\n"
            "print(json.dumps([rc, sorted({m.split('.')[0] for m in sys.modules}"
            f" & set({HEAVY!r}))]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    rc, heavy = json.loads(out.stdout.strip().splitlines()[-1])
    assert "0 stage run(s)" in out.stdout and "nothing changed" in out.stdout, out.stdout
    assert (rc, heavy) == (0, [])
