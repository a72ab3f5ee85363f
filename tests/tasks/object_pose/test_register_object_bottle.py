"""register_object on a realistic synthetic rig bottle (seed [7, 2], the demo's third session):
register_object/7 stopped ICP 17.7 deg off about the bottle's long axis at fitness times depth
agreement 0.983, above ``grid_until``, so no probe looked for the truth (0.999). One more full
ICP run from the best pose (``refit_rounds``) reaches it; the twin stays the runner-up and the
result is reported ambiguous."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.tasks.core.geometry import pose_error, rotation_error_deg
from graspcap.tasks.object_pose.register_object import PRESETS, register_object
from graspcap.tasks.object_pose.registration.point_clouds import PlatterCrop
from tests.registration_rig import rig_session_stage1

ROT_DEG, TRANS_M = 1.0, 0.003


@pytest.fixture(scope="module")
def bottle_stage1(tmp_path_factory):
    return rig_session_stage1(tmp_path_factory.mktemp("bottle"), [7, 2], "bottle")


def test_bottle_is_refitted_to_the_truth_and_reported_ambiguous(bottle_stage1):
    depth, K, T_ct, V, F, T_true = bottle_stage1
    # the case as measured: the crop without the flying-pixel filter (register_object/10's
    # one-sided filter dropped 3 of these 12241 points and changed RANSAC's draws; the
    # two-sided one finds 5 candidates in the image, under its 0.1 % gate: nothing dropped)
    as_measured = PRESETS["default"].model_copy(update={"crop": PlatterCrop(drop_flying=False)})
    r = register_object(depth, K, T_ct, V, F, as_measured)
    rot_deg, trans_m = pose_error(r.T_w_o, T_true)
    assert rot_deg < ROT_DEG and trans_m < TRANS_M
    assert r.fitness * r.depth_agreement > 0.99
    # the pose turned about the long axis explains the depth nearly as well: reported
    assert r.ambiguous and r.T_w_o_runner_up is not None
    assert rotation_error_deg(r.T_w_o_runner_up[:3, :3], T_true[:3, :3]) > 10.0
    default = register_object(depth, K, T_ct, V, F)
    rot_deg, trans_m = pose_error(default.T_w_o, T_true)
    assert rot_deg < ROT_DEG and trans_m < TRANS_M


def test_without_the_refit_the_bottle_stays_off_about_its_axis(bottle_stage1):
    """The case is a real one: without the refit the stage stops > 10 deg off, about the
    bottle's long axis (the mesh's axis of largest variance)."""
    depth, K, T_ct, V, F, T_true = bottle_stage1
    # without the grid starts too (register_object/10), which reach the truth on their own
    cfg = PRESETS["default"].model_copy(
        update={"refit_rounds": 0, "grid_group": "", "crop": PlatterCrop(drop_flying=False)}
    )
    r = register_object(depth, K, T_ct, V, F, cfg)
    rot_deg, _ = pose_error(r.T_w_o, T_true)
    assert rot_deg > 10.0
    R = r.T_w_o[:3, :3].T @ T_true[:3, :3]  # object-frame rotation from the estimate to truth
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    Vc = np.asarray(V, float) - np.mean(V, axis=0)
    long_axis = np.linalg.eigh(Vc.T @ Vc)[1][:, -1]
    assert abs(axis @ long_axis) / np.linalg.norm(axis) > 0.99
