"""Point clouds from depth images: validity, back-projection, the platter crop, normals.

Shared by the registration stages (:mod:`registration`, :mod:`register_object`,
:mod:`estimate_adjustment`, :mod:`register_scan`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import depth_to_points, inv_T, transform_points

# open3d: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d


class PlatterCrop(StageConfig):
    """The space over the platter where the object is looked for (turntable frame)."""

    radius_m: float = 0.15
    """Radius of the platter's top surface."""
    margin_m: float = 0.03
    """Kept beyond the platter's rim (objects overhanging it)."""
    min_height_m: float = 0.004
    """Points at most this high over the platter top are the platter itself and dropped."""
    max_height_m: float = 0.35
    """Points higher than this over the platter are not the object."""
    max_range_m: float = 3.0
    """Depth beyond this is treated as invalid."""
    drop_flying: bool = True
    """Drop the pixels on no surface (:func:`drop_flying_pixels`: a time-of-flight camera's
    veil at depth edges) before cropping."""
    fit_platter: bool = False
    """Measure the platter top in the depth (:func:`platter_plane`) and take heights over
    that plane instead of the calibrated one. A depth image shifted by a few pixels against
    the colour camera (a Kinect's registration error), or a turntable calibration a degree
    off, reads the platter millimetres above or below its calibrated height: wild
    [80625, 4] read it 3.7 mm up, tilted 1 deg, and half of the points over the platter
    (its top, above ``min_height_m``) were kept as the object."""
    platter_search_m: float = 0.012
    """The platter top is looked for within this of its calibrated height."""
    platter_noise_k: float = 3.0
    """Over a measured platter, points at most ``max(min_height_m, this x the plane's
    robust residual sigma)`` above it are the platter."""
    platter_max_tilt_deg: float = 5.0
    """A measured plane tilted more than this from the calibrated one is not the platter
    (the calibrated plane is kept)."""


