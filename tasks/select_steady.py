"""Stage: the first steady frame, from the manifest or detected from the keypoints.

Detection, a change point in how rigid the hand is:

1. The end of the video is certainly steady, so a fixed 3D hand is reconstructed (up to
   scale) from a window of final frames.
2. Every frame is posed against that hand (robust PnP); its residual vectors (21 x 2 px) are
   what no rigid motion of the fixed hand explains. Gross detection errors are dropped.
3. While the fingers still close, the residuals are a smooth signal that changes little
   between neighbouring frames, while detection noise is independent per frame; averaging the
   residual vectors over a short centred window keeps the one and shrinks the other, so the
   closing stays visible far closer to the onset than a per-frame error norm.
4. The window energy is standardised by its median and robust spread (MAD) over the steady
   reference frames, which is the known noise level of that video.
5. The onset is the change point ``t`` maximising ``sum_{i < t} (z_i - drift)`` (a CUSUM):
   frames before it must on average stand out by more than ``drift`` noise spreads; a single
   spike in the steady phase or a dip during closing does not move it.
6. The hand is rebuilt from all frames found steady and the frames re-scored.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from graspcap.tasks.config import StageConfig
from graspcap.tasks.errors import StageError
from graspcap.tasks.sfm_graph import bundle_adjust
from graspcap.tasks.sfm_init import initialise, pnp

STAGE = "select_steady"
STAGE_VERSION = "select_steady/2"


class SteadyMethod(StrEnum):
    """Where ``steady_from`` came from."""

    MANIFEST = "manifest"
    DETECTED = "detected"


class SelectSteadyConfig(StageConfig):
    window_frames: int = 60
    """Final frames assumed steady for the first hand model (at most ``window_share``)."""
    window_share: float = 0.7
    """Largest share of the video the first window may take."""
    model_frames: int = 40
    """Evenly spaced frames of a window that the hand model is reconstructed from."""
    pair_candidates: int = 10
    """Evenly spaced frames of the first window among which the two-view start is chosen."""
    min_confidence: float = 0.2
    """Detections with a lower confidence are treated as missing."""
    ransac_px: float = 8.0
    """RANSAC threshold (pixels) of the initialisation and of the per-frame PnP."""
    outlier_px: float = 15.0
    """Residuals longer than this (pixels) are gross detection errors and ignored."""
    smooth_frames: int = 3
    """Centred window (frames) over which residual vectors are averaged."""
    drift_sigmas: float = 2.0
    """CUSUM drift: how many noise spreads a frame must stand out by to count as moving."""
    min_points: int = 6
    """A frame needs this many detected joints to be scored."""
    refinements: int = 3
    """At most this many times the hand is re-adjusted over the frames found steady and the
    frames re-scored (stops when the onset settles)."""
    ba_iterations: int = 60
    """Levenberg-Marquardt iterations of the hand model's bundle adjustment."""


PRESETS: dict[str, SelectSteadyConfig] = {
    "default": SelectSteadyConfig(),
    "openpose": SelectSteadyConfig(ransac_px=12.0, outlier_px=25.0, drift_sigmas=2.5),
}


@dataclass(frozen=True)
class SteadySelection:
    """The chosen first steady frame and how it was chosen.

    steady_from : video frame index; method : manifest or detected.
    scores_px : (n,) float, per frame the RMS length (px) of the window-averaged residual
        vectors against the fixed hand, scaled to one frame's noise (NaN where not scored;
        all NaN from the manifest).
    z : (n,) float, the scores standardised by the steady reference frames (NaN likewise).
    threshold_px : the score a frame needs to count as moving, median + drift * spread of the
        reference frames (NaN from the manifest).
    cusum : (n + 1,) float, ``sum_{i < t} (z_i - drift)`` for every candidate onset ``t``;
        the onset is its argmax (empty from the manifest).
    model_frames : (k,) int, video frames the final hand model was reconstructed from.
    """

    steady_from: int
    method: SteadyMethod
    scores_px: np.ndarray
    threshold_px: float
    z: np.ndarray
    cusum: np.ndarray
    model_frames: np.ndarray


