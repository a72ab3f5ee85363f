"""Robust initialisation of a static-hand SfM problem: two-view geometry, triangulation, PnP.

Shared by ``select_steady`` and ``reconstruct_hand``. Poses here are ``T_c_w`` (world into
camera, what projection needs); the stages convert to ``T_w_c`` at their boundary.
The world frame of an initialisation is the camera of its first two-view frame and the
scale is the two-view baseline (unit length); callers re-anchor and re-scale.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.geometry import inv_T, make_T, project

# cv2: imported where used, so that importing the stage table stays cheap


@dataclass(frozen=True)
class TwoView:
    """The chosen initial pair.

    a, b : frame indices (rows of the observation arrays); camera ``a`` is the world.
    T_b_a : (4, 4) float, camera ``a`` into camera ``b``, unit baseline.
    parallax_deg : median triangulation angle of the pair's inlier joints.
    inliers : (21,) bool, joints seen in both and consistent with the essential matrix.
    """

    a: int
    b: int
    T_b_a: np.ndarray
    parallax_deg: float
    inliers: np.ndarray


@dataclass(frozen=True)
class Initialisation:
    """Poses and joints before bundle adjustment.

    T_c_w : (m, 4, 4) float, NaN for frames PnP could not pose.
    points_w : (21, 3) float, NaN for joints that could not be triangulated.
    pair : the :class:`TwoView` it started from.
    links_from_start : see the field.
    chain : the depth registrations that chained the cameras (``hand_sfm.depth_links.DepthLink``,
        frames of ``T_c_w``; ``hand_sfm.odometry_init``), empty for the other starts.
    """

    T_c_w: np.ndarray
    points_w: np.ndarray
    pair: TwoView
    links_from_start: bool = False
    """The cameras came from the depth surfaces (``hand_sfm.odometry_init``): the depth links
    are registered from them, in every RGB-D round, instead of from the current solve."""
    chain: tuple = ()


def normalise(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Pixels (n, 2) -> normalised image coordinates (n, 2) (no distortion)."""
    return (np.asarray(uv, dtype=float) - K[:2, 2]) / np.diag(K)[:2]


def ray_angles_deg(T_b_a: np.ndarray, points_a: np.ndarray) -> np.ndarray:
    """Angle (n,) between the rays from camera a's and camera b's centres to ``points_a``."""
    c_b = inv_T(T_b_a)[:3, 3]
    ra = points_a / np.linalg.norm(points_a, axis=1, keepdims=True)
    rb = points_a - c_b
    rb = rb / np.linalg.norm(rb, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((ra * rb).sum(1), -1.0, 1.0)))


def triangulate_pair(
    K: np.ndarray, T_a_w: np.ndarray, T_b_w: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray
) -> np.ndarray:
    """Linear triangulation (cv2.triangulatePoints) of matching pixels (n, 2) -> (n, 3) world."""
    import cv2

    P_a = K @ T_a_w[:3]
    P_b = K @ T_b_w[:3]
    X = cv2.triangulatePoints(P_a, P_b, uv_a.T.astype(float), uv_b.T.astype(float))
    return (X[:3] / X[3]).T


