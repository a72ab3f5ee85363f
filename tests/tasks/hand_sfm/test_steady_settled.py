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
