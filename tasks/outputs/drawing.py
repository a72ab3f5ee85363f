"""Drawing helpers of the QA pictures (``tasks/outputs/pictures.py``): colours, colour maps, labels,
depth colourisation and PNG encoding. RGB ``uint8`` images throughout."""

from __future__ import annotations

import numpy as np

from graspcap.tasks.core.geometry import project, transform_points

# cv2: imported where used, so that importing the stage table stays cheap

BACKGROUND_RGB = (245, 245, 245)
UNOBSERVED_RGB = (150, 150, 150)
SKIN_RGB = (226, 188, 160)
MODEL_RGB = (0, 230, 255)
OUTLIER_RGB = (255, 0, 255)
CONTACT_STOPS = np.array([[40, 90, 220], [250, 215, 50], [200, 20, 20]], dtype=float)
"""Contact 0, 0.5 and 1 (blue, yellow, red); linear in between."""


def encode_png(image_rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB ``(h, w, 3) uint8`` image."""
    import cv2

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(image_rgb),
                                                cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"cv2.imencode failed on an image of shape {image_rgb.shape}")
    return buf.tobytes()


def decode_png(data: bytes) -> np.ndarray:
    """RGB ``(h, w, 3) uint8`` image from PNG bytes (the inverse of :func:`encode_png`)."""
    import cv2

    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def colorize_depth(depth_m: np.ndarray, range_m: tuple[float, float] | None = None
                   ) -> np.ndarray:
    """Depth ``(h, w)`` metres as RGB ``(h, w, 3) uint8``: near bright, far dark over
    ``range_m`` (default: 2nd to 98th percentile of the measured depth; depth outside it is
    clipped), no measurement black."""
    import cv2

    depth = np.asarray(depth_m, dtype=float)
    valid = np.isfinite(depth) & (depth > 0)
    out = np.zeros((*depth.shape, 3), np.uint8)
    if not valid.any():
        return out
    lo, hi = np.percentile(depth[valid], [2, 98]) if range_m is None else range_m
    t = np.clip((hi - depth) / max(hi - lo, 1e-6), 0.0, 1.0)
    gray = np.where(valid, 30 + 225 * t, 0).astype(np.uint8)
    coloured = cv2.cvtColor(cv2.applyColorMap(gray, cv2.COLORMAP_BONE), cv2.COLOR_BGR2RGB)
    out[valid] = coloured[valid]
    return out


def hand_depth_range(depth_m: np.ndarray, detected: np.ndarray, min_conf: float = 0.05,
                     before_m: float = 0.05, behind_m: float = 0.15
                     ) -> tuple[float, float] | None:
    """A depth range around the detected hand (``detected`` (21, 3) x_px, y_px, conf): from
    ``before_m`` nearer than its nearest keypoint to ``behind_m`` beyond its farthest;
    None when no keypoint has a depth."""
    depth = np.asarray(depth_m, dtype=float)
    h, w = depth.shape
    uv = np.rint(detected[detected[:, 2] > min_conf, :2]).astype(int)
    uv = uv[(uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)]
    z = depth[uv[:, 1], uv[:, 0]] if len(uv) else np.zeros(0)
    z = z[np.isfinite(z) & (z > 0)]
    if not len(z):
        return None
    return float(z.min() - before_m), float(z.max() + behind_m)


def confidence_rgb(conf: float) -> tuple[int, int, int]:
    """Red (0) through yellow to green (1)."""
    import cv2

    hue = int(round(60 * float(np.clip(conf, 0.0, 1.0))))
    rgb = cv2.cvtColor(np.array([[[hue, 255, 255]]], np.uint8), cv2.COLOR_HSV2RGB)[0, 0]
    return tuple(int(c) for c in rgb)


def label(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45,
          color: tuple[int, int, int] = (255, 255, 255), box: bool = True) -> None:
    """``text`` with its baseline at ``org``; on a dark box unless ``box`` is False."""
    import cv2

    if not text:
        return
    if box:
        (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        x0, y0 = max(org[0] - 3, 0), max(org[1] - th - 3, 0)
        x1, y1 = min(org[0] + tw + 3, img.shape[1]), min(org[1] + base + 2, img.shape[0])
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * 0.35).astype(np.uint8)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, color, 1, cv2.LINE_AA)


def contact_rgb(contact: np.ndarray) -> np.ndarray:
    """Contact values (...) in [0, 1] -> RGB (..., 3) float in [0, 255] (``CONTACT_STOPS``)."""
    t = np.clip(np.asarray(contact, dtype=float), 0.0, 1.0) * (len(CONTACT_STOPS) - 1)
    i = np.minimum(t.astype(int), len(CONTACT_STOPS) - 2)
    f = (t - i)[..., None]
    return CONTACT_STOPS[i] * (1 - f) + CONTACT_STOPS[i + 1] * f


def silhouette(shape: tuple[int, int], V: np.ndarray, F: np.ndarray, T_c_o: np.ndarray,
               K: np.ndarray) -> np.ndarray:
    """Mask (h, w) bool of the mesh ``(V, F)`` (object frame) projected by ``T_c_o`` and
    ``K``; triangles with a vertex at or behind the camera plane are left out."""
    import cv2

    h, w = shape
    pts_c = transform_points(np.asarray(T_c_o, float), V)
    mask = np.zeros((h, w), np.uint8)
    front = pts_c[:, 2] > 1e-6
    if not front.any():
        return mask.astype(bool)
    uv = np.full((len(V), 2), np.nan)
    uv[front] = project(K, pts_c[front])
    tris = F[np.all(front[F], axis=1)]
    if len(tris):
        poly = np.rint(uv[tris] * 8).astype(np.int64)  # 3 bits of sub-pixel precision
        lo, hi = poly.min(axis=1), poly.max(axis=1)
        keep = (np.all(np.abs(poly) < (1 << 28), axis=(1, 2)) & (hi[:, 0] >= 0)
                & (hi[:, 1] >= 0) & (lo[:, 0] < w * 8) & (lo[:, 1] < h * 8))
        # one call per triangle: fillPoly on many polygons fills their even-odd union
        for tri in poly[keep].astype(np.int32):
            cv2.fillConvexPoly(mask, tri, 1, cv2.LINE_8, shift=3)
    return mask.astype(bool)


def outline(img: np.ndarray, mask: np.ndarray, colour: tuple[int, int, int],
            thickness: int = 1) -> None:
    """Draw the outer contours of ``mask`` (h, w) on ``img`` in place."""
    import cv2

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, colour, thickness, cv2.LINE_AA)
