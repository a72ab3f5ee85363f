"""Whole-frame rejection and a measured noise scale for ``reconstruct_hand``.

A real detector does not fail joint by joint only: in some frames the whole detection is
wrong (the hand somewhere else, mirrored, another hand) and in others two fingers' labels
are exchanged, with confidences as high as in good frames. A per-observation threshold fixed
in pixels cannot sort these: at 5-10 % of the hand's image size the honest detections of a
110 px hand miss by ~10 px, as far as a fixed 10 px gate; and a wrong frame the static hand
partly explains (a rigid 2D motion of the projections is nearly a camera motion) spreads its
error over the cameras and joints of every frame.

So the stage measures instead of assuming:

- the hand's image size (``hand_size_px``), which scales every threshold that stands for a
  detector's error;
- the continuity of the detections (``screen_jumps``): the virtual camera moves smoothly, so
  a frame whose detected hand lies far from where its neighbours' motion puts it (off the
  longest chain of frames along which it moves smoothly, ``smooth_chain``), or whose size
  differs from theirs, is another hand, or the hand in a wrong place, before any solve; a
  hand that crosses the image fast but smoothly is not;
- after the robust (Huber) solve, the residuals' scale (``robust_sigma``: a Rayleigh fit to
  their median, over the frames the hand explains), from which the inlier gate follows;
- per frame whether the static hand explains its detections (``unexplained_frames``: too few
  of them within the gate, e.g. a mirrored hand) and whether two neighbouring fingers'
  labels are exchanged (``swapped_fingers``: the exchanged labels fit much better), and
  whether its camera puts the hand off the smooth motion of the others' (``jumping_poses``,
  the same chain on the projections: a mirrored hand, even in every other frame).

A rejected frame is dropped entirely with its reason (``SfmDiagnostics.frame_rejected``, which
the per-frame validity carries as ``hand_reason``).
"""

from __future__ import annotations

import numpy as np

FINGERS: tuple[tuple[int, ...], ...] = tuple(tuple(range(1 + 4 * f, 5 + 4 * f)) for f in range(5))
"""Keypoint rows of the thumb, index, middle, ring and little finger (base to tip)."""

RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
"""Median of the length of a 2D isotropic Gaussian with unit sigma per coordinate."""


def hand_size_px(uv: np.ndarray, ok: np.ndarray, min_points: int = 6) -> np.ndarray:
    """(m,) diagonal (px) of the bounding box of each frame's usable keypoints; NaN for frames
    with fewer than ``min_points``."""
    out = np.full(len(uv), np.nan)
    for i in np.flatnonzero(ok.sum(1) >= min_points):
        p = uv[i, ok[i]]
        out[i] = float(np.linalg.norm(p.max(0) - p.min(0)))
    return out


def screen_jumps(
    uv: np.ndarray, ok: np.ndarray, *, jump_share: float, size_ratio: float, half_window: int,
    min_points: int, first_frame: int = 0, max_gap: int = 8, motion_share: float = 0.5,
) -> dict[int, str]:
    """Frames whose detection jumps off the motion of the others' -> reason (keys: rows of
    ``uv``).

    Of the frames with ``min_points`` usable keypoints, those on the longest chain along
    which the detected hand (its keypoints' median) moves smoothly (``smooth_chain``: every
    chain frame within ``jump_share`` of the hand's size of where its chain neighbours'
    motion puts it, or ``motion_share`` of that motion; ``max_gap - 1`` frames skipped) are kept,
    the others rejected: another hand or the hand in a wrong place. A hand that crosses the
    image fast is where its neighbours' motion puts it (a median of their positions is not:
    at the start of a sweep it lies a sweep behind). A frame on the chain whose size differs
    from the median of the ``2 * half_window`` nearest such frames' by more than a factor
    ``size_ratio`` is rejected too. ``first_frame`` only numbers the frames in the reasons
    (video frame = row + first_frame).
    """
    size = hand_size_px(uv, ok, min_points)
    rows = np.flatnonzero(np.isfinite(size))
    out: dict[int, str] = {}
    if len(rows) < 3:
        return out
    # each frame's keypoints' median: its noise is a fraction of a keypoint's (a velocity
    # change triples the noise of what it is taken of)
    pts = np.stack([np.median(uv[i, ok[i]], axis=0) for i in rows])[:, None]
    hand = float(np.median(size[rows]))
    on = np.zeros(len(rows), bool)
    on[smooth_chain(pts, rows.astype(float), jump_share * hand, max_gap=max_gap,
                    motion_share=motion_share)] = True
    for n in np.flatnonzero(~on):
        off = off_motion_px(pts, rows.astype(float), on, n)
        out[int(rows[n])] = (
            f"frame {rows[n] + first_frame}: the detected hand is {off:.0f} px "
            f"({off / hand:.0%} of its size) from where the neighbouring frames' motion "
            "puts it: another hand or the hand in a wrong place"
        )
    for n in np.flatnonzero(on):
        i = rows[n]
        others = rows[rows != i]
        near = others[np.argsort(np.abs(others - i), kind="stable")[: 2 * half_window]]
        ratio = float(size[i] / np.median(size[near]))
        if not 1.0 / size_ratio <= ratio <= size_ratio:
            out[int(i)] = (
                f"frame {i + first_frame}: the detected hand is {ratio:.2f} x the size of the "
                "neighbouring frames': another hand or a wrong detection"
            )
    return out


