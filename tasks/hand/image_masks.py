"""Image masks of the hand from its 2D keypoints (the object stages and the per-frame
validity leave the hand's pixels out of the object's)."""

from __future__ import annotations

import numpy as np

from graspcap.tasks.hand.model import RIGID_PALM_POINTS, SKELETON

# cv2: imported where used, so that importing the stage table stays cheap


def grow_mask(mask: np.ndarray, dilate_px: int) -> np.ndarray:
    """The boolean image ``mask`` (h, w) grown by ``dilate_px`` pixels."""
    import cv2

    if dilate_px <= 0:
        return mask
    k = 2 * dilate_px + 1
    return cv2.dilate(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)


HAND_BONES = (*SKELETON, (5, 9), (9, 13), (13, 17))
"""Connected keypoint pairs of the 21-point layout (fingers, palm rim)."""
PALM = RIGID_PALM_POINTS


def hand_mask_from_keypoints(
    keypoints_2d: np.ndarray,
    conf: np.ndarray,
    shape: tuple[int, int],
    radius_px: float,
    min_conf: float = 0.1,
) -> np.ndarray:
    """Pixels (h, w) bool covered by the hand: bones between confident connected keypoints
    drawn ``radius_px`` thick, plus the palm polygon when three or more palm points are
    confident.

    Parameters
    ----------
    keypoints_2d : (21, 2) float
        Pixel coordinates (x, y), 21-point layout.
    conf : (21,) float
        Detection confidence; points below ``min_conf`` are ignored.
    """
    import cv2

    kp = np.asarray(keypoints_2d, dtype=float)
    ok = np.asarray(conf, dtype=float) >= min_conf
    ok &= np.all(np.isfinite(kp), axis=1)
    mask = np.zeros(shape, np.uint8)
    r = max(int(round(radius_px)), 1)
    pts = np.round(np.where(ok[:, None], kp, 0.0)).astype(np.int32)
    for a, b in HAND_BONES:
        if ok[a] and ok[b]:
            cv2.line(mask, tuple(pts[a]), tuple(pts[b]), 1, thickness=2 * r + 1)
    for i in np.flatnonzero(ok):
        cv2.circle(mask, tuple(pts[i]), r, 1, thickness=-1)
    palm = [i for i in PALM if ok[i]]
    if len(palm) >= 3:
        cv2.fillPoly(mask, [cv2.convexHull(pts[palm])], 1)
    return mask.astype(bool)
