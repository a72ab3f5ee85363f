"""Importing the stage table, and the modules ``graspcap build`` imports before it knows whether
anything must run, loads none of the stages' heavy libraries (issue 21): the stage modules import
them inside the functions that use them. Each check runs in a fresh interpreter, as the CLI
does (this process has imported them all long ago)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("open3d", "gtsam", "pycolmap", "cv2", "trimesh", "scipy", "skimage", "torch",
         "mediapipe")
"""Top-level names of the libraries that only compute (~8 s to import on a loaded machine:
open3d ~2.8 s, scipy ~2 s of it); ``scipy`` covers ``scipy.stats``, ``scipy.spatial`` ..."""


def heavy_after(*modules: str) -> list[str]:
    """The :data:`HEAVY` libraries a fresh interpreter has loaded after importing ``modules``."""
    code = (f"import json, sys\nfor m in {modules!r}:\n    __import__(m)\n"
            f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r}))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_the_stage_table_loads_no_heavy_library():
    assert heavy_after("graspcap.tasks.pipeline") == []


@pytest.mark.parametrize("modules", [
    ("graspcap.cli",),
    # what `graspcap build` imports before it settles the sessions (flows/commands.run_build);
    # Prefect is among them: flows/build.py and flows/session.py define its flow and tasks
    ("graspcap.cli", "graspcap.flows.commands", "graspcap.flows.build",
     "graspcap.flows.progress", "graspcap.catalog.audit"),
])
def test_the_build_command_imports_no_heavy_library(modules):
    assert heavy_after(*modules) == []


def test_the_keys_the_stages_import_without_gtsam_and_cv2_match_theirs():
    """Constants written out so that their module needs no import: the same values."""
    import cv2
    import gtsam

    from graspcap.tasks.core.camera import UNDISTORT_CRITERIA
    from graspcap.tasks.hand_sfm.hand_graph import A_KEY, B_KEY, S_KEY

    assert (A_KEY, B_KEY, S_KEY) == tuple(gtsam.symbol(c, 0) for c in "abs")
    assert UNDISTORT_CRITERIA[0] == cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS
