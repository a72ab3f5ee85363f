"""``select_steady``'s steps 1-4: the onset from the 2D keypoints alone.

A hand is fitted to late frames (up to scale: two-view start, bundle adjustment), every frame
posed against it by PnP, and each frame's residual, smoothed over a window, scored against
the final frames'; the CUSUM change point of those scores is the coarse onset. The hand is
refitted from more viewpoints after it, grown backwards while earlier frames fit it, and the
onset refined by the matched filter of the last motion (``steady_stats.matched_filter``).
The module docstring of ``select_steady`` gives the steps in full; this module is their code.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import umeyama
from graspcap.tasks.hand_sfm.batch_pnp import ransac_poses, refine_poses, residual_vectors
from graspcap.tasks.hand_sfm.graph import bundle_adjust
from graspcap.tasks.hand_sfm.steady_stats import cusum, matched_filter, standardise, window_scores
from graspcap.tasks.hand_sfm.two_view_init import initialise

if TYPE_CHECKING:
    from graspcap.tasks.hand_sfm.select_steady import SelectSteadyConfig

STAGE = "select_steady"  # the stage these steps' errors belong to


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
        n_hypotheses=cfg.pair_hypotheses,
        n_check_frames=cfg.check_frames,
    )
    if init is None:
        return None
    a, b = init.pair.a, init.pair.b
    return _bundle(uv, ok, K, cfg, frames, init.T_c_w, init.points_w, a, b)[1]


def _refine(uv, ok, K, cfg, frames, T_c_w, X):
    """The hand re-adjusted over ``frames``, warm-started from per-frame poses (n, 4, 4)
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


def _same_gauge(X_new, X_old):
    """``X_new`` (21, 3) moved by the similarity that best maps it onto ``X_old``, so that
    poses found against ``X_old`` stay good starts (a bundle's gauge may drift)."""
    both = np.all(np.isfinite(X_new), axis=1) & np.all(np.isfinite(X_old), axis=1)
    if both.sum() < 3:
        return X_new
    T, s = umeyama(X_new[both], X_old[both])
    return s * X_new @ T[:3, :3].T + T[:3, 3]


def _pose_frames(K, X, uv, ok, cfg, start=None):
    """Every frame posed against X: T_c_w (n, 4, 4) (NaN where unknown) and residual vectors
    (n, 21, 2) px (NaN where unknown or gross). ``start`` warm-starts the refinement (4 steps,
    not 8); frames without a start pose, and those the warm start leaves mostly unexplained
    (the hand changed too much for it), get a RANSAC one."""
    known = np.all(np.isfinite(X), axis=1)
    use = ok & known[None]
    scored = use.sum(1) >= cfg.min_points
    T = np.full((len(uv), 4, 4), np.nan) if start is None else np.array(start)
    cold = scored & ~np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    for attempt in range(2):
        if cold.any():
            T[cold] = ransac_poses(K, X, uv[cold], use[cold], cfg.ransac_px, cfg.min_points)[0]
        T = refine_poses(K, X, uv, use, T, huber_px=cfg.huber_px, outlier_px=cfg.outlier_px,
                         iterations=8 if start is None else 4)  # fmt: skip
        res, Xc = residual_vectors(K, np.nan_to_num(T), np.nan_to_num(X), uv)
        near = use & (np.linalg.norm(res, axis=2) < cfg.outlier_px)
        lost = scored & ~cold & (near.sum(1) < 0.5 * use.sum(1))
        if attempt or start is None or not lost.any():
            break
        cold = lost
    res[~use | (Xc[..., 2] <= 0) | (np.linalg.norm(res, axis=2) > cfg.outlier_px)] = np.nan
    res[~scored] = np.nan
    front = np.sum(use & (Xc[..., 2] > 0), axis=1) > 0.5 * np.maximum(use.sum(1), 1)
    bad = ~np.all(np.isfinite(T.reshape(len(T), -1)), axis=1) | ~front
    res[bad], T[bad] = np.nan, np.nan
    return T, res


