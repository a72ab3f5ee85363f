"""The oracle detections of ``bench/wild_joint_floor.py`` (docs/benchmarks.md, "Session 31:
where the wild joints' error comes from") are what its docstring says: the noise of
``truth+S`` has a mean length of S of the hand's image size, the gross frames are the ones the
rig corrupted, and ``no_gross`` / ``truth`` keep the detections' missing joints missing."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

from tests.conftest import REPO


@pytest.fixture(scope="module")
def floor():
    sys.path.insert(0, str(REPO / "bench"))  # it imports keypoint_floor beside it
    try:
        spec = importlib.util.spec_from_file_location(
            "wild_joint_floor", REPO / "bench" / "wild_joint_floor.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(REPO / "bench"))
    return module


def _hand(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(detections (n, 21, 3), true projections (n, 21, 2)): a 100 px hand, 2 px noise."""
    clean = rng.uniform(300.0, 370.0, (n, 21, 2))
    kp = np.concatenate([clean + rng.normal(0.0, 2.0, clean.shape), np.ones((n, 21, 1))], 2)
    return kp, clean


def test_truth_plus_share_noise_has_that_mean_share(floor):
    rng = np.random.default_rng(0)
    kp, clean = _hand(400, rng)
    out = floor.variant_keypoints("truth+6%", kp, clean, np.random.default_rng(1))
    size = np.linalg.norm(np.ptp(clean, axis=1), axis=1)
    share = np.linalg.norm(out[..., :2] - clean, axis=2).mean(axis=1) / size
    assert np.mean(share) == pytest.approx(0.06, rel=0.03)
    assert np.array_equal(out[..., 2], kp[..., 2])
    exact = floor.variant_keypoints("truth", kp, clean, np.random.default_rng(1))
    assert np.array_equal(exact[..., :2], clean)


def test_gross_frames_are_the_corrupted_ones(floor):
    rng = np.random.default_rng(2)
    kp, clean = _hand(10, rng)
    kp[3, :, :2] += 40.0                   # the whole hand elsewhere (40 % of its ~100 px)
    kp[6, 5:9, :2] = clean[6, 13:17]       # the index finger on the ring finger's place
    kp[8, :, 2] = 0.0                      # no detection: missing, not gross
    kp[9, 0, :2] += 30.0                   # one joint off: noise, not gross
    assert np.flatnonzero(floor.gross_frames(kp, clean)).tolist() == [3, 6]
    out = floor.variant_keypoints("no_gross", kp, clean, np.random.default_rng(3))
    assert np.all(out[[3, 6], :, 2] == 0.0) and np.all(out[[0, 9], :, 2] == 1.0)
    truth = floor.variant_keypoints("truth", kp, clean, np.random.default_rng(3))
    assert np.all(truth[8, :, 2] == 0.0)