def _pair_hypotheses(K, uv_a, uv_b, ransac_px):
    """Every (T_b_a, parallax_deg, inlier mask) an essential matrix of the pair allows."""
    import cv2

    na, nb = normalise(K, uv_a), normalise(K, uv_b)
    thr = ransac_px / float(np.mean(np.diag(K)[:2]))
    E, mask = cv2.findEssentialMat(
        na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr, maxIters=200
    )
    if E is None or mask is None:
        return []
    out = []
    for k in range(E.shape[0] // 3):
        _, R, t, pose_mask = cv2.recoverPose(
            E[3 * k : 3 * k + 3], na, nb, np.eye(3), mask=mask.copy()
        )
        inl = pose_mask.ravel() > 0
        if inl.sum() < 8:
            continue
        T_b_a = make_T(R, t.ravel())
        X_a = triangulate_pair(K, np.eye(4), T_b_a, uv_a[inl], uv_b[inl])
        front = (X_a[:, 2] > 0) & (((X_a @ R.T) + t.ravel())[:, 2] > 0)
        if front.sum() < 8:
            continue
        parallax = float(np.median(ray_angles_deg(T_b_a, X_a[front])))
        keep = np.zeros(len(uv_a), bool)
        keep[np.flatnonzero(inl)[front]] = True
        out.append((T_b_a, parallax, keep))
    return out


def pair_hypotheses(
    uv: np.ndarray,
    ok: np.ndarray,
    K: np.ndarray,
    n_candidates: int,
    ransac_px: float,
    min_motion_px: float = 10.0,
) -> list[TwoView]:
    """Two-view hypotheses among evenly spaced candidate frames, largest parallax first.

    uv : (m, 21, 2) float pixels; ok : (m, 21) bool usable observations.
    Pairs whose keypoints move less than ``min_motion_px`` (median) are skipped.
    """
    usable = np.flatnonzero(ok.sum(1) >= 8)
    if len(usable) < 2:
        return []
    pick = np.unique(np.round(np.linspace(0, len(usable) - 1, n_candidates)).astype(int))
    cand = usable[pick]
    found: list[TwoView] = []
    for ia, a in enumerate(cand):
        for b in cand[ia + 1 :]:
            common = np.flatnonzero(ok[a] & ok[b])
            if len(common) < 8:
                continue
            if np.median(np.linalg.norm(uv[a, common] - uv[b, common], axis=1)) < min_motion_px:
                continue  # keypoints that barely move carry no parallax, only noise
            for T_b_a, parallax, keep in _pair_hypotheses(
                K, uv[a, common], uv[b, common], ransac_px
            ):
                inliers = np.zeros(ok.shape[1], bool)
                inliers[common[keep]] = True
                found.append(TwoView(int(a), int(b), T_b_a, parallax, inliers))
    return sorted(found, key=lambda h: -h.parallax_deg)


def pnp(
    K: np.ndarray, points_w: np.ndarray, uv: np.ndarray, ransac_px: float, min_points: int
) -> np.ndarray | None:
    """Robust PnP (cv2.solvePnPRansac + LM refinement on its inliers) -> T_c_w (4, 4) or None.

    points_w : (n, 3); uv : (n, 2) pixels, matching rows.
    """
    import cv2

    if len(points_w) < max(min_points, 6):
        return None
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        points_w.astype(float),
        uv.astype(float),
        K,
        None,
        iterationsCount=100,
        reprojectionError=ransac_px,
        confidence=0.999,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inl is None or len(inl) < max(min_points // 2, 4):
        return None
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(points_w[inl], uv[inl], K, None, rvec, tvec)
    T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
    if np.median((points_w @ T[:3, :3].T + T[:3, 3])[:, 2]) <= 0:
        return None
    return T


def triangulate_multiview(
    K: np.ndarray, T_c_w: np.ndarray, uv: np.ndarray, reject_px: float
) -> np.ndarray | None:
    """One point from k >= 2 views by linear DLT, refitted once without views > reject_px.

    T_c_w : (k, 4, 4); uv : (k, 2). Returns (3,) or None when under-determined.
    """
    keep = np.ones(len(uv), bool)
    X = None
    for _ in range(2):
        if keep.sum() < 2:
            return X
        P = K @ T_c_w[keep, :3]
        rows = np.concatenate(
            [uv[keep, :1] * P[:, 2] - P[:, 0], uv[keep, 1:2] * P[:, 2] - P[:, 1]], axis=0
        )
        _, _, Vt = np.linalg.svd(rows, full_matrices=False)
        if abs(Vt[-1, 3]) < 1e-12:
            return X
        X = Vt[-1, :3] / Vt[-1, 3]
        proj = project(K, np.einsum("kab,b->ka", T_c_w[:, :3, :3], X) + T_c_w[:, :3, 3])
        keep = np.linalg.norm(proj - uv, axis=1) < reject_px
    return X


def _pnp_frames(K, X, uv, sel, frames, ransac_px, min_points, threads):
    """:func:`pnp` of each of ``frames`` from its ``sel`` (m, 21) joints; with ``threads`` 2
    the second half of the frames on a second thread (OpenCV's RANSAC runs without the GIL,
    from a fixed seed per call): the same poses either way."""
    frames = [int(i) for i in frames]

    def solve(part):
        return [pnp(K, X[sel[i]], uv[i, sel[i]], ransac_px, min_points) for i in part]

    half = (len(frames) + 1) // 2
    if threads < 2 or len(frames) < 8:
        return solve(frames)
    with ThreadPoolExecutor(max_workers=1) as pool:
        second = pool.submit(solve, frames[half:])
        return solve(frames[:half]) + second.result()


def _grow(uv, ok, K, pair, frames, ransac_px, min_points, passes, threads=1):
    """Triangulate the pair, PnP the given frames (on ``threads``, see :func:`_pnp_frames`),
    triangulate the rest; (T_c_w, X)."""
    m, nj = ok.shape
    X = np.full((nj, 3), np.nan)
    j = np.flatnonzero(pair.inliers)
    X[j] = triangulate_pair(K, np.eye(4), pair.T_b_a, uv[pair.a, j], uv[pair.b, j])
    T = np.full((m, 4, 4), np.nan)
    for _ in range(passes):  # later passes: more joints known after multi-view triangulation
        known = np.all(np.isfinite(X), axis=1)
        for i, pose in zip(frames, _pnp_frames(K, X, uv, ok & known, frames, ransac_px,
                                                min_points, threads), strict=True):
            if pose is not None:
                T[i] = pose
        T[pair.a] = np.eye(4)
        T[pair.b] = pair.T_b_a
        posed = np.all(np.isfinite(T[:, :3, 3]), axis=1)
        for jj in range(nj):
            views = np.flatnonzero(posed & ok[:, jj])
            if len(views) >= 2:
                Xj = triangulate_multiview(K, T[views], uv[views, jj], 3 * ransac_px)
                if Xj is not None:
                    X[jj] = Xj
    return T, X


def _agreement(uv, ok, K, T, X, ransac_px):
    """Share of the observations of posed frames and known joints within ``ransac_px``."""
    from graspcap.tasks.hand_sfm.graph import reprojection_residuals

    res = reprojection_residuals(K, np.nan_to_num(T, nan=0.0), np.nan_to_num(X, nan=0.0), uv)
    valid = ok & np.all(np.isfinite(T[:, :3, 3]), axis=1)[:, None] & np.all(np.isfinite(X), 1)
    return float((res[valid] < ransac_px).sum()) / max(int(ok.sum()), 1)


def check_frames(m: int, n_check_frames: int = 15) -> np.ndarray:
    """The evenly spaced frames of ``m`` on which :func:`initialise` checks the pairs."""
    return np.unique(np.round(np.linspace(0, m - 1, n_check_frames)).astype(int))


def initialise(
    uv: np.ndarray,
    ok: np.ndarray,
    K: np.ndarray,
    *,
    n_candidates: int,
    ransac_px: float,
    min_points: int,
    min_parallax_deg: float,
    n_hypotheses: int = 6,
    n_check_frames: int = 15,
    depth_score: Callable[[np.ndarray, np.ndarray, np.ndarray], float] | None = None,
    agreement_slack: float = 0.05,
    threads: int = 1,
) -> tuple[Initialisation | None, float]:
    """Two-view start, triangulation, PnP for every frame, then the remaining joints.

    Two views of a small, distant hand are often ambiguous (several essential matrices fit),
    so the ``n_hypotheses`` pairs of largest parallax (at least ``min_parallax_deg``) are each
    grown on ``n_check_frames`` evenly spaced frames and the one most observations agree
    with wins. Under weak perspective (a hand ~130 px across) a pair also fits its depth-
    reversed (Necker) twin almost as well as the truth; with ``depth_score(frames (k,),
    T_c_w (k, 4, 4), points_w (21, 3)) -> float`` (higher is better, e.g. the share of depth
    readings that one scale explains) the winner is the hypothesis of best depth score among
    those within ``agreement_slack`` of the best pixel agreement. With ``threads`` 2 the
    frames' PnP runs on two threads (the same result).
    Returns (initialisation or None, the largest parallax found in degrees).
    """
    hyps = pair_hypotheses(uv, ok, K, n_candidates, ransac_px)
    best_parallax = hyps[0].parallax_deg if hyps else 0.0
    hyps = [h for h in hyps if h.parallax_deg >= min_parallax_deg][:n_hypotheses]
    if not hyps:
        return None, best_parallax
    m = len(ok)
    check = check_frames(m, n_check_frames)
    scored = []
    for h in hyps:
        T, X = _grow(uv, ok, K, h, check, ransac_px, min_points, passes=1, threads=threads)
        agree = _agreement(uv[check], ok[check], K, T[check], X, ransac_px)
        scored.append((agree, h, T[check], X))
    pair = max(scored, key=lambda s: s[0])[1]
    if depth_score is not None and len(scored) > 1:
        best = max(s[0] for s in scored)
        close = [s for s in scored if s[0] >= best - agreement_slack]
        pair = max(close, key=lambda s: depth_score(check, s[2], s[3]))[1]
    T, X = _grow(uv, ok, K, pair, range(m), ransac_px, min_points, passes=2, threads=threads)
    return Initialisation(T, X, pair), best_parallax
