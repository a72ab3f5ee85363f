"""Where the held object can be in a steady frame: the depth around the hand.

Used by :mod:`estimate_adjustment`: the hand's own points (its largest Euclidean cluster),
the clusters near it that are no wider than the object (in each steady frame on its own),
the points either registration path can reach, the hand mask drawn from the keypoints and
grown.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.core.render import render
from graspcap.tasks.hand.image_masks import hand_mask_from_keypoints
from graspcap.tasks.object_pose.registration.point_clouds import to_pcd

if TYPE_CHECKING:
    from graspcap.tasks.object_pose.estimate_adjustment import EstimateAdjustmentConfig
    from graspcap.tasks.object_pose.registration.engine import Model

# scipy: imported where used, so that importing the stage table stays cheap

_WEIGH_PIXELS = 20000
"""At most this many masked pixels (evenly strided) weigh the clusters in :func:`hand_cluster`."""


class RegionConfig(Protocol):
    """The settings :func:`near_hand` and :func:`within_reach` read (fields of
    ``EstimateAdjustmentConfig``)."""

    min_hand_points: int
    stage1_reach_m: float
    region_margin_m: float
    cluster_voxel_m: float
    cluster_eps_m: float


def hand_cluster(points: np.ndarray, voxel_m: float, eps_m: float) -> np.ndarray:
    """The hand's own points (k, 3, on a ``voxel_m`` grid) among the masked pixels' ``points``
    (n, 3): the Euclidean cluster holding the most of them. The mask's rim and the gaps
    between fingers also hold pixels of the table or platter behind the hand; counted as
    hand, they would make the background "touch" it. Clusters are weighed by the pixels they
    hold, not by their voxels: a hand 0.35 m away has ~7 pixels per 4 mm voxel, the
    background seen through a mask drawn from a real detector's keypoints at 1 m under one
    (real-detector [56705, 3]: a 2393-voxel piece of background at 1.07 m outweighed the hand
    and the object was looked for there)."""
    from scipy.spatial import cKDTree

    down = to_pcd(points).voxel_down_sample(voxel_m)
    labels = np.asarray(down.cluster_dbscan(eps_m, 4))
    pts = np.asarray(down.points)
    if not (labels >= 0).any():
        return pts
    sample = points[:: max(1, len(points) // _WEIGH_PIXELS)]
    held = labels[cKDTree(pts).query(sample, k=1)[1]]
    return pts[labels == np.bincount(held[held >= 0], minlength=labels.max() + 1).argmax()]


def near_hand(
    points: np.ndarray, hand_pts: np.ndarray, radius_m: float, cfg: RegionConfig
) -> np.ndarray:
    """The points near the hand that may be the object: the Euclidean clusters no wider than
    the object (every point within ``radius_m`` + margin of the cluster's centroid) that come
    within ``radius_m`` + margin of the hand (the hand splits the object into pieces, so
    several; the table and platter are wider or further), else the cluster nearest the hand.
    Pieces of the hand the mask missed are kept too: registration treats them as outliers."""
    from scipy.spatial import cKDTree

    if len(hand_pts) < cfg.min_hand_points:
        return points
    hand = hand_cluster(hand_pts, cfg.cluster_voxel_m, cfg.cluster_eps_m)
    tree = cKDTree(hand)
    reach = radius_m + cfg.region_margin_m
    # clusters on the voxel grid of the points in the hand's box grown by twice the reach (no
    # farther point can be kept; the box test is cheap, voxelising every frame's points is
    # not); full-resolution points only inside the kept clusters' box (KD queries of a whole
    # frame's points cost seconds; the KD queries stop searching beyond twice their radius)
    grow = 2 * reach + cfg.cluster_voxel_m
    around = np.all((points >= hand.min(0) - grow) & (points <= hand.max(0) + grow), axis=1)
    points = points[around]
    grid = np.asarray(to_pcd(points).voxel_down_sample(cfg.cluster_voxel_m).points)
    pts = grid[tree.query(grid, k=1, distance_upper_bound=4 * reach)[0] <= 2 * reach]
    if len(pts) == 0:
        return points[:0]
    labels = np.asarray(to_pcd(pts).cluster_dbscan(cfg.cluster_eps_m, 4))
    clustered = labels >= 0
    if not clustered.any():
        kept = pts
    else:
        gap = tree.query(pts, k=1)[0]
        object_like = []
        for label in range(labels.max() + 1):
            piece = labels == label
            width = np.linalg.norm(pts[piece] - pts[piece].mean(0), axis=1).max()
            if width <= reach and gap[piece].min() <= reach:
                object_like.append(label)
        touching = object_like or labels[clustered][[np.argmin(gap[clustered])]]
        kept = pts[np.isin(labels, touching)]
    tol = cfg.cluster_voxel_m * 1.5
    box = np.all((points >= kept.min(0) - tol) & (points <= kept.max(0) + tol), axis=1)
    cand = points[box]
    return cand[cKDTree(kept).query(cand, k=1, distance_upper_bound=2 * tol)[0] <= tol]


def region_per_view(
    points: list[np.ndarray], hand_pts: list[np.ndarray], radius_m: float, cfg: RegionConfig
) -> np.ndarray:
    """The object's points near the hand (:func:`near_hand`) found in each view on its own and
    joined (``points``, ``hand_pts``: each view's (n, 3) in one frame): fused first, the views'
    clouds sit a camera error apart (a degree is 10 mm at the object's far side), the object's
    pieces merge with each other and with the table into clusters wider than the object, and
    only a sliver was left (wild [78643, 9]: 34 points of 7 views). Views without enough hand
    points of their own are left out while one has them."""
    with_hand = [(p, h) for p, h in zip(points, hand_pts, strict=True)
                 if len(h) >= cfg.min_hand_points]  # fmt: skip
    if not with_hand:
        return near_hand(np.concatenate(points), np.concatenate(hand_pts), radius_m, cfg)
    return np.concatenate([near_hand(p, h, radius_m, cfg) for p, h in with_hand])


def within_reach(
    points: np.ndarray, hand_pts: np.ndarray, centres: list[np.ndarray], radius_m: float,
    cfg: RegionConfig,
) -> np.ndarray:
    """The ``points`` (n, 3) either registration path can use: within the box of the hand's
    own points (:func:`hand_cluster`) grown as :func:`near_hand` grows it, or within
    ``radius_m + stage1_reach_m`` of a register_object hypothesis's object centre (``centres``,
    each (3,); path 1). Every view's every pixel, carried into the first frame, cost seconds of
    distance computations per hypothesis."""
    keep = np.zeros(len(points), bool)
    for centre in centres:
        keep |= np.linalg.norm(points - centre, axis=1) <= radius_m + cfg.stage1_reach_m
    if len(hand_pts) < cfg.min_hand_points:
        return points
    hand = hand_cluster(hand_pts, cfg.cluster_voxel_m, cfg.cluster_eps_m)
    grow = 2 * (radius_m + cfg.region_margin_m) + 2 * cfg.cluster_voxel_m
    keep |= np.all((points >= hand.min(0) - grow) & (points <= hand.max(0) + grow), axis=1)
    return points[keep]


def hand_mask(
    shape: tuple[int, int],
    K: np.ndarray,
    T_c_w: np.ndarray,
    hand_mesh_w: tuple[np.ndarray, np.ndarray],
    keypoints: np.ndarray,
    bone_radius_px: float = 6.0,
) -> np.ndarray:
    """Pixels (h, w) bool of a frame the hand covers: the fitted hand mesh (world vertices,
    faces) rendered by the frame's camera ``T_c_w``, plus the detected keypoints' bones
    (``keypoints`` (21, 3): pixels and confidence) in case the fit misses a finger."""
    h, w = shape
    rendered = render([hand_mesh_w], [T_c_w], K, w, h)
    bones = hand_mask_from_keypoints(keypoints[:, :2], keypoints[:, 2], (h, w), bone_radius_px)
    return (rendered.mesh_index >= 0) | bones


def needed_pixels(
    views: list, K: np.ndarray, model: Model, area_m2: float, T_w_o: np.ndarray,
    config: EstimateAdjustmentConfig,
) -> int:
    """The judged pixels a pose ``T_w_o`` needs (``min_points``, ``min_visible_share``): the
    object's mean silhouette (``area_m2`` / 4, its surface area's quarter) at its centroid's
    distance in every view, at the agreement's stride."""
    f2 = float(K[0, 0] * K[1, 1]) / max(config.agree_stride_px, 1) ** 2
    centre = T_w_o[:3, :3] @ model.centroid + T_w_o[:3, 3]
    expected = 0.0
    for _, _, T_ref_c in views:
        z = float((inv_T(T_ref_c)[:3, :3] @ centre + inv_T(T_ref_c)[:3, 3])[2])
        expected += area_m2 / 4 * f2 / max(z, 0.05) ** 2
    share = int(np.ceil(config.min_visible_share * expected))
    return max(config.min_points_floor, min(config.min_points, share))


def surface_area_m2(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Surface area of a triangle mesh (vertices (n, 3) metres, faces (m, 3))."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return 0.5 * float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
