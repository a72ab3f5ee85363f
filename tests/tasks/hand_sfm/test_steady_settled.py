"""The onset a marked change point falls back on (``steady_depth.settled_after_deforming``).

The shares are wild `[44199, 0]`'s (40 frames, depth share per frame, rounded): the grasp
deforms on frames 0-4, is rigid from 5 (the truth's onset is 6 = 5 + the lag), and a fast
turn of the held grasp, which ICP misregisters, reads 0.2-0.7 on frames 17-20 and 28-34.
Those fill the change point's reference, and select_steady/10 put the onset on frame 1.
"""

from __future__ import annotations

import numpy as np

from graspcap.tasks.hand_sfm.steady_depth import settled_after_deforming

SHARE = np.array([0.498, 0.531, 0.63, 0.676, 0.668, 0.009, 0.002, 0.003, 0.005, 0.005, 0.008,
                  0.007, 0.005, 0.002, 0.002, 0.002, 0.015, 0.587, 0.644, 0.617, 0.599, 0.004,
                  0.0, 0.001, 0.002, 0.001, 0.0, 0.001, 0.219, 0.635, 0.704, 0.669, 0.662,
                  0.591, 0.192, 0.031, np.nan, np.nan, np.nan, np.nan])  # fmt: skip


def test_the_first_settled_run_after_the_deformation():
    assert settled_after_deforming(SHARE, 0.2, 0.1, 5, latest=20) == 5


def test_frames_without_a_share_are_skipped_not_counted():
    share = SHARE.copy()
    share[6:8] = np.nan  # a run of frames without a surface inside the rigid run
    assert settled_after_deforming(share, 0.2, 0.1, 5, latest=20) == 5


def test_a_rigid_run_too_short_is_passed_over():
    share = SHARE.copy()
    share[7:10] = 0.4  # rigid on 5-6 only, deforming again on 7-9
    assert settled_after_deforming(share, 0.2, 0.1, 5, latest=20) == 10


def test_nothing_before_the_first_deformation_and_nothing_after_the_window():
    assert settled_after_deforming(np.full(30, 0.01), 0.2, 0.1, 5, latest=20) == -1
    assert settled_after_deforming(SHARE, 0.2, 0.1, 5, latest=4) == -1


def test_a_short_rigid_run_before_a_fast_turn_is_the_default_fallback():
    """Wild ``[94397, 0]`` (40 frames, truth onset 8): the grasp deforms on 0-6, is rigid on
    7-8, then turns 46-81 deg between registered frames, which reads 0.5-0.7 on 9-12; the
    change point lands on 14 and is marked (rigid, then deforming again). With the default
    two settled frames the fallback is frame 7 (onset 8 with the lag); the earlier default of
    five passed over the short run to 13."""
    from graspcap.tasks.hand_sfm.select_steady import SelectSteadyConfig

    share = np.array([0.5, 0.5, 0.5, 0.757, 0.647, 0.701, 0.404, 0.001, 0.007, 0.514, 0.665,
                      0.624, 0.642, 0.041, 0.019, 0.012, 0.005, 0.0, 0.0, 0.0, 0.0, 0.001, 0.0,
                      0.002, 0.007, 0.49, 0.68, 0.725, 0.737, 0.696, np.nan, np.nan, 0.455,
                      0.019, 0.007, 0.0, np.nan, np.nan, np.nan, np.nan])  # fmt: skip
    cfg = SelectSteadyConfig()
    args = (share, cfg.depth_strong_share, cfg.depth_settled_share)
    assert settled_after_deforming(*args, cfg.depth_settled_frames, latest=20) == 7
    assert settled_after_deforming(*args, 5, latest=20) == 13
