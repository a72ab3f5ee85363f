"""select_steady's depth onset (step 5, ``hand_sfm.steady_depth``): under a real detector's
keypoint noise the keypoint onset is many frames early; the depth's non-rigidity finds it."""

from __future__ import annotations

import json

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage


def test_depth_onset_where_the_keypoints_are_early(tmp_path):
    d = generate_session(tmp_path, [9700, 0], config_for("real-detector", 60))
    truth = json.loads((d / "ground_truth" / "truth.json").read_text())["steady_from"]
    res: dict = {}
    for name in ("load_session", "detect_keypoints", "select_steady"):
        res[name] = run_stage(STAGES[name], d, configs_for()[name], res)
    sel = res["select_steady"]
    assert abs(sel.keypoint_from - truth) > 3  # the keypoints alone: early
    assert sel.depth_from >= 0 and abs(sel.steady_from - truth) <= 3
    assert "hides the last motion" not in sel.uncertain
    share = sel.depth_share
    # the surface deforms before the onset, moves rigidly after it
    assert np.nanmedian(share[: max(truth - 4, 1)]) > 5 * np.nanmedian(share[truth + 2:])
