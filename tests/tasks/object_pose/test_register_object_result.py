"""ObjectRegistration.second_hypothesis: the runner-up estimate_adjustment tries beside the
pose, only for an ambiguous result."""

from __future__ import annotations

import dataclasses

import numpy as np

from graspcap.tasks.object_pose.register_object import ObjectRegistration

RUNNER_UP = np.diag([-1.0, -1.0, 1.0, 1.0])
RESULT = ObjectRegistration(
    T_w_o=np.eye(4), fitness=0.9, inlier_rmse_m=0.002, n_points=500, depth_agreement=0.95,
    ambiguous=True, ambiguity_deg=180.0, T_w_o_runner_up=RUNNER_UP, runner_up_fitness=0.88,
    runner_up_rmse_m=0.002, runner_up_depth_agreement=0.94, free_axis_o=np.zeros(3),
    free_point_o=np.zeros(3), free_weakness=1.0,
)


def test_an_ambiguous_result_hands_on_its_runner_up():
    assert RESULT.second_hypothesis is RUNNER_UP


def test_a_clear_result_hands_on_none_even_with_a_runner_up():
    assert dataclasses.replace(RESULT, ambiguous=False).second_hypothesis is None
    assert dataclasses.replace(RESULT, T_w_o_runner_up=None).second_hypothesis is None
