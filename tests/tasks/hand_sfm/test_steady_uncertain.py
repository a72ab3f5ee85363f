"""select_steady says when its detected onset cannot be trusted (issue 19 item 3): a QA flag
instead of a silently wrong onset."""

from __future__ import annotations

import numpy as np

from graspcap.synth.hand_video import make_hand_video
from graspcap.tasks.hand_sfm.select_steady import SelectSteadyConfig, select_steady
from graspcap.tasks.outputs.qa_metrics import stage_warnings


def test_a_clear_onset_is_not_marked():
    video = make_hand_video(n_frames=90, steady_from=30, seed=5, closing_deg_per_frame=3.0)
    sel = select_steady(video.keypoints, video.K, None)
    assert abs(sel.steady_from - 30) <= 3
    assert sel.uncertain == ""
    assert stage_warnings({"select_steady": sel}) == []


def test_no_adjustment_seen_is_marked():
    """The fingers never move: no frame stands out, the onset is the first frame, and the
    selection says that the adjustment phase was not seen."""
    video = make_hand_video(n_frames=50, steady_from=0, seed=5)
    sel = select_steady(video.keypoints, video.K, None)
    assert sel.steady_from == 0
    assert sel.uncertain.startswith("no frame before 0 stands out as moving above the keypoint "
                                    "noise")
    flags = stage_warnings({"select_steady": sel})
    assert flags == [f"select_steady: steady onset uncertain: {sel.uncertain}"]


def test_noise_that_hides_the_closing_fingers_is_marked():
    """8 px per coordinate on a hand ~300 px across (2.6 %): the fingers closing by 3 deg a
    frame no longer stand out, and the selection says so instead of calling frame 0 the
    onset silently."""
    noisy = make_hand_video(n_frames=90, steady_from=30, seed=5, closing_deg_per_frame=3.0,
                            noise_px=8.0)  # fmt: skip
    sel = select_steady(noisy.keypoints, noisy.K, None)
    assert sel.steady_from == 0
    assert sel.uncertain.startswith("no frame before 0 stands out")
    assert "2.6% of the hand's 295 px" in sel.uncertain


def test_noise_share_above_the_limit_is_marked():
    """The same 2.5 px video as the clear onset, its onset found, but judged against a limit
    below its measured noise share: marked, with the onset kept."""
    video = make_hand_video(n_frames=90, steady_from=30, seed=5, closing_deg_per_frame=3.0)
    strict = SelectSteadyConfig(max_noise_share=0.005)
    sel = select_steady(video.keypoints, video.K, None, strict)
    assert abs(sel.steady_from - 30) <= 3
    assert "hides the last motion of the grasp" in sel.uncertain
    assert f"(frame {sel.steady_from})" in sel.uncertain


def test_the_manifest_onset_is_never_marked():
    video = make_hand_video(n_frames=20, steady_from=5, seed=1)
    sel = select_steady(video.keypoints, video.K, 5)
    assert sel.uncertain == ""
    assert np.isnan(sel.scores_px).all()