def robust_sigma(res: np.ndarray) -> float:
    """Per-coordinate pixel sigma of residual lengths ``res`` (any shape, NaN ignored), from
    their median as if they were Rayleigh (2D Gaussian) lengths; NaN without residuals."""
    r = np.asarray(res, dtype=float)
    r = r[np.isfinite(r)]
    return float(np.median(r) / RAYLEIGH_MEDIAN) if r.size else float("nan")


def unexplained_frames(
    res: np.ndarray, ok: np.ndarray, gate_px: float, *, min_share: float, first_frame: int = 0,
) -> dict[int, str]:
    """Posed frames whose detections the static hand does not explain -> reason.

    res : (m, 21) residuals (px) of the solve, NaN for unposed frames; ok : (m, 21) usable.
    A frame is rejected when fewer than ``min_share`` of its usable detections lie within
    ``gate_px`` of the projections (a mirrored hand, another hand the solve half explains).
    """
    out: dict[int, str] = {}
    posed = np.isfinite(np.where(ok, res, np.nan)).any(1)
    for i in np.flatnonzero(posed):
        n = int(ok[i].sum())
        within = int((ok[i] & (res[i] < gate_px)).sum())
        if within < min_share * n:
            out[int(i)] = (
                f"frame {i + first_frame}: only {within} of {n} detected keypoints within "
                f"{gate_px:.1f} px of the static hand (need {min_share:.0%}): the detection is "
                "not this hand (mirrored, another hand)"
            )
    return out


def swapped_fingers(
    uv: np.ndarray, ok: np.ndarray, proj: np.ndarray, gate_px: float, *, gain: float,
) -> np.ndarray:
    """(m, 21) bool: observations of two neighbouring fingers whose labels are exchanged.

    uv : (m, 21, 2) detections; ok : (m, 21) usable; proj : (m, 21, 2) projections of the
    static hand (NaN for unposed frames). For each frame and each pair of neighbouring
    fingers, the cost ``sum min(residual, gate_px)`` of their usable keypoints is compared
    with the cost when the two fingers' labels are exchanged; when the exchange lowers it by
    more than the factor ``gain`` both fingers' keypoints are marked (the largest such pair
    per frame).
    """
    m = len(uv)
    out = np.zeros((m, uv.shape[1]), bool)
    posed = np.all(np.isfinite(proj.reshape(m, -1)), axis=1)
    for i in np.flatnonzero(posed):
        best, best_rows = 1.0, None
        for f in range(len(FINGERS) - 1):
            a, b = list(FINGERS[f]), list(FINGERS[f + 1])
            both = ok[i, a] & ok[i, b]
            if both.sum() < 2:
                continue
            ra, rb = np.array(a)[both], np.array(b)[both]
            rows = np.concatenate([ra, rb])
            as_is = np.minimum(np.linalg.norm(uv[i, rows] - proj[i, rows], axis=1), gate_px)
            exchanged = np.minimum(
                np.linalg.norm(uv[i, rows] - proj[i, np.concatenate([rb, ra])], axis=1), gate_px
            )
            ratio = float(exchanged.sum() / max(as_is.sum(), 1e-9))
            if ratio < best:
                best, best_rows = ratio, rows
        if best_rows is not None and best * gain < 1.0:
            out[i, best_rows] = True
    return out


