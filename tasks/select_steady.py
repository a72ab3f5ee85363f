"""Stage: the first steady frame, from the manifest or detected from the keypoints.

Detection: the end of the video is certainly steady, so a fixed 3D hand is reconstructed
(up to scale) from a window of final frames. Every frame is then posed against that hand
(PnP with RANSAC); while the fingers still close the joints move relative to the palm and no
rigid pose explains them, so the frame's robust reprojection error is high. The steady
phase is the final run of low-error frames (a 3-frame median filter ignores single spikes).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.ndimage import median_filter

from graspcap.tasks.config import StageConfig
from graspcap.tasks.errors import StageError
from graspcap.tasks.sfm_graph import bundle_adjust, reprojection_residuals
from graspcap.tasks.sfm_init import initialise, pnp

STAGE = "select_steady"
STAGE_VERSION = "select_steady/1"


class SteadyMethod(StrEnum):
    """Where ``steady_from`` came from."""

    MANIFEST = "manifest"
    DETECTED = "detected"


class SelectSteadyConfig(StageConfig):
    window_frames: int = 30
    """Final frames assumed steady, from which the fixed hand is reconstructed."""
    min_confidence: float = 0.2
    """Detections with a lower confidence are treated as missing."""
    ransac_px: float = 8.0
    """RANSAC threshold (pixels) of the initialisation and of the per-frame PnP."""
    trim_fraction: float = 0.2
    """Share of a frame's largest residuals ignored by its score (gross detection errors)."""
    threshold_factor: float = 1.6
    """A frame is moving when its score exceeds this multiple of the window's median score."""
    min_threshold_px: float = 2.0
    """Lower bound of that threshold (noise-free keypoints would give a zero median)."""
    min_points: int = 6
    """A frame needs this many detected joints to be scored."""
    refinements: int = 3
    """Times the hand is rebuilt from all frames found steady so far and the frames re-scored."""


PRESETS: dict[str, SelectSteadyConfig] = {
    "default": SelectSteadyConfig(),
    "openpose": SelectSteadyConfig(ransac_px=12.0, threshold_factor=2.0, min_threshold_px=4.0),
}


@dataclass(frozen=True)
class SteadySelection:
    """The chosen first steady frame.

    steady_from : video frame index; method : manifest or detected.
    scores_px : (n,) float, each frame's trimmed RMS reprojection error against the fixed
        hand (NaN where not scored; all NaN when taken from the manifest).
    threshold_px : the score above which a frame counted as moving (NaN from the manifest).
    """

    steady_from: int
    method: SteadyMethod
    scores_px: np.ndarray
    threshold_px: float


def _reconstruct(uv, ok, K, cfg, frames):
    """Up-to-scale joints (21, 3) from the given frames, None without enough parallax."""
    init, _ = initialise(
        uv[frames],
        ok[frames],
        K,
        n_candidates=10,
        ransac_px=cfg.ransac_px,
        min_points=cfg.min_points,
        min_parallax_deg=2.0,
    )
    if init is None:
        return None
    ba = bundle_adjust(
        uv[frames],
        ok[frames],
        np.full(ok[frames].shape, 2.5),
        K,
        init.T_c_w,
        init.points_w,
        anchor=init.pair.a,
        scale_ref=init.pair.b,
        huber_k=2.0,
        max_iterations=20,
    )
    return ba.points_w


def _fixed_hand(uv, ok, K, cfg, n):
    """Joints from the final window, growing it until it has parallax; (X, window)."""
    window = min(cfg.window_frames, n)
    while True:
        X = _reconstruct(uv, ok, K, cfg, np.arange(n - window, n))
        if X is not None:
            return X, window
        if window >= n:
            raise StageError(
                STAGE,
                "cannot detect the steady phase: no frame pair of the video has enough "
                "parallax to reconstruct the hand; set grasp.steady_from in session.json",
            )
        window = min(2 * window, n)


def _onset(scores: np.ndarray, threshold: float) -> int:
    """First frame of the final run of frames scoring at most ``threshold``."""
    moving = np.where(np.isnan(scores), False, scores > threshold)
    # Unscored frames inherit their predecessor's state, then single spikes are ignored.
    for i in np.flatnonzero(np.isnan(scores)):
        moving[i] = moving[i - 1] if i > 0 else False
    moving = median_filter(moving.astype(np.uint8), size=3, mode="nearest").astype(bool)
    last_moving = np.flatnonzero(moving)
    return int(last_moving[-1] + 1) if len(last_moving) else 0


def _score(K, X, uv, ok, cfg) -> float:
    """Trimmed RMS reprojection error (px) of the best rigid pose of X for one frame."""
    sel = ok & np.all(np.isfinite(X), axis=1)
    T = pnp(K, X[sel], uv[sel], cfg.ransac_px, cfg.min_points)
    if T is None:
        return float("inf") if sel.sum() >= cfg.min_points else float("nan")
    res = np.sort(reprojection_residuals(K, T[None], X[sel], uv[None, sel])[0])
    keep = max(int(np.ceil(len(res) * (1.0 - cfg.trim_fraction))), 1)
    return float(np.sqrt(np.mean(res[:keep] ** 2)))


def select_steady(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int | None,
    config: SelectSteadyConfig = PRESETS["default"],
) -> SteadySelection:
    """The first steady frame: the manifest's ``steady_from`` when given, else detected.

    Parameters
    ----------
    keypoints : (n, 21, 3) float, x, y pixels and confidence per video frame.
    K : (3, 3) colour intrinsics.
    steady_from : the manifest's value, or None to detect it.
    """
    cfg = config
    kp = np.asarray(keypoints, dtype=float)
    n = len(kp)
    if steady_from is not None:
        if not 0 <= steady_from < n:
            raise StageError(STAGE, f"grasp.steady_from = {steady_from} is outside 0..{n - 1}")
        return SteadySelection(int(steady_from), SteadyMethod.MANIFEST, np.full(n, np.nan), np.nan)
    K = np.asarray(K, dtype=float)
    uv = kp[..., :2]
    ok = (kp[..., 2] >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)
    if (ok.sum(1) >= cfg.min_points).sum() < 5:
        raise StageError(
            STAGE,
            f"cannot detect the steady phase: fewer than 5 frames have >= "
            f"{cfg.min_points} detected joints",
        )
    X, window = _fixed_hand(uv, ok, K, cfg, n)
    start, scores, threshold = n - window, np.full(n, np.nan), np.nan
    for _ in range(cfg.refinements + 1):
        scores = np.array([_score(K, X, uv[i], ok[i], cfg) for i in range(n)])
        ref = scores[start:][np.isfinite(scores[start:])]
        threshold = max(cfg.min_threshold_px, cfg.threshold_factor * float(np.median(ref)))
        new_start = _onset(scores, threshold)
        if new_start >= n - 2:
            raise StageError(
                STAGE,
                "cannot detect the steady phase: the final frames are not explained by "
                "one rigid hand; set grasp.steady_from in session.json",
            )
        if new_start == start:
            break
        start = new_start
        # More viewpoints give a better hand for the next pass (at most 40 frames of it).
        frames = np.unique(np.linspace(start, n - 1, min(40, n - start)).round().astype(int))
        X = _reconstruct(uv, ok, K, cfg, frames)
        if X is None:
            break
    return SteadySelection(start, SteadyMethod.DETECTED, scores, threshold)
