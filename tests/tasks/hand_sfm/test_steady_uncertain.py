"""select_steady says when its detected onset cannot be trusted (issue 19 item 3): a QA flag
instead of a silently wrong onset."""

from __future__ import annotations

import numpy as np
import pytest

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import load_truth
from graspcap.synth.hand_video import make_hand_video
from graspcap.tasks.hand_sfm.select_steady import SelectSteadyConfig, select_steady
from graspcap.tasks.outputs.qa_metrics import stage_warnings
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage


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


# step 6: is the depth's onset trustworthy? Constructed shares (the steady level 0, spread
# 0.01: z = share / 0.01), the depth's change point ``t`` and the final onset.

def _doubt(share, t, onset=None, at_end=False, cfg=None):
    from graspcap.tasks.hand_sfm.steady_depth import depth_doubt

    cfg = cfg or SelectSteadyConfig()
    share = np.array(share, dtype=float)
    onset = t + cfg.depth_lag_frames if onset is None else onset
    return depth_doubt(share, share / 0.01, t, onset, at_end, cfg)


def test_a_sharp_or_settling_end_is_not_marked():
    # deforming, then rigid at once
    assert _doubt([0.6, 0.7, 0.5, 0.4, 0.0, 0.0, 0.0, 0.0], 4) == ("", 3)
    # a settling tail: the share falls frame by frame through weak values
    assert _doubt([0.2, 0.4, 0.3, 0.21, 0.17, 0.15, 0.10, 0.05, 0.0, 0.0], 8) == ("", 7)
    # a frame or two without a surface between the motion and the change point
    assert _doubt([0.6, 0.6, np.nan, np.nan, 0.0, 0.0, 0.0, 0.0], 4) == ("", 1)


def test_a_change_after_a_run_of_unknown_frames_is_marked():
    """Deforming at frame 1, no surface on frames 2-5, rigid from 6: the grasp may have
    settled anywhere in the run, so the change point at 6 is no better than frame 2 (wild
    ``[50832, 11]``: 10 unknown frames, the onset 4 frames late)."""
    why, last = _doubt([0.6, 0.6, np.nan, np.nan, np.nan, np.nan, 0.0, 0.0, 0.0], 6)
    assert last == 1
    assert why.startswith("the depth sees the grasp deforming up to frame 1, the onset is "
                          "frame 7")


def test_weak_non_rigidity_that_does_not_fall_is_marked():
    """A deformation that ends at frame 6, then weak non-rigidity that neither grows nor
    falls (a misfit of a rigid surface, or a slow last motion: the depth cannot tell)."""
    share = [0.6, 0.6, 0.5, 0.5, 0.4, 0.4, 0.38, 0.08, 0.05, 0.12, 0.07, 0.10, 0.12, 0.0, 0.0]
    why, last = _doubt(share, 13)
    assert last == 8  # 0.38 -> 0.08 -> 0.05 falls; 0.12 does not
    assert why.startswith("the depth sees the grasp deforming up to frame 8, the onset is "
                          "frame 14")


def test_frames_without_the_hand_after_the_change_are_marked():
    """A clean change at frame 4, but the hand is not detected in frames 5-10: the onset
    moves to frame 11 and may be up to 7 frames late."""
    why, _ = _doubt([0.6, 0.7, 0.5, 0.4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], 4, onset=11)
    assert "deforming up to frame 3, the onset is frame 11" in why


def test_two_candidate_ends_are_marked():
    """Rigid at frames 3-4, deforming again at 5-8: which end is the grasp's?"""
    share = [0.9, 0.9, 0.5, 0.0, 0.01, 0.13, 0.59, 0.6, 0.42, 0.03, 0.0, 0.0]
    why, last = _doubt(share, 9)
    assert last == 8
    assert why.startswith("the surface is rigid at frame 3 and deforms again up to frame 8")


def test_a_change_on_the_last_searched_frame_is_marked():
    why, _ = _doubt([0.6, 0.6, 0.6, 0.6, 0.5], 4, onset=4, at_end=True)
    assert why.startswith("the surface still deforms at frame 4, the last searched frame")


def test_a_change_with_no_deformation_before_it_is_marked():
    why, last = _doubt([0.8, 0.0, 0.0, 0.0, 0.0], 0)
    assert last == -1
    assert why.startswith("the depth sees no deformation before its change point (frame 0)")


@pytest.mark.slow
def test_a_wild_session_with_two_candidate_ends_is_marked(tmp_path):
    """Tuning session wild [9700, 11], 40 frames: the surface turns rigid at the true onset
    (frame 10) and deforms again in frames 12-17 (a misfit of the rigid surface); the depth's
    change point is the later end, 8-9 frames late, and the selection says so."""
    d = generate_session(tmp_path, [9700, 11], config_for("wild", 40))
    res: dict = {}
    for name in ("load_session", "detect_keypoints", "select_steady"):
        res[name] = run_stage(STAGES[name], d, configs_for()[name], res)
    sel, truth = res["select_steady"], int(load_truth(d)["steady_from"])
    assert sel.depth_from >= 0 and sel.steady_from - truth > 3
    assert sel.uncertain.startswith(f"the surface is rigid at frame {truth}")
