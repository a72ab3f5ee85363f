"""The registration stages give the same pose for the same input, in one process and in
another (a cached build must agree with a fresh one).

With Open3D's RANSAC (TBB threads sharing one generator) and multi-threaded ICP, the build
bench's mug (seed 11 #0) came out 15 and 32 deg off in two runs of register_object, and the
one-frame adjustment of the same session 10, 140 or 163 deg off.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from graspcap.tasks.object_pose.estimate_adjustment import estimate_adjustment
from graspcap.tasks.object_pose.register_object import register_object
from tests.registration_rig import (
    K,
    lifted_in_hand,
    load_mesh,
    look_at_turntable,
    random_pose_on_platter,
)

CHILD = """
import json, sys
import numpy as np
from graspcap.tasks.object_pose.estimate_adjustment import estimate_adjustment
from graspcap.tasks.object_pose.register_object import register_object
a = np.load(sys.argv[1])
if sys.argv[2] == "register_object":
    r = register_object(a["depth"], a["K"], a["T_ct"], a["V"], a["F"])
else:
    r = estimate_adjustment(a["depth"], a["K"], a["V"], a["F"], a["T_w_o1"], a["mask"])
print(json.dumps(r.T_w_o.tolist()))
"""


def _in_child(tmp_path, stage: str, **arrays) -> np.ndarray:
    """The stage's ``T_w_o`` computed in a fresh Python process."""
    path = tmp_path / f"{stage}.npz"
    np.savez(path, **arrays)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(path), stage], capture_output=True, text=True,
        env=env, check=True, timeout=600,
    )  # fmt: skip
    return np.array(json.loads(out.stdout.strip().splitlines()[-1]))


@pytest.fixture(scope="module")
def mug_stage1(tmp_path_factory):
    """Stage 1 of the build bench's first session (seed 11 #0, easy): a mug whose candidate
    poses compete closely (the stage-1 scene is drawn before the video: 8 frames suffice)."""
    from graspcap.synth import config_for, generate_session
    from graspcap.tasks import pipeline

    d = generate_session(tmp_path_factory.mktemp("mug11"), [11, 0], config_for("easy", 8))
    assert d.name.endswith("mug")
    s = pipeline.run_stage(
        pipeline.STAGES["load_session"], d, pipeline.configs_for()["load_session"], {}
    )
    V, F = s.read_mesh()
    return {
        "depth": s.read_depth_m(s.manifest.stage1.depth),
        "K": np.asarray(s.manifest.color_camera.K, float),
        "T_ct": np.asarray(s.manifest.turntable.T_color_turntable, float),
        "V": V,
        "F": F,
    }


def test_register_object_is_repeatable_across_runs_and_processes(mug_stage1, tmp_path):
    a = mug_stage1
    first = register_object(a["depth"], a["K"], a["T_ct"], a["V"], a["F"])
    again = register_object(a["depth"], a["K"], a["T_ct"], a["V"], a["F"])
    np.testing.assert_array_equal(first.T_w_o, again.T_w_o)  # bit for bit
    assert first.fitness == again.fitness and first.ambiguous == again.ambiguous
    np.testing.assert_array_equal(_in_child(tmp_path, "register_object", **a), first.T_w_o)


def test_estimate_adjustment_global_path_is_repeatable(shared_data, tmp_path):
    """The one-frame global path (FPFH + RANSAC + ICP + probes) on a bunny lifted 0.2 m."""
    mesh = load_mesh(shared_data, "bunny")
    T_ct = look_at_turntable()
    rng = np.random.default_rng(3)
    T_w_o1 = T_ct @ random_pose_on_platter(*mesh, rng)
    depth, mask, _ = lifted_in_hand(mesh, T_w_o1, T_ct, rng, angle_deg=30.0)
    runs = [estimate_adjustment(depth, K, *mesh, T_w_o1, mask) for _ in range(2)]
    assert runs[0].path == "near_hand_global"
    np.testing.assert_array_equal(runs[0].T_w_o, runs[1].T_w_o)
    child = _in_child(
        tmp_path, "estimate_adjustment", depth=depth, K=K, V=mesh[0], F=mesh[1], T_w_o1=T_w_o1,
        mask=mask,
    )  # fmt: skip
    np.testing.assert_array_equal(child, runs[0].T_w_o)
