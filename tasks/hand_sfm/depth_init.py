"""A second initialisation of the static-hand SfM problem, from the aligned depth.

The two-view start (``hand_sfm.two_view_init``) works from pixels alone. For a small, distant
hand the essential matrices of many frame pairs are ill-conditioned: RANSAC returns motions that
fit the 21 keypoints of both frames but are wrong by tens of degrees (on the rig's seed-7
drill session 34 of 35 hypotheses were off by 10-165 deg), and a bundle adjustment started
from one settles in a wrong minimum (a bone of 140 mm). The depth needs no such luck: each
frame's keypoints, backprojected with their depth (joint centres ``surface_offset_m`` below
the skin), are the same rigid hand in metres, so a robust rigid fit (RANSAC over joint
triples, then least squares on the inliers) poses every frame against a reference frame.
Readings on the object or on a nearer finger are the fit's outliers. The joints are then
triangulated from the pixels with those poses, and the frames re-posed by PnP, as the
two-view start does.

``reconstruct_hand`` uses it to restart a solve that failed from the two-view start.
"""

from __future__ import annotations

import numpy as np

from graspcap.tasks.core.geometry import backproject, umeyama
from graspcap.tasks.hand_sfm.metric_scale import DepthLookup
from graspcap.tasks.hand_sfm.two_view_init import (
    Initialisation,
    TwoView,
    pnp,
    ray_angles_deg,
    triangulate_multiview,
)


def backprojected_joints(
    uv: np.ndarray,
    ok: np.ndarray,
    K: np.ndarray,
    depth_at: DepthLookup | np.ndarray,
    offset_m: np.ndarray,
    first_frame: int,
) -> np.ndarray:
    """Camera-frame joint centres (m, 21, 3) from the depth at the keypoints, NaN where the
    observation is unusable or has no depth.

    uv : (m, 21, 2) pixels; ok : (m, 21) usable observations; offset_m : (21,) depth of each
    joint centre below the skin; row i is video frame ``first_frame + i``; ``depth_at`` a
    lookup or the readings (m, 21) at the keypoints (``hand_sfm.depth_sweep``).
    """
    m = len(uv)
    out = np.full((m, 21, 3), np.nan)
    for i in np.flatnonzero(ok.any(1)):
        j = np.flatnonzero(ok[i])
        d = (
            np.asarray(depth_at[i, j], dtype=float)
            if isinstance(depth_at, np.ndarray)
            else np.asarray(depth_at(first_frame + int(i), uv[i, j]), dtype=float)
        )
        good = np.isfinite(d) & (d > 0)
        out[i, j[good]] = backproject(K, uv[i, j[good]], d[good] + offset_m[j[good]])
    return out


