"""A camera's lens: pinhole intrinsics ``K`` with OpenCV distortion ``dist``.

Real Kinect and webcam lenses are not pinhole; ``session.json`` gives each camera's OpenCV
distortion (k1 k2 p1 p2 [k3 ...], ``cv2.projectPoints`` semantics). The builder converts at
the boundary, once, into *ideal* pixels: the pixels of a pinhole camera with the same ``K``
(``P = K`` in ``cv2.undistortPoints``). Keypoints are undistorted into ideal pixels before any
geometry, depth images are resampled into the ideal image (:meth:`Camera.undistort_image`),
and every stage past that boundary projects with ``K`` alone. Only what is drawn on or read
from a raw (distorted) image goes back through :meth:`Camera.project`: the pictures, and the
thermal images of the contact map.

With ``dist`` all zeros every method returns its input's pinhole result bit for bit (nothing
is resampled or iterated), so undistorted sessions build exactly as before.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from graspcap.tasks.core.geometry import project as pinhole_project

# cv2: imported where used, so that importing the stage table stays cheap

UNDISTORT_CRITERIA = (3, 50, 1e-12)  # 3: cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS
"""``cv2.undistortPoints`` iterations: OpenCV's default (5 iterations) leaves a tenth of a
pixel at a webcam's corners; 50 reach 1e-6 px on any lens the contract accepts."""

