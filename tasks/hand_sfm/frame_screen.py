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
  a frame whose detected hand lies far from where its neighbours' lie (in position or size)
  is another hand, or the hand in a wrong place, before any solve;
- after the robust (Huber) solve, the residuals' scale (``robust_sigma``: a Rayleigh fit to
  their median, over the frames the hand explains), from which the inlier gate follows;
- per frame whether the static hand explains its detections (``unexplained_frames``: too few
  of them within the gate, e.g. a mirrored hand) and whether two neighbouring fingers'
  labels are exchanged (``swapped_fingers``: the exchanged labels fit much better).

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
    min_points: int, first_frame: int = 0,
) -> dict[int, str]:
    """Frames whose detection jumps away from its neighbours' -> reason (keys: rows of ``uv``).

    For each frame with ``min_points`` usable keypoints, the neighbours are the
    ``2 * half_window`` other such frames nearest in time (one-sided at the ends of the
    video); a frame is rejected when its keypoints' median lies more than ``jump_share`` of
    the hand's size from the median of its neighbours' medians, or its size differs from
    theirs by more than a factor ``size_ratio``. Medians keep a run of up to
    ``half_window - 1`` wrong frames from hiding each other, at the ends too. ``first_frame``
    only numbers the frames in the reasons (video frame = row + first_frame).
    """
    size = hand_size_px(uv, ok, min_points)
    rows = np.flatnonzero(np.isfinite(size))
    centre = np.full((len(uv), 2), np.nan)
    for i in rows:
        centre[i] = np.median(uv[i, ok[i]], axis=0)
    out: dict[int, str] = {}
    for i in rows:
        others = rows[rows != i]
        near = others[np.argsort(np.abs(others - i), kind="stable")[: 2 * half_window]]
        if len(near) < 2:
            continue
        c_ref = np.median(centre[near], axis=0)
        s_ref = float(np.median(size[near]))
        jump = float(np.linalg.norm(centre[i] - c_ref))
        ratio = float(size[i] / s_ref)
        if jump > jump_share * s_ref:
            out[int(i)] = (
                f"frame {i + first_frame}: the detected hand is {jump:.0f} px "
                f"({jump / s_ref:.0%} of its size) from where the neighbouring frames' are: "
                "another hand or the hand in a wrong place"
            )
        elif not 1.0 / size_ratio <= ratio <= size_ratio:
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


def jumping_poses(
    T_c_w: np.ndarray, X: np.ndarray, K: np.ndarray, candidates: np.ndarray, gate_px: float,
    *, first_frame: int = 0, motion_factor: float = 4.0,
) -> dict[int, str]:
    """Posed frames among ``candidates`` (m,) bool whose camera jumps away from its
    neighbours' -> reason.

    The static hand ``X`` (21, 3) is projected by each frame's pose ``T_c_w`` (m, 4, 4) and by
    the poses of the two nearest candidate frames on each side; the frame's jump is the
    second smallest of those four median displacements (one wrong neighbour on each side
    cannot make a good frame jump). A frame jumping more than ``gate_px`` and more than
    ``motion_factor`` times the median frame's jump (the clip's own pace) is rejected: the
    solve posed it to explain a detection no smooth motion of this hand gives (a mirrored
    hand, another hand in a near place).
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
    jumps = np.empty(len(rows))
    for n in range(len(rows)):
        near = [k for k in (n - 2, n - 1, n + 1, n + 2) if 0 <= k < len(rows)]
        d = sorted(float(np.median(np.linalg.norm(proj[n] - proj[k], axis=1))) for k in near)
        jumps[n] = d[1] if len(d) > 1 else d[0]
    # the session's own pace: a short or fast clip moves the hand tens of pixels between
    # frames without any wrong detection (an easy 12-frame rig clip: 20-70 px per frame)
    limit = max(gate_px, motion_factor * float(np.median(jumps)))
    out: dict[int, str] = {}
    for n, i in enumerate(rows):
        if jumps[n] > limit:
            out[int(i)] = (
                f"frame {i + first_frame}: its camera moves the hand {jumps[n]:.0f} px away from "
                f"where the neighbouring frames' cameras put it (> {limit:.1f} px): the "
                "detection is not this hand (mirrored, another hand)"
            )
    return out
