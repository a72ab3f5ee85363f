"""select_steady on a hand that slows down before it stops, and the batched pose refinement.

The scenes are ``make_hand_video``'s static hand (2.5 px noise, 5 % outliers of 20-80 px, 3 %
misses) with the fingers drawn towards the palm before the onset by a share that falls to 0
along a smoothstep, so the last moving frames differ from the steady hand by about a pixel:
the case where an energy threshold stops 4-9 frames early.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from graspcap.synth.hand_video import make_hand_video
from graspcap.tasks.core.geometry import inv_T, make_T, pose_error, project
from graspcap.tasks.hand_sfm.batch_pnp import refine_poses, residual_vectors
from graspcap.tasks.hand_sfm.select_steady import SelectSteadyConfig, SteadyMethod, select_steady
from graspcap.tasks.hand_sfm.steady_stats import matched_filter

PALM = [0, 1, 5, 9, 13, 17]
ONSET = 30


def _slowing_hand(seed: int, n: int = 90, reach: float = 0.8):
    """Keypoints (n, 21, 3) and K of a hand whose fingers close until frame ONSET, slowing
    to a stop (the share still to close is 1 - smoothstep(i / ONSET))."""
    video = make_hand_video(n_frames=n, steady_from=0, seed=seed)
    centre = video.joints_w[PALM].mean(0)
    fingers = np.setdiff1d(np.arange(21), PALM)
    x = np.clip(np.arange(n) / ONSET, 0.0, 1.0)
    left = 1.0 - x * x * (3 - 2 * x)
    kp = video.keypoints.copy()
    for i in range(n):
        X = video.joints_w.copy()
        X[fingers] += reach * left[i] * (centre - X[fingers])
        T_c_w = inv_T(video.T_w_c[i])
        shift = project(video.K, X @ T_c_w[:3, :3].T + T_c_w[:3, 3]) - project(
            video.K, video.joints_c[i]
        )
        seen = kp[i, :, 2] > 0
        kp[i, seen, :2] += shift[seen]
    return kp, video.K


def test_onset_of_a_hand_that_slows_down():
    """The refined onset (matched filter on the direction of the last motion) is within 3
    frames in at least 4 of 5 scenes and later than the coarse energy onset, which is 3-7
    frames early here (measured: refined -5, -2, -3, -3, -3; coarse -6, -6, -4, -4, -5; with
    growth by whole blocks, select_steady/9: refined -3, -2, -3, -3, -3)."""
    errors, coarse = [], []
    for seed in range(5):
        kp, K = _slowing_hand(seed)
        sel = select_steady(kp, K, None)
        assert sel.method is SteadyMethod.DETECTED
        assert sel.steady_from == int(np.argmax(sel.cusum))
        assert sel.pattern_px.shape == (21, 2)
        np.testing.assert_allclose(np.linalg.norm(sel.pattern_px), 1.0)
        # growth takes blocks of down to 2 frames: the coarse onset may fall inside the last
        # (measured: the model starts 1, 0, 1, 0, 2 frames before it)
        assert sel.model_frames.min() >= sel.coarse_from - SelectSteadyConfig().grow_min_frames
        errors.append(sel.steady_from - ONSET)
        coarse.append(sel.coarse_from - ONSET)
    errors, coarse = np.array(errors), np.array(coarse)
    assert (np.abs(errors) <= 3).sum() >= 4, errors
    assert np.all(errors >= coarse) and np.mean(errors - coarse) >= 1.5, (errors, coarse)


def test_steady_frames_stay_steady():
    """Before the onset the projection on the last motion's direction stands out; after it
    the steady frames are noise (median |z| < 1.5)."""
    kp, K = _slowing_hand(7)
    sel = select_steady(kp, K, None)
    assert np.nanmedian(sel.z[ONSET - 12 : ONSET - 4]) > 3.0
    assert np.nanmedian(np.abs(sel.z[ONSET + 3 :])) < 1.5


def test_onset_moves_past_a_frame_without_the_hand():
    """A dropped detection (confidence 0 everywhere) at the detected onset moves the onset to
    the next detected frame: the first steady frame anchors the cameras and needs a pose of
    its own (the demo's bottle s7 #2: onset on such a frame, cameras 3.85 deg off)."""
    kp, K = _slowing_hand(0)
    onset = select_steady(kp, K, None).steady_from
    kp[onset : onset + 2, :, 2] = 0.0
    sel = select_steady(kp, K, None)
    assert sel.steady_from == onset + 2, (onset, sel.steady_from)
    assert int(np.argmax(sel.cusum)) in (onset, onset + 1)
    assert "not detected" not in sel.uncertain  # two frames skipped: within the tolerance


def test_an_onset_moved_past_many_frames_without_the_hand_is_marked():
    """Five frames without a detection from the detected onset: the grasp may have ended
    anywhere among them, so the onset taken after them is marked uncertain (select_steady/13;
    wild [94397, 22]: 4 frames skipped, +4, unmarked before)."""
    kp, K = _slowing_hand(0)
    onset = select_steady(kp, K, None).steady_from
    kp[onset : onset + 5, :, 2] = 0.0
    sel = select_steady(kp, K, None)
    assert sel.steady_from == onset + 5
    assert f"not detected in frames {onset}-{onset + 4}" in sel.uncertain
    off = select_steady(kp, K, None, SelectSteadyConfig(max_undetected_skip=10))
    assert "not detected" not in off.uncertain


def _late_still_camera(seed: int, steady: int = 20, turn: int = 60, n: int = 120):
    """Keypoints (n, 21, 3) and K of ``make_hand_video``'s hand, steady from ``steady``,
    whose virtual camera turns as usual until frame ``turn`` and then only 3 deg about the
    hand's centre: the final 60 frames have little parallax, so a hand reconstructed from
    them alone fits the earlier steady viewpoints poorly."""
    video = make_hand_video(n_frames=n, steady_from=steady, seed=seed)
    axis = np.random.default_rng(seed + 100).normal(size=3)
    axis /= np.linalg.norm(axis)
    kp = video.keypoints.copy()
    centre = video.joints_w.mean(0)
    for i in range(turn, n):
        R = Rotation.from_rotvec(np.deg2rad(3.0) * (i - turn) / (n - turn) * axis).as_matrix()
        T_c_w = inv_T(make_T(R, centre - R @ centre) @ video.T_w_c[turn])
        uv = project(video.K, video.joints_w @ T_c_w[:3, :3].T + T_c_w[:3, 3])
        seen = kp[i, :, 2] > 0  # the detections keep their noise and gross errors
        kp[i, seen, :2] += uv[seen] - project(video.K, video.joints_c[i])[seen]
    return kp, video.K


def _grown_and_plain(seed: int) -> tuple[int, int, int]:
    """(onset error, model's first frame) with growth and the onset error without."""
    kp, K = _late_still_camera(seed)
    sel = select_steady(kp, K, None)
    plain = select_steady(kp, K, None, SelectSteadyConfig(grow_frames=0))
    return sel.steady_from - 20, int(sel.model_frames[0]), plain.steady_from - 20


def test_model_grows_back_over_early_steady_viewpoints():
    """Steady from 20, the last 60 frames nearly still (seed 4): growing the hand model
    backwards brings its first frame to <= 26 and the onset within 3 frames (measured -1,
    model from 16); without growth it is more than 10 frames late (measured +14)."""
    grown, first, plain = _grown_and_plain(4)
    assert first <= 26 and abs(grown) <= 3 and plain > 10, (grown, first, plain)


@pytest.mark.slow
def test_model_grows_back_over_eight_scenes():
    """The same for seeds 0-7: every grown model starts at <= 26 and every onset is within
    -3 .. +7 frames (measured 0, 0, -1, 0, -1, -2, -2, 0; by whole blocks, select_steady/9:
    +1, 0, +5, +6, -1, +1, -2, +1); without growth at least 2 of the 8 are more than 10
    frames late (measured +1, +11, +5, +6, +14, +1, +4, +1)."""
    runs = np.array([_grown_and_plain(seed) for seed in range(8)])
    assert np.all(runs[:, 1] <= 26), runs
    assert np.all((runs[:, 0] >= -3) & (runs[:, 0] <= 7)), runs
    assert np.sum(runs[:, 2] > 10) >= 2, runs


def test_refine_poses_matches_opencv_on_inliers():
    """All frames at once under a Huber loss with gross outliers rejected: the same poses
    as cv2.solvePnPRefineLM on the true inliers, within 0.05 deg and 0.5 mm."""
    video = make_hand_video(n_frames=20, steady_from=0, seed=3)
    X, K = video.joints_w, video.K
    uv = video.keypoints[..., :2]
    use = video.keypoints[..., 2] > 0
    rng = np.random.default_rng(0)
    start = np.array([inv_T(T) for T in video.T_w_c])
    start[:, :3, 3] += rng.normal(0, 0.003, (len(start), 3))  # 3 mm off
    T = refine_poses(K, X, uv, use, start, huber_px=1e6, outlier_px=15.0)
    for i in range(len(T)):
        inl = use[i] & ~video.outlier[i]
        T_true = inv_T(video.T_w_c[i])
        rvec, tvec = cv2.Rodrigues(T_true[:3, :3])[0], T_true[:3, 3].reshape(3, 1).copy()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl], uv[i, inl], K, None, rvec, tvec)
        ref = np.eye(4)
        ref[:3, :3], ref[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        rot_deg, trans_m = pose_error(T[i], ref)
        assert rot_deg < 0.05 and trans_m < 5e-4, (i, rot_deg, trans_m)
    res, _ = residual_vectors(K, T, X, uv)
    clean = use & ~video.outlier
    assert np.sqrt(np.mean(np.sum(res[clean] ** 2, axis=1))) == pytest.approx(
        2.5 * np.sqrt(2), rel=0.2
    )


def test_clean_keypoints_keep_the_later_of_their_onset_and_the_depths(monkeypatch):
    """A depth change point 8 frames early (the settling too slow for the depth's gap, as at
    120 frames) does not pull a clean keypoint onset early: the later of the two stands
    (``later_of_both``); without the rule, or with noisy keypoints, the depth's stands."""
    from graspcap.tasks.hand_sfm import steady_depth

    kp, K = _slowing_hand(0)
    n = len(kp)
    early = ONSET - 8

    def depth_onset(uv, ok, K_, onset, depth_frame, T, cfg):
        return early, np.zeros(n), np.zeros(n), False

    monkeypatch.setattr(steady_depth, "onset_from_depth", depth_onset)
    args = dict(depth_frame=lambda i: np.zeros((4, 4)), T_color_turntable=np.eye(4))
    keypoints_only = select_steady(kp, K, None, SelectSteadyConfig(depth_onset=False))
    assert keypoints_only.steady_from > early + 2  # measured -5 from ONSET, early is -8
    both = select_steady(kp, K, None, **args)
    assert both.depth_from == early and both.steady_from == keypoints_only.steady_from
    depth_alone = select_steady(kp, K, None, SelectSteadyConfig(later_of_both=False), **args)
    assert depth_alone.steady_from == early + SelectSteadyConfig().depth_lag_frames
    noisy = kp.copy()
    seen = noisy[..., 2] > 0
    noisy[seen, :2] += np.random.default_rng(1).normal(0, 12.0, (seen.sum(), 2))
    assert select_steady(noisy, K, None, **args).steady_from <= early + 1


def test_halved_blocks_bring_the_grown_model_to_the_onset():
    """Seeds 2 and 3: growing by whole blocks of 8 stops a block short of the onset, which is
    then 5-6 frames late (measured +5, +6; model from 21, 22); halving a rejected block down
    to two frames (``grow_min_frames``) brings it within 2 (measured -1, 0; model from 19, 18)."""
    for seed in (2, 3):
        kp, K = _late_still_camera(seed)
        halved = select_steady(kp, K, None)
        blocks = select_steady(kp, K, None, SelectSteadyConfig(grow_min_frames=8))
        assert blocks.steady_from - 20 > 3, (seed, blocks.steady_from)
        assert abs(halved.steady_from - 20) <= 2, (seed, halved.steady_from)
        assert halved.model_frames[0] < blocks.model_frames[0], seed


def test_matched_filter_never_moves_the_onset_before_the_energys():
    """Before the coarse onset (frame 10) the hand moves one way and then turns back, so
    each frame's residual points against the sum of the others: the filter's CUSUM falls from
    its window's start, which is where its onset would land; ``earliest`` keeps it at or
    after the coarse onset."""
    rng = np.random.default_rng(0)
    res = rng.normal(0.0, 1.0, (40, 21, 2))
    v = rng.normal(0.0, 3.0, (21, 2))
    res[2:9] += v
    res[9] -= 10 * v
    free = matched_filter(res, 10, 8, 1.0, 6, 3, latest=14)
    held = matched_filter(res, 10, 8, 1.0, 6, 3, latest=14, earliest=10)
    assert free[3] == 2, free[3]
    assert 10 <= held[3] <= 14, held[3]
    assert held[3] == int(np.argmax(held[2]))