def row_nanmedian(x: np.ndarray) -> np.ndarray:
    """``np.nanmedian(x, axis=1)`` of a 2-D array, bit for bit (NaN for a row without a
    finite value, and no warning), without numpy's masked-array path for small arrays, which
    made ``_smooth_triples``' thousands of (<= 8, 21) medians 7 % of a session's CPU."""
    x = np.sort(np.asarray(x, dtype=float), axis=1)  # NaNs last
    n = np.count_nonzero(~np.isnan(x), axis=1)
    rows = np.arange(len(x))
    lo, hi = x[rows, (n - 1) // 2], x[rows, n // 2]  # an empty row reads column -1 or 0: NaN out
    return np.where(n > 0, (lo + hi) / 2, np.nan)


def _smooth_triples(proj: np.ndarray, t: np.ndarray, gate_px: float, max_gap: int,
                    motion_share: float) -> dict[tuple[int, int], list[int]]:
    """(a, b) -> the c > b (rows of ``proj`` at frame times ``t``, consecutive ones at most
    ``max_gap`` rows apart) through which the hand moves smoothly: the change of its
    velocity at b (per keypoint) times the longer of the two steps in frames, i.e. how far
    the outer frame of that step lies from where the other two frames' straight-line motion
    puts it (median over the keypoints), is within ``gate_px`` or ``motion_share`` times the
    hand's motion over that step at its mean speed from a to c. A wrong frame (or a run of
    them) at a chain's end or inside it is as far from its neighbours' motion as it is from
    them (a lone one inside twice: it jumps out and back), whatever frames were skipped. A
    step longer than ``max_gap`` frames (a hole in the detections) is not judged."""
    n = len(t)
    out: dict[tuple[int, int], list[int]] = {}
    for a in range(n):
        for b in range(a + 1, min(a + 1 + max_gap, n)):
            c = np.arange(b + 1, min(b + 1 + max_gap, n))
            if not len(c):
                continue
            g_bc = t[c] - t[b]
            v_ab = (proj[b] - proj[a]) / (t[b] - t[a])
            v_bc = (proj[c] - proj[b]) / g_bc[:, None, None]
            step = np.maximum(t[b] - t[a], g_bc)
            with np.errstate(invalid="ignore"):  # keypoints missing (NaN)
                off = step * row_nanmedian(np.linalg.norm(v_bc - v_ab, axis=2))
                speed = row_nanmedian(np.linalg.norm(proj[c] - proj[a], axis=2)) / (t[c] - t[a])
                limit = np.maximum(gate_px, motion_share * speed * step)
                # across a hole of more than max_gap frames without a detection the motion
                # is not predicted: such a step is not judged (the next triple judges b)
                out[(a, b)] = [int(k) for k in c[(off <= limit) | (step > max_gap)]]
    return out


def smooth_chain(proj: np.ndarray, t: np.ndarray, gate_px: float, *, max_gap: int = 8,
                 motion_share: float = 0.5, cost: np.ndarray | None = None) -> np.ndarray:
    """Rows of the longest chain of frames (``proj`` (n, j, 2) projections of the hand, NaN
    where missing, at frame times ``t`` (n,), increasing) along which the hand moves
    smoothly (at every chain frame its velocity hardly changes: ``_smooth_triples``),
    consecutive chain frames at most ``max_gap`` rows apart (skipping up to ``max_gap - 1``
    wrong frames). Of equally long chains the one with the least summed ``cost`` (n,) (e.g.
    each frame's median residual; none: the earliest) wins. A longest path over frame pairs:
    a hand moving fast but smoothly is one chain; frames of another or a mirrored hand are
    off it, even every other frame (then the better explained of the two interleaved chains
    is kept)."""
    n = len(t)
    if n < 3:
        return np.arange(n)
    c_row = np.zeros(n) if cost is None else np.nan_to_num(np.asarray(cost, float), nan=1e6)
    triples = _smooth_triples(proj, t, gate_px, max_gap, motion_share)
    best: dict[tuple[int, int], tuple[int, float]] = {}  # (length, -summed cost)
    back: dict[tuple[int, int], tuple[int, int] | None] = {}
    for a in range(n):  # pairs in order of their first frame: every predecessor is final
        for b in range(a + 1, min(a + 1 + max_gap, n)):
            best.setdefault((a, b), (2, -float(c_row[a] + c_row[b])))
            back.setdefault((a, b), None)
            for c in triples.get((a, b), ()):
                step = (best[(a, b)][0] + 1, best[(a, b)][1] - float(c_row[c]))
                if step > best.get((b, c), (2, -float(c_row[b] + c_row[c]))):
                    best[(b, c)] = step
                    back[(b, c)] = (a, b)
    end = max(best, key=lambda k: (best[k], -k[1]))
    chain = [end[1], end[0]]
    while back[end] is not None:
        end = back[end]
        chain.append(end[0])
    return np.array(sorted(chain))


def off_motion_px(pts: np.ndarray, t: np.ndarray, on: np.ndarray, n: int) -> float:
    """Median keypoint distance (px) of row ``n`` of ``pts`` (k, j, 2) (NaN: missing) from
    where the straight-line motion of the nearest ``on`` rows puts it: interpolated between
    the nearest on either side, extrapolated from the two nearest at an end; NaN without
    two such rows."""
    kept = np.flatnonzero(on)
    before, after = kept[kept < n], kept[kept > n]
    if len(before) and len(after):
        a, c = before[-1], after[0]
    elif len(before) > 1:
        a, c = before[-2], before[-1]
    elif len(after) > 1:
        a, c = after[0], after[1]
    else:
        return float("nan")
    pred = pts[a] + (pts[c] - pts[a]) * (t[n] - t[a]) / (t[c] - t[a])
    d = np.linalg.norm(pts[n] - pred, axis=1)
    return float(np.nanmedian(d)) if np.isfinite(d).any() else float("nan")


def jumping_poses(
    T_c_w: np.ndarray, X: np.ndarray, K: np.ndarray, candidates: np.ndarray, gate_px: float,
    *, first_frame: int = 0, max_gap: int = 8, motion_share: float = 0.5,
    residual_px: np.ndarray | None = None,
) -> dict[int, str]:
    """Posed frames among ``candidates`` (m,) bool whose camera jumps off the smooth motion
    of the others -> reason.

    The static hand ``X`` (21, 3) is projected by each frame's pose ``T_c_w`` (m, 4, 4); the
    frames on the longest chain along which every frame lies within ``gate_px``, or
    ``motion_share`` of the hand's motion, of where its chain neighbours' motion puts it
    (``smooth_chain``), are kept, the
    others rejected: the solve posed them to explain a detection no smooth motion of this
    hand gives (a mirrored hand, another hand in a near place). The hand's own pace does not
    count against a frame (a sweep of 20-100 px per frame moves at its neighbours' velocity);
    a wrong frame, or every other frame mirrored, does not. ``residual_px`` (m, k): the
    solve's residuals; of equally long chains the one with the lower median residuals wins.
    """
    m = len(T_c_w)
    known = np.all(np.isfinite(X), axis=1)
    posed = candidates & np.all(np.isfinite(T_c_w.reshape(m, -1)), axis=1)
    rows = np.flatnonzero(posed)
    if len(rows) < 3 or known.sum() < 3:
        return {}
    Xc = np.einsum("mab,jb->mja", T_c_w[rows, :3, :3], X[known]) + T_c_w[rows, None, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = (Xc[..., :2] / Xc[..., 2:]) * np.diag(K)[:2] + K[:2, 2]
    on = np.zeros(len(rows), bool)
    cost = None
    if residual_px is not None:
        with np.errstate(all="ignore"):
            r = np.where(np.isfinite(residual_px[rows]), residual_px[rows], np.nan)
            cost = np.array([np.nanmedian(x) if np.isfinite(x).any() else np.nan for x in r])
    on[smooth_chain(proj, rows.astype(float), gate_px, max_gap=max_gap,
                    motion_share=motion_share, cost=cost)] = True
    out: dict[int, str] = {}
    for n in np.flatnonzero(~on):
        i = rows[n]
        d = off_motion_px(proj, rows.astype(float), on, n)
        out[int(i)] = (
            f"frame {i + first_frame}: its camera moves the hand {d:.0f} px away from where "
            f"the neighbouring frames' cameras' motion puts it (gate {gate_px:.1f} px): the "
            "detection is not this hand (mirrored, another hand)"
        )
    return out