def to_pcd(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """Open3D cloud from ``points`` (n, 3) and optional ``normals`` (n, 3)."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=float))
    return pcd


def valid_depth(depth_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """Depth (h, w) with non-finite, negative and beyond-range values set to 0."""
    d = np.asarray(depth_m, dtype=float)
    if d.ndim != 2:
        raise ValueError(f"depth has shape {d.shape}, expected (h, w)")
    return np.where(np.isfinite(d) & (d > 0) & (d <= max_range_m), d, 0.0)


def drop_flying_pixels(
    depth_m: np.ndarray, K: np.ndarray, tol_m: float = 0.008, slope: float = 4.0,
    min_neighbours: int = 3,
    min_share: float = 1e-3,
) -> np.ndarray:
    """Depth (h, w) with the pixels that lie on no surface set to 0: those with fewer than
    ``min_neighbours`` of their 8 neighbours within ``max(tol_m, slope * z / f)`` of their own
    depth AND both a nearer and a farther pixel within two pixels. A time-of-flight camera
    (Kinect v2) reads a depth between the near and the far side at a depth edge ("flying
    pixels", a veil along the silhouette, a ramp from the one side to the other): such a pixel
    has nearly no neighbour at its depth, where a surface pixel, its silhouette's rim
    included, has at least three (``slope`` pixel spacings per pixel: a surface seen at 76 deg
    of incidence, the grazing limit of such sensors). A clean camera's silhouette pixel (a
    thin corner of the rim, or the background beside it) has a nearer or a farther pixel
    beside it, never both, and is never touched: dropping a realistic bottle's silhouette
    corners flipped its registration to the symmetric twin. An image in which fewer than
    ``min_share`` of the valid pixels are such is returned unchanged (a realistic stage-1
    image had 0.07 % under the one-sided rule, a wild grasp frame 0.2 %). The veil joins a
    held object to everything behind it and costs registration its inliers; a surface loses
    at most isolated pixels."""
    d = np.asarray(depth_m, dtype=np.float32)
    h, w = d.shape
    f = float(np.asarray(K, float)[0, 0])
    tol = np.maximum(np.float32(tol_m), np.float32(slope / f) * d)
    pad = np.pad(d, 2)
    agree = np.zeros((h, w), np.int8)
    nearer = np.zeros((h, w), bool)
    farther = np.zeros((h, w), bool)
    for dv in range(-2, 3):
        for du in range(-2, 3):
            if dv == 0 and du == 0:
                continue
            nb = pad[2 + dv : 2 + dv + h, 2 + du : 2 + du + w]
            valid = nb > 0
            if abs(dv) <= 1 and abs(du) <= 1:
                agree += valid & (np.abs(nb - d) <= tol)
            nearer |= valid & (nb < d - tol)
            farther |= valid & (nb > d + tol)
    # between a nearer and a farther surface (within 2 pixels: a veil is a ramp from the near
    # side to the far one) and on no surface; a clean camera's silhouette pixel, its rim or
    # the background beside it, has only one of the two and is never touched
    flying = (d > 0) & (agree < min_neighbours) & nearer & farther
    if flying.sum() < min_share * max(int((d > 0).sum()), 1):
        return np.asarray(depth_m, float)  # no veil: the depth as it is, bit for bit
    return np.where((d > 0) & ~flying, np.asarray(depth_m, float), 0.0)


def cloud_from_depth(
    depth_m: np.ndarray, K: np.ndarray, keep: np.ndarray | None = None
) -> np.ndarray:
    """Camera-frame points (n, 3) of the valid pixels of ``depth_m`` (h, w), optionally only
    where the boolean image ``keep`` (h, w) is True."""
    d = depth_m if keep is None else np.where(keep, depth_m, 0.0)
    return depth_to_points(d, np.asarray(K, dtype=float))[0]


def platter_depth(depth_m: np.ndarray, K: np.ndarray, crop: PlatterCrop) -> np.ndarray:
    """The depth (h, w) the platter crop uses: valid pixels within range, without flying
    pixels when ``crop.drop_flying``."""
    d = valid_depth(depth_m, crop.max_range_m)
    return drop_flying_pixels(d, K) if crop.drop_flying else d


def crop_platter(
    depth_m: np.ndarray, K: np.ndarray, T_color_turntable: np.ndarray, crop: PlatterCrop,
    prepared: bool = False,
) -> np.ndarray:
    """Colour-frame points (n, 3) of the valid pixels of ``depth_m`` (h, w) that lie over the
    platter (turntable frame: origin at the centre of its top, z up); ``prepared``: the depth
    is :func:`platter_depth`'s already. With ``crop.fit_platter`` the heights are taken over
    the platter top measured in the depth (:func:`platter_plane`)."""
    pts_c = cloud_from_depth(depth_m if prepared else platter_depth(depth_m, K, crop), K)
    pts_t = transform_points(inv_T(np.asarray(T_color_turntable, float)), pts_c)
    r = np.linalg.norm(pts_t[:, :2], axis=1)
    z = pts_t[:, 2]
    floor = crop.min_height_m
    if crop.fit_platter:
        plane = platter_plane(pts_t, crop)
        # a plane within one reading's noise of the calibrated one everywhere on the platter
        # confirms the calibration: the calibrated plane stays (realistic depth: 0.7-0.8 mm
        # at the rim, noise 1.0-1.4 mm; wild [80625, 4]: 6.4 mm, noise 1.4 mm)
        if plane is not None and platter_departure_m(plane[0], crop.radius_m) > plane[1]:
            coef, sigma_m = plane
            z = z - (pts_t[:, 0] * coef[0] + pts_t[:, 1] * coef[1] + coef[2])
            floor = max(crop.min_height_m, crop.platter_noise_k * sigma_m)
    keep = (r <= crop.radius_m + crop.margin_m) & (z >= floor)
    return pts_c[keep & (z <= crop.max_height_m)]


def platter_departure_m(coef: np.ndarray, radius_m: float) -> float:
    """Largest height (m) of the plane ``z = coef[0] x + coef[1] y + coef[2]`` over the
    calibrated platter top (z = 0) within ``radius_m`` of its centre."""
    return abs(float(coef[2])) + radius_m * float(np.hypot(coef[0], coef[1]))


def platter_plane(
    pts_t: np.ndarray, crop: PlatterCrop, min_points: int = 500, rounds: int = 4
) -> tuple[np.ndarray, float] | None:
    """The platter top as the depth shows it: ``(coef, sigma_m)`` with the plane
    ``z = coef[0] x + coef[1] y + coef[2]`` (turntable frame, metres) and the robust sigma of
    its residuals; None when fewer than ``min_points`` of the points ``pts_t`` (n, 3,
    turntable frame) lie on the platter within ``crop.platter_search_m`` of its calibrated
    height, or the plane found tilts more than ``crop.platter_max_tilt_deg``.

    A least-squares plane trimmed ``rounds`` times to the points within 2.5 robust sigmas
    (at least 1 mm) below and above it: the object's base, which rises from the platter, is
    trimmed with the rest of the object."""
    r = np.linalg.norm(pts_t[:, :2], axis=1)
    near = (r <= crop.radius_m) & (np.abs(pts_t[:, 2]) <= crop.platter_search_m)
    if near.sum() < min_points:
        return None
    P = pts_t[near]
    A = np.c_[P[:, :2], np.ones(len(P))]
    coef = np.array([0.0, 0.0, float(np.median(P[:, 2]))])
    sigma = 0.0
    for _ in range(rounds):
        res = P[:, 2] - A @ coef
        sigma = 1.4826 * float(np.median(np.abs(res - np.median(res))))
        inl = np.abs(res) <= max(2.5 * sigma, 0.001)
        if inl.sum() < min_points:
            return None
        coef = np.linalg.lstsq(A[inl], P[inl, 2], rcond=None)[0]
    res = P[:, 2] - A @ coef
    sigma = 1.4826 * float(np.median(np.abs(res[np.abs(res) <= max(2.5 * sigma, 0.001)])))
    tilt_deg = np.degrees(np.arctan(np.hypot(coef[0], coef[1])))
    if tilt_deg > crop.platter_max_tilt_deg:
        return None
    return coef, sigma


def estimate_normals(pcd: o3d.geometry.PointCloud, radius_m: float, viewpoint: np.ndarray) -> None:
    """Normals by local PCA (in place), oriented towards ``viewpoint`` (3,)."""
    import open3d as o3d

    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    pcd.orient_normals_towards_camera_location(np.asarray(viewpoint, dtype=float))
