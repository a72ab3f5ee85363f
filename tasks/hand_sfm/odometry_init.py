"""A third initialisation of the static-hand SfM problem: the cameras chained by registering
each frame's depth surface onto its predecessor's.

The two-view start and the depth-backprojected joints (``hand_sfm.depth_init``) both pose the
cameras from the keypoints. A real detector's keypoints miss by 5-10 % of the hand's image
size, correlated over neighbouring frames: cameras posed from them are off by 6-35 deg (rig
real-detector sessions), and the depth links, which refine a keypoint solve by at most a few
degrees, then find nothing to refine. The depth surface of the static hand and the object it
holds needs no keypoints beyond a crop: neighbouring frames move a few degrees, so each
frame's surface registers onto its predecessor's from no motion (``depth_links.icp_batch``),
and the chained registrations give every camera of the chain in metres. The joints are then
triangulated from the pixels with those cameras (the rays of ~50 frames average the detector's
error), and frames off the chain posed by PnP against them.

``reconstruct_hand`` tries it as a restart (``hand_sfm.restart``): kept only when more of the
depth readings agree with its result.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from graspcap.tasks.core.geometry import inv_T, rotation_error_deg
from graspcap.tasks.hand_sfm.depth_links import DepthLink, DepthLinkConfig, icp_batch
from graspcap.tasks.hand_sfm.surface_clouds import SurfaceCloud
from graspcap.tasks.hand_sfm.two_view_init import (
    Initialisation,
    TwoView,
    pnp,
    ray_angles_deg,
    triangulate_multiview,
)


def chain_cameras(
    surfaces: Sequence[SurfaceCloud | None], K: np.ndarray, cfg: DepthLinkConfig,
    max_skip: int = 3,
    max_gap: int = 4,
    max_rmse_m: float = 0.002,
) -> tuple[np.ndarray, list[DepthLink]]:
    """T_c_w (m, 4, 4) of the frames whose surfaces chain (world = the chain's first camera),
    NaN elsewhere, and the registrations that chained them (one into each chained frame but
    the start, ``a`` the frame it was registered onto).

    Away from the start, each frame's surface is registered onto the last chained frame's (from
    the last motion between neighbours continued over the gap, then from no motion), else
    onto one of the ``max_skip`` chained frames before it, at most ``max_gap`` frames back (a
    wrong surface, a crop around a wrong detection, breaks no chain: it is skipped; over a
    longer gap the motion is unknown and a registration may slip). A registration counts
    when it overlaps by ``min_overlap``, fits within ``max_rmse_m`` (stricter than a link's
    ``cfg.max_rmse_m``: a chain carries every slip on; rig registrations of neighbours fit
    to 0.6-1.0 mm) and finds at most
    ``max_step_*`` of motion. The chain grows both ways from its start, tried at six evenly
    spaced frames; the longest is kept (the first covering 80 % of the surfaces at once).
    """
    m = len(surfaces)
    have = [i for i in range(m) if surfaces[i] is not None]
    best = np.full((m, 4, 4), np.nan)
    best_links: list[DepthLink] = []
    if len(have) < 2:
        return best, best_links
    starts = list(dict.fromkeys(have[k] for k in np.linspace(0, len(have) - 1, 6).astype(int)))
    for start in starts:
        T = np.full((m, 4, 4), np.nan)
        T[start] = np.eye(4)
        links: list[DepthLink] = []
        for order in ([i for i in have if i > start], [i for i in have if i < start][::-1]):
            _grow(surfaces, K, cfg, T, start, order, max_skip, max_gap, max_rmse_m, links)
        if len(links) + 1 > np.isfinite(best[:, 0, 0]).sum():
            best, best_links = T, links
        if len(links) + 1 >= 0.8 * len(have):
            break
    return best, best_links


def _grow(surfaces, K, cfg, T, start, order, max_skip, max_gap, max_rmse_m, links) -> None:
    """Chain the frames of ``order`` (away from ``start``, in time order either way) onto
    the chain (``T`` (m, 4, 4) filled in place, each registration appended to ``links``)."""
    chain = [start]
    step = np.eye(4)  # the last motion between neighbouring chained frames (a onto b)
    for b in order:
        tries = [(a, g) for a in chain[::-1][:max_skip] if abs(b - a) <= max_gap
                 for g in (np.linalg.matrix_power(step, abs(b - a)), np.eye(4))]  # fmt: skip
        for a, guess in tries:
            T_a_b, info, rmse, overlap = icp_batch(
                [surfaces[a], surfaces[b]], np.array([[0, 1]]), guess[None], K,
                max_points=cfg.max_points, max_distance_m=cfg.max_distance_m,
                huber_m=cfg.huber_m, iterations=cfg.iterations, sigma_m=cfg.sigma_m,
                effective_points=cfg.effective_points,
            )  # fmt: skip
            R, t = T_a_b[0, :3, :3], T_a_b[0, :3, 3]
            angle = rotation_error_deg(np.eye(3), R)
            if (overlap[0] >= cfg.min_overlap and rmse[0] <= max_rmse_m
                    and angle <= cfg.max_step_deg and np.linalg.norm(t) <= cfg.max_step_m):
                T[b] = inv_T(T_a_b[0]) @ T[a]  # T_b_w = (T_a_b)^-1 T_a_w
                chain.append(b)
                links.append(DepthLink(int(a), int(b), T_a_b[0], info[0], float(rmse[0]),
                                       float(overlap[0])))
                if abs(b - a) == 1:
                    step = T_a_b[0]
                break


def odometry_initialisation(
    surfaces: Sequence[SurfaceCloud | None],
    uv: np.ndarray,
    ok: np.ndarray,
    K: np.ndarray,
    cfg: DepthLinkConfig,
    *,
    ransac_px: float,
    min_points: int,
    min_frames: int,
) -> Initialisation | None:
    """Cameras chained by the depth surfaces, joints triangulated from the pixels, frames off
    the chain posed by PnP; metric, in the frame of the chain's first camera.

    surfaces : (m) each solve frame's surface (None without); uv : (m, 21, 2) pixels; ok :
    (m, 21) usable observations (frames rejected whole already left out). Returns None when
    the chain has fewer than ``min_frames`` cameras or fewer than ``min_points`` joints
    triangulate. The ``pair`` is the chain's first camera and the one turned furthest from it;
    ``chain`` the registrations that chained the cameras.
    """
    T, links = chain_cameras(surfaces, K, cfg)
    chained = np.all(np.isfinite(T[:, :3, 3]), axis=1)
    if chained.sum() < min_frames:
        return None
    X = np.full((ok.shape[1], 3), np.nan)
    for j in range(ok.shape[1]):
        views = np.flatnonzero(chained & ok[:, j])
        if len(views) >= 2:
            Xj = triangulate_multiview(K, T[views], uv[views, j], 3 * ransac_px)
            if Xj is not None:
                X[j] = Xj
    known = np.all(np.isfinite(X), axis=1)
    if known.sum() < min_points:
        return None
    for i in np.flatnonzero(~chained):
        sel = known & ok[i]
        pose = pnp(K, X[sel], uv[i, sel], ransac_px, min_points)
        if pose is not None:
            T[i] = pose
    a = int(np.flatnonzero(chained)[0])
    rows = np.flatnonzero(chained)
    b = int(rows[np.argmin(np.trace(T[rows, :3, :3], axis1=1, axis2=2))])
    if b == a:
        return None
    parallax = float(np.median(ray_angles_deg(T[b], X[known])))
    return Initialisation(T, X, TwoView(a, b, T[b].copy(), parallax, known),
                          links_from_start=True, chain=tuple(links))