FIELD_MARGIN = 1.5
"""Points whose ideal normalised radius is beyond this times the image's own (its corners')
are outside the lens's calibrated field: the distortion polynomial there may fold back into
the image, so :meth:`Camera.project` gives them NaN, never a pixel."""


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics ``K`` (3, 3), OpenCV distortion ``dist`` (n,) and the image size, pixels."""

    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    distorted: bool = field(init=False)
    """Whether any distortion coefficient is non-zero (False: a pinhole camera)."""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=float).reshape(3, 3)
        dist = np.asarray(self.dist, dtype=float).reshape(-1)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "distorted", bool(np.any(dist != 0)))

    @classmethod
    def of(cls, camera) -> Camera:
        """From a manifest camera (``color_camera``, ``thermal_camera``): K, dist, width,
        height."""
        return cls(np.asarray(camera.K, dtype=float), np.asarray(camera.dist, dtype=float),
                   int(camera.width), int(camera.height))

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels."""
        return self.width, self.height

    def project(self, points_c: np.ndarray) -> np.ndarray:
        """Camera-frame points (n, 3) -> pixels of the raw (distorted) image (n, 2), as
        ``cv2.projectPoints``; NaN for points outside the lens's field (:data:`FIELD_MARGIN`)
        or at z <= 0. Pinhole ``geometry.project`` when ``dist`` is zero."""
        points_c = np.asarray(points_c, dtype=float).reshape(-1, 3)
        ideal = pinhole_project(self.K, points_c)
        if not self.distorted:
            return ideal
        ideal[~(points_c[:, 2] > 0)] = np.nan
        return self.distort_px(ideal)

    def distort_px(self, ideal_px: np.ndarray) -> np.ndarray:
        """Ideal (pinhole) pixels (n, 2) -> raw image pixels (n, 2); NaN rows stay NaN, and
        pixels outside the lens's field become NaN. The identity when ``dist`` is zero."""
        import cv2

        ideal_px = np.asarray(ideal_px, dtype=float).reshape(-1, 2)
        if not self.distorted:
            return ideal_px.copy()
        out = np.full(ideal_px.shape, np.nan)
        xy = self._normalised(ideal_px)
        ok = np.isfinite(xy).all(axis=1) & ((xy**2).sum(axis=1) <= self._field_r2)
        if ok.any():
            rays = np.concatenate([xy[ok], np.ones((int(ok.sum()), 1))], axis=1)
            px, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), self.K, self.dist)
            out[ok] = px.reshape(-1, 2)
        return out

    def undistort_px(self, px: np.ndarray) -> np.ndarray:
        """Raw image pixels (n, 2) -> ideal pinhole pixels (n, 2) (``cv2.undistortPoints``
        with ``P = K``); NaN rows stay NaN. The identity (a copy) when ``dist`` is zero."""
        import cv2

        px = np.asarray(px, dtype=float).reshape(-1, 2)
        if not self.distorted:
            return px.copy()
        out = np.full(px.shape, np.nan)
        ok = np.isfinite(px).all(axis=1)
        if ok.any():
            und = cv2.undistortPoints(px[ok].reshape(-1, 1, 2), self.K, self.dist, None, None,
                                      self.K, UNDISTORT_CRITERIA)
            out[ok] = und.reshape(-1, 2)
        return out

    def undistort_keypoints(self, keypoints: np.ndarray) -> np.ndarray:
        """Keypoints (..., 3) as (x_px, y_px, confidence) in the raw image -> the same with
        ideal pixels; confidences untouched. Returned as is (not copied) when ``dist`` is zero."""
        keypoints = np.asarray(keypoints)
        if not self.distorted:
            return keypoints
        out = np.array(keypoints, dtype=float)
        flat = out.reshape(-1, out.shape[-1])
        flat[:, :2] = self.undistort_px(flat[:, :2])
        return out

    def undistort_image(self, image: np.ndarray, *, nearest: bool = True) -> np.ndarray:
        """A raw image of this camera (h, w[, c]) resampled into the ideal pinhole image of
        the same ``K`` and size; 0 where the ideal pixel's ray misses the raw image.

        ``nearest`` (depth): each ideal pixel takes the raw pixel nearest to where its ray
        lands, so depth values are never blended across an edge (a ray is then off by at most
        half a raw pixel); else bilinear. Returned as is when ``dist`` is zero.
        """
        import cv2

        if not self.distorted:
            return image
        h, w = image.shape[:2]
        map_x, map_y = _undistort_maps(self.K.tobytes(), self.dist.tobytes(), w, h)
        return cv2.remap(image, map_x, map_y, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def _normalised(self, px: np.ndarray) -> np.ndarray:
        """Pixels (n, 2) -> normalised image coordinates (n, 2) through ``K`` (skew included)."""
        fx, s, cx = self.K[0]
        fy, cy = self.K[1, 1], self.K[1, 2]
        y = (px[:, 1] - cy) / fy
        x = (px[:, 0] - cx - s * y) / fx
        return np.stack([x, y], axis=1)

    @property
    def _field_r2(self) -> float:
        return _field_r2(self.K.tobytes(), self.dist.tobytes(), self.width, self.height)


@lru_cache(maxsize=16)
def _field_r2(K: bytes, dist: bytes, width: int, height: int) -> float:
    """Squared normalised radius of the lens's field: :data:`FIELD_MARGIN` times the largest
    ideal radius of the raw image's border."""
    cam = Camera(np.frombuffer(K).reshape(3, 3), np.frombuffer(dist), width, height)
    t = np.linspace(0.0, 1.0, 65)
    w, h = width - 1.0, height - 1.0
    border = np.concatenate([
        np.stack([t * w, np.zeros_like(t)], 1), np.stack([t * w, np.full_like(t, h)], 1),
        np.stack([np.zeros_like(t), t * h], 1), np.stack([np.full_like(t, w), t * h], 1)])
    xy = cam._normalised(cam.undistort_px(border))
    return float(FIELD_MARGIN**2 * np.nanmax((xy**2).sum(axis=1)))


@lru_cache(maxsize=8)
def _undistort_maps(K: bytes, dist: bytes, width: int, height: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.initUndistortRectifyMap`` with ``newCameraMatrix = K``: for every ideal pixel,
    where its ray lands in the raw image (two (h, w) float32 maps)."""
    import cv2

    K_ = np.frombuffer(K).reshape(3, 3)
    return cv2.initUndistortRectifyMap(K_, np.frombuffer(dist), None, K_, (width, height),
                                       cv2.CV_32FC1)


__all__ = ["FIELD_MARGIN", "UNDISTORT_CRITERIA", "Camera"]
