"""How far the hand and the object it holds deform between video frames, from the depth.

Before the grasp settles the surface of the hand and the object deforms from frame to frame
(the fingers close, the palm approaches, the object is lifted off the platter); from the
first steady frame on, two frames' surfaces differ by one rigid motion. The depth is far less
noisy than a real detector's keypoints, so that residual non-rigidity shows the last frames
of the adjustment where the keypoints' noise hides them.

For every frame ``i`` the surface (``surface_clouds.surface_cloud``: the depth within a sphere
around the hand's centre, the platter and table dropped) is registered rigidly
(``depth_links.icp_batch``, point-to-plane) onto frame ``i + gap``'s, both cut by the same
sphere, from the chained registrations of neighbouring frames. The signal is the share of
frame ``i``'s points that, after the registration, lie further than ``far_m`` from the other
surface (point-to-plane, or with no surface point within ``max_distance_m``): the share of the
surface that no rigid motion explains.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.hand_sfm.depth_links import icp_batch
from graspcap.tasks.hand_sfm.metric_scale import window_median
from graspcap.tasks.hand_sfm.steady_stats import cusum, standardise
from graspcap.tasks.hand_sfm.surface_clouds import SurfaceCloud, hand_centre, surface_cloud

if TYPE_CHECKING:
    from graspcap.tasks.hand_sfm.select_steady import SelectSteadyConfig


def hand_centres(
    depth_frame: Callable[[int], np.ndarray], K: np.ndarray, uv: np.ndarray, ok: np.ndarray,
    *, below_skin_m: float, min_points: int, smooth: int = 2, max_fill: int = 12,
) -> np.ndarray:
    """(n, 3) hand centres in the camera (``surface_clouds.hand_centre`` from the detected
    joints' depth readings), each the median over frames ``i - smooth .. i + smooth`` (a
    wrong detection moves it less); a frame without one takes the nearest frame's, at most
    ``max_fill`` frames away (the sphere around it is wide); NaN where unknown."""
    n = len(uv)
    raw = np.full((n, 3), np.nan)
    for i in range(n):
        if ok[i].sum() >= min_points:
            px = uv[i, ok[i]]
            c = hand_centre(K, px, window_median(depth_frame(i), px, 2), below_skin_m)
            if c is not None:
                raw[i] = c
    out = np.full((n, 3), np.nan)
    for i in range(n):
        win = raw[max(i - smooth, 0): i + smooth + 1]
        win = win[np.all(np.isfinite(win), axis=1)]
        if len(win):
            out[i] = np.median(win, axis=0)
    have = np.flatnonzero(np.all(np.isfinite(out), axis=1))
    for i in np.flatnonzero(~np.all(np.isfinite(out), axis=1)):
        if len(have):  # a frame without a detection: the nearest frame's centre
            near = have[np.argmin(np.abs(have - i))]
            if abs(near - i) <= max_fill:
                out[i] = out[near]
    return out


def _seen_through(depth_m: np.ndarray, K: np.ndarray, points: np.ndarray, T_a_b: np.ndarray,
                  far_m: float) -> float:
    """Share of ``points`` (camera ``b``), moved by ``T_a_b`` into camera ``a``, at whose pixel
    ``a``'s depth ``depth_m`` reads more than ``far_m`` behind them: ``a`` sees through where
    the surface would be if only a rigid motion had moved it (free space violated). Points
    that ``a`` sees something in front of (hidden by the motion) or has no reading for do not
    count either way."""
    p = points @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    h, w = depth_m.shape
    z = p[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.rint(K[0, 0] * p[:, 0] / z + K[0, 2]).astype(int)
        v = np.rint(K[1, 1] * p[:, 1] / z + K[1, 2]).astype(int)
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    seen = np.zeros(len(p))
    seen[inside] = depth_m[v[inside], u[inside]]
    valid = seen > 0
    if valid.sum() < 20:
        return float("nan")
    return float(np.mean(seen[valid] > z[valid] + far_m))


def deformation(
    depth_frame: Callable[[int], np.ndarray], K: np.ndarray, centres: np.ndarray,
    T_color_turntable: np.ndarray, *, gap: int, radius_m: float, stride_px: int,
    min_height_m: float, max_points: int, max_distance_m: float, huber_m: float,
    iterations: int, far_m: float, spacing_m: float | None = None,
) -> np.ndarray:
    """(n,) per frame ``i`` the share of its hand-and-object surface that no rigid motion
    onto frame ``i + gap``'s explains (NaN where a frame lacks a centre or a surface, and for
    the last ``gap`` frames)."""
    n = len(centres)

    def cloud(frame: int, centre: np.ndarray) -> SurfaceCloud | None:
        return surface_cloud(depth_frame(frame), K, centre, radius_m=radius_m,
                             stride_px=stride_px, T_color_turntable=T_color_turntable,
                             min_height_m=min_height_m, spacing_m=spacing_m)  # fmt: skip

    def register(pairs: list[tuple[SurfaceCloud, SurfaceCloud]], guess: np.ndarray):
        clouds = [c for pair in pairs for c in pair]
        idx = np.arange(2 * len(pairs)).reshape(-1, 2)
        return icp_batch(clouds, idx, guess, K, max_points=max_points,
                         max_distance_m=max_distance_m, huber_m=huber_m,
                         iterations=iterations, sigma_m=0.0015,
                         effective_points=300.0)[0]  # fmt: skip

    # neighbouring frames first (from no motion), their chain the start of the gapped pairs
    step = np.full((n, 4, 4), np.nan)  # step[i] = T_{i+1, i}
    known = [i for i in range(n - 1) if np.all(np.isfinite(centres[i]))]
    pairs, rows = [], []
    for i in known:
        a, b = cloud(i + 1, centres[i]), cloud(i, centres[i])
        if a is not None and b is not None:
            pairs.append((a, b))
            rows.append(i)
    if pairs:
        step[rows] = register(pairs, np.repeat(np.eye(4)[None], len(pairs), 0))
    out = np.full(n, np.nan)
    pairs, rows, guesses = [], [], []
    for i in known:
        j = i + gap
        if j >= n:
            continue
        chain = np.eye(4)
        for m in range(i, j):
            chain = step[m] @ chain if np.all(np.isfinite(step[m])) else chain
        a, b = cloud(j, centres[i]), cloud(i, centres[i])
        if a is not None and b is not None:
            pairs.append((a, b))
            rows.append(i)
            guesses.append(chain)
    if pairs:
        T = register(pairs, np.array(guesses))
        for (a, b), i, T_a_b in zip(pairs, rows, T, strict=True):
            out[i] = 0.5 * (_seen_through(depth_frame(i + gap), K, b.points, T_a_b, far_m)
                            + _seen_through(depth_frame(i), K, a.points, inv_T(T_a_b), far_m))
    return out


def depth_onset(z_signal: np.ndarray, kp_onset: int, before: int, after: int, drift: float,
                ref_from: int, ref_frames: int = 20,
                min_spread: float = 0.01) -> tuple[int, np.ndarray]:
    """Change point of the signal standardised by the last ``ref_frames`` known frames from
    ``ref_from``, searched in
    ``kp_onset - before .. kp_onset + after``: the ``t`` maximising
    ``sum_{i < t} (z_i - drift)``; (onset, z). The spread is at least ``min_spread``.
    ``kp_onset`` when too few reference frames are known."""
    n = len(z_signal)
    finite = np.flatnonzero(np.isfinite(z_signal))
    ref = finite[finite >= min(ref_from, n - 3)][-ref_frames:]
    found = standardise(z_signal, ref)
    if found is None:
        return kp_onset, np.full(n, np.nan)
    spread = max(found[2], min_spread)  # a share: a flat floor is no noise scale
    z = (z_signal - found[1]) / spread
    sums = cusum(z, drift)
    lo, hi = max(kp_onset - before, 0), min(kp_onset + after, n - 1)
    sums[:lo], sums[hi + 1:] = -np.inf, -np.inf
    # the last of tied maxima: NaN frames count 0, so a change inside a run of frames without
    # a surface lands at the run's end (a later onset loses frames; an early one spoils them)
    return int(len(sums) - 1 - np.argmax(sums[::-1])), z


def last_deforming(share: np.ndarray, z: np.ndarray, onset: int, strong: float,
                   drift: float) -> int:
    """The last frame before ``onset`` that the grasp is seen deforming in (-1 if none): the
    last frame whose ``share`` is at least ``strong``, extended over the frames after it whose
    share keeps falling while still above the steady frames' (``z > drift``): a settling
    motion decelerates, so its residual deformation shrinks frame by frame. Frames without a
    share are not seen deforming: a change point after a run of them could lie anywhere in
    the run (wild ``[50832, 11]``: deforming at frame 1, no surface on frames 2-11, the onset
    4 frames late and unmarked while the unknown frames took the last known frame's state).

    share, z : (n,) float, the share and its standardised values (``depth_onset``), NaN where
        unknown.
    """
    seen = np.flatnonzero(share[:onset] >= strong)
    last = int(seen[-1]) if len(seen) else -1
    while (last + 1 < onset and np.isfinite(share[last + 1]) and z[last + 1] > drift
           and (last < 0 or share[last + 1] <= share[last])):
        last += 1
    return last


def rigid_between(share: np.ndarray, z: np.ndarray, last: int, strong: float,
                  drift: float) -> int:
    """The first frame before ``last`` (the last deforming frame) whose surface is rigid
    (finite ``z <= drift``) after a frame with a ``strong`` share: the surface turned rigid
    and deformed again later; -1 if none."""
    seen = False
    for i in range(max(last, 0)):
        if seen and np.isfinite(z[i]) and z[i] <= drift:
            return i
        seen = seen or bool(share[i] >= strong)
    return -1


def settled_after_deforming(share: np.ndarray, strong: float, rigid: float, frames: int,
                            latest: int) -> int:
    """The first frame after the first one read deforming (``share >= strong``) from which
    ``frames`` known shares in a row are below ``rigid``, at most ``latest``; -1 if none.

    ``select_steady``'s estimate where its change point is marked uncertain: the change point
    standardises the share by the steady frames', and a fast turn of the held grasp, which
    ICP misregisters, fills that reference with shares of 0.2-0.7 (wild `[44199, 0]`: 11 of its
    20 frames), so a plain deformation at the start does not stand out. The first settled run
    after a deformation does not depend on that reference."""
    known = np.flatnonzero(np.isfinite(share))
    deforming = known[share[known] >= strong]
    if not len(deforming):
        return -1
    for k in np.flatnonzero(known > deforming[0]):
        run = known[k: k + frames]
        if known[k] > latest:
            break
        if len(run) == frames and np.all(share[run] < rigid):
            return int(known[k])
    return -1


def onset_from_depth(uv, ok, K, onset, depth_frame, T_color_turntable,
                     cfg: SelectSteadyConfig):
    """``select_steady``'s step 5 around the keypoint ``onset``: (depth onset or -1, share
    (n,), its standardised values z (n,) or None, whether the onset is the searched window's
    last frame)."""
    share_of = deformation(
        depth_frame, K,
        hand_centres(depth_frame, K, uv, ok, below_skin_m=0.01,
                                  min_points=cfg.min_points),
        T_color_turntable, gap=cfg.depth_gap, radius_m=cfg.depth_radius_m,
        stride_px=cfg.depth_stride_px, min_height_m=cfg.depth_min_height_m,
        max_points=cfg.depth_max_points, max_distance_m=0.01, huber_m=0.003,
        iterations=cfg.depth_iterations, far_m=cfg.depth_far_m,
        spacing_m=cfg.depth_spacing_m,
    )  # fmt: skip
    if np.isfinite(share_of).mean() < cfg.depth_min_share:
        return -1, share_of, None, False

    def search(before):
        return depth_onset(share_of, onset, before, cfg.depth_after,
                                        cfg.depth_drift_sigmas, onset + cfg.depth_ref_after,
                                        min_spread=cfg.depth_min_spread)  # fmt: skip

    found, z = search(cfg.depth_before)
    if found == onset - cfg.depth_before > 0:  # rigid from the window's start: search before
        found, z = search(onset)
    return found, share_of, z, found >= min(onset + cfg.depth_after, len(share_of) - 1)


def depth_doubt(share, z, depth_from, onset, at_end,
                cfg: SelectSteadyConfig) -> tuple[str, int]:
    """``select_steady``'s step 6: (why the depth's ``onset`` may be wrong by more than a few
    frames or "", the last frame seen deforming)."""
    drift = cfg.depth_drift_sigmas
    last = last_deforming(share, z, depth_from, cfg.depth_strong_share, drift)
    if last < 0:
        return (f"the depth sees no deformation before its change point (frame {depth_from}): "
                "the adjustment phase is not seen; set grasp.steady_from in session.json"), last
    if at_end:
        return (f"the surface still deforms at frame {depth_from}, the last searched frame: "
                "the grasp's end lies later or the depth misfits a rigid surface; set "
                "grasp.steady_from in session.json"), last
    if onset - cfg.depth_lag_frames - (last + 1) > cfg.depth_max_span:
        return (f"the depth sees the grasp deforming up to frame {last}, the onset is frame "
                f"{onset}: the frames between (weak non-rigidity, no surface or no hand "
                "detected) leave the end of the grasp anywhere among them; set "
                "grasp.steady_from in session.json"), last
    rigid = rigid_between(share, z, last, cfg.depth_strong_share, drift)
    if rigid >= 0 and depth_from - rigid > cfg.depth_max_span:
        return (f"the surface is rigid at frame {rigid} and deforms again up to frame {last}: "
                f"two candidate onsets ({rigid} and {onset}); set grasp.steady_from in "
                "session.json"), last
    return "", last