def _rigid_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rotations (k, 3, 3) and translations (k, 3) with ``dst ~ R @ src + t``
    of k point sets (k, p, 3) at once (``geometry.umeyama`` without scale, batched)."""
    mu_s, mu_d = src.mean(1), dst.mean(1)
    xs, xd = src - mu_s[:, None], dst - mu_d[:, None]
    cov = xd.transpose(0, 2, 1) @ xs / src.shape[1]
    U, _, Vt = np.linalg.svd(cov)
    S = np.tile(np.eye(3), (len(src), 1, 1))
    S[np.linalg.det(U) * np.linalg.det(Vt) < 0, 2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_d - np.einsum("kab,kb->ka", R, mu_s)


def robust_rigid(
    src: np.ndarray, dst: np.ndarray, inlier_m: float, rng: np.random.Generator, trials: int = 60
) -> tuple[np.ndarray, np.ndarray] | None:
    """``T`` with ``dst ~ T @ src`` by RANSAC over point triples, refitted on the inliers.

    src, dst : (n, 3) matching points. Returns (T (4, 4), inlier mask (n,)) or None when
    fewer than 4 points agree within ``inlier_m``.
    """
    n = len(src)
    if n < 4:
        return None
    # the triples drawn one by one (the same draws as ever), the fits and scores in one batch
    picks = np.array([rng.choice(n, 3, replace=False) for _ in range(trials)])
    a, b, c = (src[picks[:, k]] for k in range(3))
    fine = np.linalg.norm(np.cross(b - a, c - a), axis=1) >= 1e-6  # else no rotation
    best = np.zeros(n, bool)
    if fine.any():
        R, t = _rigid_batch(src[picks[fine]], dst[picks[fine]])
        inl = np.linalg.norm(src @ R.transpose(0, 2, 1) + t[:, None] - dst, axis=2) < inlier_m
        count = inl.sum(1)
        k = int(np.argmax(count))  # the first of the most, as the sequential search kept
        if count[k] > 0:
            best = inl[k]
    if best.sum() < 4:
        return None
    for _ in range(2):  # least squares on the inliers, then re-gate once
        T, _ = umeyama(src[best], dst[best], with_scale=False)
        inl = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1) < inlier_m
        if inl.sum() < 4:
            break
        best = inl
    return T, best


def depth_initialisation(
    uv: np.ndarray,
    ok: np.ndarray,
    K: np.ndarray,
    depth_at: DepthLookup | np.ndarray,
    offset_m: np.ndarray,
    first_frame: int,
    *,
    ransac_px: float,
    min_points: int,
    inlier_m: float = 0.012,
    seed: int = 0,
    reference: int | None = None,
) -> Initialisation | None:
    """Poses from rigid fits of the depth-backprojected joints, joints triangulated from the
    pixels, frames re-posed by PnP; metric, in the frame of the reference camera.

    uv : (m, 21, 2) pixels; ok : (m, 21) usable observations (row i is video frame
    ``first_frame + i``); offset_m : (21,) joint centre below the skin; depth_at : a lookup
    or the readings (m, 21) at the keypoints.
    The reference is the frame with the most depth readings (or ``reference``, a row of
    ``uv``); a frame is posed when at
    least ``min_points`` of its readings agree with the reference within ``inlier_m``.
    Returns None when fewer than two frames can be posed or no joint can be triangulated.
    The ``pair`` of the result is the reference and the frame turned furthest from it.
    """
    rng = np.random.default_rng(seed)
    P = backprojected_joints(uv, ok, K, depth_at, np.asarray(offset_m, float), first_frame)
    valid = np.all(np.isfinite(P), axis=2)
    m = len(uv)
    a = int(np.argmax(valid.sum(1))) if reference is None else int(reference)
    if valid[a].sum() < min_points:
        return None
    T_c_w = np.full((m, 4, 4), np.nan)
    T_c_w[a] = np.eye(4)
    for i in range(m):
        common = np.flatnonzero(valid[a] & valid[i])
        if i == a or len(common) < min_points:
            continue
        fit = robust_rigid(P[a, common], P[i, common], inlier_m, rng)
        if fit is not None and fit[1].sum() >= min_points:
            T_c_w[i] = fit[0]  # reference camera (the world) into camera i
    X = median_joints(T_c_w, P, inlier_m)
    X_px = _triangulate(K, T_c_w, uv, ok, 3 * ransac_px)
    # a joint the depth never sees (a fingertip behind the object) is the median of wrong
    # readings, off its rays: the pixels' triangulation then
    off_rays = _median_reprojection_px(K, T_c_w, X, uv, ok) > ransac_px
    X = np.where((off_rays | ~np.all(np.isfinite(X), axis=1))[:, None], X_px, X)
    known = np.all(np.isfinite(X), axis=1)
    if known.sum() < min_points:
        return None
    for i in range(m):  # pixel-accurate poses against the hand from the depth
        sel = known & ok[i]
        pose = pnp(K, X[sel], uv[i, sel], ransac_px, min_points)
        if pose is not None:
            T_c_w[i] = pose
    T_c_w[a] = np.eye(4)
    X = np.where(known[:, None], X, _triangulate(K, T_c_w, uv, ok, 3 * ransac_px))
    posed = np.flatnonzero(np.all(np.isfinite(T_c_w[:, :3, 3]), axis=1))
    if len(posed) < 2:
        return None
    R_a = T_c_w[posed, :3, :3]
    b = int(posed[np.argmin(np.trace(R_a, axis1=1, axis2=2))])  # turned furthest from a
    known = np.all(np.isfinite(X), axis=1)
    if b == a or known.sum() < min_points:
        return None
    parallax = float(np.median(ray_angles_deg(T_c_w[b], X[known])))
    return Initialisation(T_c_w, X, TwoView(a, b, T_c_w[b].copy(), parallax, known))


def median_joints(T_c_w: np.ndarray, P: np.ndarray, inlier_m: float | None = None,
                  min_frames: int = 3) -> np.ndarray:
    """Each joint (21, 3) in the world as the median of its backprojections ``P`` (m, 21, 3,
    camera frames, :func:`backprojected_joints`) from the frames posed in ``T_c_w``, then,
    given ``inlier_m``, again over those within it of that median (readings on the object or
    a nearer finger are minorities); NaN where fewer than ``min_frames`` frames read it."""
    posed = np.all(np.isfinite(T_c_w[:, :3, 3]), axis=1)
    T_w_c = np.stack([np.linalg.inv(T) for T in T_c_w[posed]])
    Pw = np.einsum("mab,mjb->mja", T_w_c[:, :3, :3], P[posed]) + T_w_c[:, None, :3, 3]
    X = np.full((P.shape[1], 3), np.nan)
    for j in range(P.shape[1]):
        pts = Pw[:, j][np.all(np.isfinite(Pw[:, j]), axis=1)]
        if len(pts) < min_frames:
            continue
        X[j] = centre = np.median(pts, axis=0)
        if inlier_m is not None:
            near = pts[np.linalg.norm(pts - centre, axis=1) < inlier_m]
            X[j] = np.median(near, axis=0) if len(near) >= min_frames else centre
    return X


def _median_reprojection_px(K, T_c_w, X, uv, ok):
    """Median reprojection error (21,) of each joint over the posed frames that saw it (inf
    where none or the joint is unknown)."""
    posed = np.all(np.isfinite(T_c_w[:, :3, 3]), axis=1)
    Xc = np.einsum("mab,jb->mja", T_c_w[posed, :3, :3], X) + T_c_w[posed, None, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = (Xc[..., :2] / Xc[..., 2:]) * np.diag(K)[:2] + K[:2, 2]
    err = np.where(ok[posed], np.linalg.norm(proj - uv[posed], axis=2), np.nan)
    out = np.full(len(X), np.inf)
    seen = np.isfinite(err).any(0)
    out[seen] = np.nanmedian(err[:, seen], axis=0)
    return out


def _triangulate(K, T_c_w, uv, ok, reject_px):
    """Each joint from every posed frame that saw it (``triangulate_multiview``); NaN rows
    for joints seen by fewer than two posed frames."""
    posed = np.all(np.isfinite(T_c_w[:, :3, 3]), axis=1)
    X = np.full((ok.shape[1], 3), np.nan)
    for j in range(ok.shape[1]):
        views = np.flatnonzero(posed & ok[:, j])
        if len(views) >= 2:
            Xj = triangulate_multiview(K, T_c_w[views], uv[views, j], reject_px)
            if Xj is not None:
                X[j] = Xj
    return X