def _bundle(uv, ok, K, cfg, frames, T_c_w, X, anchor, scale_ref):
    """Bundle adjustment of the given frames; (T_c_w (k, 4, 4), joints (21, 3))."""
    ba = bundle_adjust(
        uv[frames],
        ok[frames],
        np.full(ok[frames].shape, 2.5),
        K,
        T_c_w,
        X,
        anchor=anchor,
        scale_ref=scale_ref,
        huber_k=2.0,
        scale_sigma_rel=1e-3,
        max_iterations=cfg.ba_iterations,
    )
    return ba.T_c_w, ba.points_w


def _reconstruct(uv, ok, K, cfg, frames):
    """Up-to-scale joints (21, 3) from the given frames, None without enough parallax."""
    init, _ = initialise(
        uv[frames],
        ok[frames],
        K,
        n_candidates=cfg.pair_candidates,
        ransac_px=cfg.ransac_px,
        min_points=cfg.min_points,
        min_parallax_deg=2.0,
    )
    if init is None:
        return None
    a, b = init.pair.a, init.pair.b
    return _bundle(uv, ok, K, cfg, frames, init.T_c_w, init.points_w, a, b)[1]


def _refine(uv, ok, K, cfg, frames, T_c_w, X):
    """The hand re-adjusted over ``frames``, warm-started from per-frame PnP poses (n, 4, 4)
    against ``X``; None when fewer than two of the frames are posed."""
    T = T_c_w[frames]
    posed = np.flatnonzero(np.all(np.isfinite(T.reshape(len(frames), -1)), axis=1))
    if len(posed) < 2:
        return None
    a, b = int(posed[0]), int(posed[-1])
    return _bundle(uv, ok, K, cfg, frames, T, X, a, b)[1]


def _spread(first: int, n: int, k: int) -> np.ndarray:
    """At most k evenly spaced frames of first .. n-1."""
    return np.unique(np.linspace(first, n - 1, min(k, n - first)).round().astype(int))


def _fixed_hand(uv, ok, K, cfg, n, max_frames):
    """Joints from (at most ``max_frames`` of) the final window, growing it until it has
    parallax; (X, frames)."""
    window = min(cfg.window_frames, max(int(cfg.window_share * n), 2))
    while True:
        frames = _spread(n - window, n, max_frames)
        X = _reconstruct(uv, ok, K, cfg, frames)
        if X is not None:
            return X, frames
        if window >= n:
            raise StageError(
                STAGE,
                "cannot detect the steady phase: no frame pair of the video has enough "
                "parallax to reconstruct the hand; set grasp.steady_from in session.json",
            )
        window = min(2 * window, n)