def _coarse(res, ref, cfg):
    """(onset, scores, threshold) of the windowed residual energy against frames ``ref``."""
    scores = window_scores(res, cfg.smooth_frames // 2, cfg.min_points)
    found = standardise(scores, ref)
    if found is None:
        raise StageError(STAGE, "cannot detect the steady phase: too few final frames posed")
    z, med, spread = found
    onset = int(np.argmax(cusum(z, cfg.drift_sigmas)))
    return onset, scores, med + cfg.drift_sigmas * spread


def detect_onset(uv, ok, K, cfg: SelectSteadyConfig):
    """(coarse onset, scores, threshold, matched result or None, model frames)."""
    n = len(uv)
    half = cfg.smooth_frames // 2
    X, model = _fixed_hand(uv, ok, K, cfg, n, cfg.model_frames)
    T, res = _pose_frames(K, X, uv, ok, cfg)
    onset, scores, threshold = _coarse(res, np.arange(model[0], n), cfg)
    if onset > model[0] + half + 1:
        # The model's own frames look moving: a poor start (or a very long adjustment).
        # Retry from every frame of the window; keep it when it is self-consistent.
        X2, model2 = _fixed_hand(uv, ok, K, cfg, n, n)
        if len(model2) > len(model):
            T2, res2 = _pose_frames(K, X2, uv, ok, cfg)
            coarse2 = _coarse(res2, np.arange(model2[0], n), cfg)
            if coarse2[0] <= model2[0] + half + 1:
                X, model, T, res = X2, model2, T2, res2
                onset, scores, threshold = coarse2
    for _ in range(cfg.refinements):
        # More viewpoints give a better hand for the next pass; skip the smoothing margin.
        first = min(onset + half + 1, n - 3)
        frames = _spread(first, n, cfg.model_frames)
        if np.array_equal(frames, model):
            break
        X_new = _refine(uv, ok, K, cfg, frames, T, X)
        if X_new is None:
            break
        X, model = _same_gauge(X_new, X), frames
        T, res = _pose_frames(K, X, uv, ok, cfg, start=T)
        onset_new, scores, threshold = _coarse(res, np.arange(first, n), cfg)
        settled = onset_new == onset
        onset = onset_new
        if settled:
            break
    # Grow backwards: a hand fitted to late viewpoints can make earlier steady frames look
    # moving. Refit with the block of frames just before the model's; keep it while the
    # block then fits as well as the model's own frames did before (a moving block, pulled
    # into the fit, still stands out and worsens the fit of the others).
    before, rejected = (X, T, res, model, onset, scores, threshold), -1
    step = cfg.grow_frames
    while step > 0 and model[0] > 0:
        first = int(model[0])
        lo = max(first - step, 0)
        ref = standardise(window_scores(res, half, cfg.min_points), np.arange(first, n))
        if ref is None:
            break
        _, med, spread = ref
        frames = np.union1d(np.arange(lo, first), _spread(first, n, cfg.model_frames))
        X_new = _refine(uv, ok, K, cfg, frames, T, X)
        if X_new is None:
            break
        X_new = _same_gauge(X_new, X)
        T_new, res_new = _pose_frames(K, X_new, uv, ok, cfg, start=T)
        z_block = (window_scores(res_new, half, cfg.min_points)[lo:first] - med) / spread
        if not np.nanmean(z_block) <= cfg.grow_z:
            rejected = lo
            step = step // 2 if step // 2 >= cfg.grow_min_frames else 0
            continue
        X, T, res, model = X_new, T_new, res_new, frames
    if model[0] < before[3][0]:
        onset, scores, threshold = _coarse(res, np.arange(model[0], n), cfg)
        if onset < rejected:
            # The grown hand calls steady a block the growth found moving: it absorbed a
            # slow motion, so the hand before the growth stands.
            X, T, res, model, onset, scores, threshold = before
    matched, guess, seen = None, onset, set()
    latest = onset + cfg.pattern_frames // 2
    for _ in range(cfg.pattern_passes):
        found = matched_filter(res, guess, cfg.pattern_frames, cfg.pattern_drift_sigmas,
                               cfg.min_points, cfg.smooth_frames, latest, onset)  # fmt: skip
        if found is None:
            break
        matched = found
        seen.add(guess)
        guess = found[3]
        if guess in seen:
            break
    return onset, scores, threshold, matched, model
