"""Real frames (issue 19 item 6): the pipeline's MediaPipe detector and the pixels-only
static-hand solve of ``reconstruct_hand`` on the 20 real CORe50 frames of
``../shared/data/core50_handheld_real`` (``bench/core50_consistency.py``). A consistency check
on real detections, not an accuracy figure: the facts asserted are those docs/benchmarks.md
reports, with tolerances for the solver's numerics."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

from tests.conftest import REPO


def _bench():
    spec = importlib.util.spec_from_file_location(
        "core50_consistency", REPO / "bench" / "core50_consistency.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def clip(shared_data):
    frames = shared_data / "core50_handheld_real" / "clip_bulb" / "frames"
    if not frames.is_dir():
        pytest.skip(f"{frames} is absent")
    pytest.importorskip("mediapipe", reason="the mediapipe backend is not installed "
                                            "(docs/detectors.md)")
    bench = _bench()
    paths = bench.frame_paths(frames)
    kp, corrupt = bench.detect(paths)
    return bench, paths, kp, corrupt


def test_every_real_frame_has_a_detection(clip):
    _, paths, kp, corrupt = clip
    assert len(paths) == 20
    assert int((kp[..., 2] > 0).any(1).sum()) == 20 and corrupt == {}
    assert int((kp[..., 2] > 0).sum()) == 420  # every joint of every frame


def test_one_static_hand_explains_the_real_clip(clip, tmp_path):
    bench, paths, kp, _ = clip
    facts, T_c_w, X, res, _ = bench.static_hand(kp, bench.FOCAL_PX)
    assert facts.frames_posed == 20
    assert facts.inliers >= 415 and facts.inlier_share >= 0.985  # measured 419 / 420
    assert 2.3 <= facts.rmse_px <= 3.2  # measured 2.73 px
    assert 40.0 <= facts.turn_deg <= 60.0  # measured 49.3 deg
    assert facts.max_step_deg <= 30.0  # measured 20.1 deg
    assert facts.one_static_hand
    # the assumed focal length barely matters (350 and 1000 px: 2.71, 2.77 px)
    for f in (350.0, 1000.0):
        other = bench.static_hand(kp, f)[0]
        assert abs(other.rmse_px - facts.rmse_px) < 0.3 and other.inliers >= 415
    out = bench.draw(paths, kp, facts, T_c_w, X, res, tmp_path / "hand.png")
    assert out.stat().st_size > 10_000


def test_the_controls_show_what_the_check_can_and_cannot_tell(clip):
    """Frames the static hand should not explain: swapped thumb and little finger lose a
    third of the inliers; a mirrored hand (the other hand) in every other frame is rejected
    whole by reconstruct_hand's frame screening (the cameras of the two interleaved sets
    jump by the mirror between neighbours; of the two smooth chains the better explained,
    the real frames', is kept): only the 10 real frames keep inliers, and one static hand no
    longer explains the clip."""
    bench, _, kp, _ = clip
    real = bench.static_hand(kp, bench.FOCAL_PX)[0]
    swapped = bench.static_hand(bench.CONTROLS["thumb/little swapped"](kp), bench.FOCAL_PX)[0]
    assert swapped.inlier_share < real.inlier_share - 0.25  # measured 0.629 against 0.998
    mirrored, _, _, _, inlier = bench.static_hand(bench.CONTROLS["mirrored (other hand)"](kp),
                                                  bench.FOCAL_PX)
    assert not mirrored.one_static_hand  # measured 0.495
    assert mirrored.inlier_share < 0.6
    # the control mirrors frames 0, 2, ..., 18: every one rejected whole, every real one kept
    np.testing.assert_array_equal(np.flatnonzero(inlier.any(1)), np.arange(1, 20, 2))