def _residual_vectors(K, X, uv, ok, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's robust PnP against X: residual vectors (n, 21, 2) px and T_c_w (n, 4, 4),
    NaN where unknown."""
    n = len(uv)
    out = np.full((n, 21, 2), np.nan)
    poses = np.full((n, 4, 4), np.nan)
    known = np.all(np.isfinite(X), axis=1)
    for i in range(n):
        sel = ok[i] & known
        if sel.sum() < cfg.min_points:
            continue  # no detection (or too few joints): not scored
        T = pnp(K, X[sel], uv[i, sel], cfg.ransac_px, cfg.min_points)
        if T is None:
            continue
        poses[i] = T
        Xc = X[sel] @ T[:3, :3].T + T[:3, 3]
        proj = (Xc[:, :2] / Xc[:, 2:]) * np.diag(K)[:2] + K[:2, 2]
        out[i, sel] = uv[i, sel] - proj
    gross = np.linalg.norm(out, axis=2) > cfg.outlier_px
    out[gross] = np.nan
    return out, poses


def _window_scores(res: np.ndarray, half: int, min_points: int) -> np.ndarray:
    """(n,) RMS px of the residual vectors averaged over frames i-half .. i+half.

    Each joint's mean vector is weighted by its count, so pure noise gives the same expected
    score whatever the window holds.
    """
    n = len(res)
    valid = np.isfinite(res[..., 0])
    filled = np.where(valid[..., None], res, 0.0)
    c_sum = np.concatenate([np.zeros((1, 21, 2)), np.cumsum(filled, axis=0)])
    c_cnt = np.concatenate([np.zeros((1, 21)), np.cumsum(valid, axis=0)])
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) + half + 1, 0, n)
    total = c_sum[hi] - c_sum[lo]
    count = c_cnt[hi] - c_cnt[lo]
    energy = np.sum(total**2, axis=2) / np.maximum(count, 1)  # count * |mean|^2
    seen = count > 0
    scores = np.sqrt(np.sum(energy, axis=1) / np.maximum(seen.sum(1), 1))
    scores[(seen.sum(1) < min_points) | ~valid.any(1)] = np.nan
    return scores


def _score(K, X, uv, ok, cfg, ref):
    """(onset, z, cusum, threshold, scores_px, poses) of every frame against the hand X."""
    res, poses = _residual_vectors(K, X, uv, ok, cfg)
    scores = _window_scores(res, cfg.smooth_frames // 2, cfg.min_points)
    return (*_change_point(scores, ref, cfg.drift_sigmas), scores, poses)


def _change_point(scores, ref, drift):
    """(onset, z, cusum, threshold) of the scores against the reference frames ``ref``."""
    ref_scores = scores[ref][np.isfinite(scores[ref])]
    if len(ref_scores) < 3:
        raise StageError(STAGE, "cannot detect the steady phase: too few final frames posed")
    med = float(np.median(ref_scores))
    spread = max(1.4826 * float(np.median(np.abs(ref_scores - med))), 1e-3 * max(med, 1e-9))
    z = (scores - med) / spread
    cusum = np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(z), z - drift, 0.0))])
    return int(np.argmax(cusum)), z, cusum, med + drift * spread


def select_steady(
    keypoints: np.ndarray,
    K: np.ndarray,
    steady_from: int | None,
    config: SelectSteadyConfig = PRESETS["default"],
) -> SteadySelection:
    """The first steady frame: the manifest's ``steady_from`` when given, else detected.

    Parameters
    ----------
    keypoints : (n, 21, 3) float, x, y pixels and confidence per video frame (a frame without
        a detection has confidence 0 everywhere).
    K : (3, 3) colour intrinsics.
    steady_from : the manifest's value, or None to detect it.
    """
    cfg = config
    kp = np.asarray(keypoints, dtype=float)
    n = len(kp)
    if steady_from is not None:
        if not 0 <= steady_from < n:
            raise StageError(STAGE, f"grasp.steady_from = {steady_from} is outside 0..{n - 1}")
        nan = np.full(n, np.nan)
        return SteadySelection(
            int(steady_from), SteadyMethod.MANIFEST, nan, np.nan, nan, np.empty(0), np.empty(0, int)
        )
    K = np.asarray(K, dtype=float)
    uv = kp[..., :2]
    ok = (kp[..., 2] >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)
    if (ok.sum(1) >= cfg.min_points).sum() < 5:
        raise StageError(
            STAGE,
            f"cannot detect the steady phase: fewer than 5 frames have >= "
            f"{cfg.min_points} detected joints",
        )
    half = cfg.smooth_frames // 2
    X, model = _fixed_hand(uv, ok, K, cfg, n, cfg.model_frames)
    ref = np.arange(model[0], n)
    onset, z, cusum, threshold, scores, poses = _score(K, X, uv, ok, cfg, ref)
    if onset > model[0] + half + 1:
        # The model's own frames look moving: a poor start (or a very long adjustment).
        # Retry from every frame of the window; keep it when it is self-consistent.
        X2, model2 = _fixed_hand(uv, ok, K, cfg, n, n)
        if len(model2) > len(model):
            scored = _score(K, X2, uv, ok, cfg, np.arange(model2[0], n))
            if scored[0] <= model2[0] + half + 1:
                X, model, ref = X2, model2, np.arange(model2[0], n)
                onset, z, cusum, threshold, scores, poses = scored
    for _ in range(cfg.refinements):
        # More viewpoints give a better hand for the next pass; skip the smoothing margin.
        first = min(onset + half + 1, n - 3)
        frames = _spread(first, n, cfg.model_frames)
        if np.array_equal(frames, model):
            break
        X_new = _refine(uv, ok, K, cfg, frames, poses, X)
        if X_new is None:
            break
        X, model, ref = X_new, frames, np.arange(first, n)
        onset, z, cusum, threshold, scores, poses = _score(K, X, uv, ok, cfg, ref)
    if onset >= n - 2:
        raise StageError(
            STAGE,
            "cannot detect the steady phase: the final frames are not explained by "
            "one rigid hand; set grasp.steady_from in session.json",
        )
    return SteadySelection(
        steady_from=onset,
        method=SteadyMethod.DETECTED,
        scores_px=scores,
        threshold_px=threshold,
        z=z,
        cusum=cusum,
        model_frames=model,
    )
