"""Pictures a person can look at, per session: RGB ``uint8`` images and their PNG bytes.

- :func:`keypoints_picture`: the detected 2D keypoints (dots coloured by confidence, red low
  to green high, with the hand skeleton) and the reprojected model joints (cyan crosses)
  drawn on a video frame, the colour frame when the session has one, else the depth frame
  colourised (:func:`~graspcap.tasks.outputs.drawing.colorize_depth`); beside it a zoom on the hand.
- :func:`contact_picture`: the contact map on the object from a few viewpoints around it
  (top row), and the same views with the refined hand in a skin colour (bottom row).
  Ray cast offscreen with :func:`graspcap.tasks.core.render.cast_rays` (hit triangle and
  barycentrics interpolate the per-vertex contact), Lambert-shaded by the incidence;
  unobserved surface is grey, so "unobserved" is visibly not "no contact" (blue).
- :func:`reprojection_picture`: the object model drawn where the catalog's ``T_c_o`` puts it
  in the frame (tinted silhouette, outline, object axes): the check of the object pose.
- :func:`strip_picture`: a few small frames across the grasp video, with the detections and,
  from the steady frame on, the object's outline.
- :func:`contact_ply`: the object mesh with the contact map as vertex colours (PLY), for a
  viewer a person can rotate.

The QA reasons (failures, flags) are written under the pictures (:func:`with_reasons`).

:func:`pictures` is the stage's pure entry point: it returns PNG bytes (``cv2.imencode``);
the build writes them. No display, no Open3D visualizer.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import inv_T, make_T, project, transform_points
from graspcap.tasks.core.render import cast_rays, pixel_rays
from graspcap.tasks.hand.model import SKELETON
from graspcap.tasks.outputs.drawing import (
    BACKGROUND_RGB,
    MODEL_RGB,
    OUTLIER_RGB,
    SKIN_RGB,
    UNOBSERVED_RGB,
    colorize_depth,
    confidence_rgb,
    contact_rgb,
    encode_png,
    hand_depth_range,
    label,
    outline,
    silhouette,
)

# cv2: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "pictures/2"
STAGE = "pictures"

BONES = list(SKELETON)
"""The hand skeleton in the 21-keypoint layout."""

class Background(StrEnum):
    """What the keypoints are drawn on."""

    COLOR = "color"
    """The session's colour frame."""
    DEPTH = "depth"
    """The aligned depth frame, colourised (sessions without colour video)."""


class PicturesConfig(StageConfig):
    """Sizes and viewpoints of the pictures."""

    views: int = 4
    """Viewpoints around the object in the contact picture."""
    view_px: int = 280
    """Side of one view of the contact picture (pixels)."""
    elevation_deg: float = 25.0
    """Height of the viewpoints above the object's horizontal plane; every other view is as
    far below it (the face the object stood on during the scan is unobserved)."""
    fov_deg: float = 40.0
    """Field of view of the virtual camera of the contact picture."""
    min_confidence: float = 0.05
    """Detections at or below this confidence are not drawn."""
    zoom_margin: float = 0.35
    """Margin around the keypoints of the zoomed hand view (share of their extent)."""
    strip_frames: int = 5
    """Frames in the strip across the grasp video (0: no strip)."""
    strip_height_px: int = 120
    """Height of one frame of the strip (pixels)."""


PRESETS: dict[str, PicturesConfig] = {
    "default": PicturesConfig(),
    "large": PicturesConfig(view_px=400, views=6),
}


@dataclass(frozen=True)
class Pictures:
    """Result of :func:`pictures`: PNG bytes and what they show.

    Attributes
    ----------
    keypoints_png : bytes
        :func:`keypoints_picture` of frame ``frame``.
    contact_png : bytes or None
        :func:`contact_picture`; None without a contact map.
    frame : int
        Video frame of the keypoints picture.
    background : Background
        What the keypoints are drawn on.
    """

    keypoints_png: bytes
    contact_png: bytes | None
    frame: int
    background: Background
    reprojection_png: bytes | None = None
    """:func:`reprojection_picture` of frame ``frame``; None without the object's pose."""
    strip_png: bytes | None = None
    """:func:`strip_picture`; None without frames."""
    contact_ply: bytes | None = None
    """:func:`contact_ply`; None without a contact map."""

    def files(self) -> dict[str, bytes]:
        """The pictures by file name (``keypoints.png``, ...), those there are; pictures of a
        result pickled before a field existed have it missing."""
        named = {"keypoints.png": self.keypoints_png, "contact.png": self.contact_png,
                 "reprojection.png": getattr(self, "reprojection_png", None),
                 "strip.png": getattr(self, "strip_png", None),
                 "contact.ply": getattr(self, "contact_ply", None)}
        return {name: data for name, data in named.items() if data is not None}


def _draw_hand(img: np.ndarray, detected: np.ndarray, model_px: np.ndarray | None,
               outlier: np.ndarray | None, offset: np.ndarray, scale: float,
               min_conf: float) -> None:
    """Skeleton, confidence dots and model crosses, in image coordinates ``(p - offset) *
    scale``."""
    import cv2

    r = max(2, int(round(2 + scale)))

    def pt(p: np.ndarray) -> tuple[int, int]:
        q = (np.asarray(p, float) - offset) * scale
        return int(round(q[0])), int(round(q[1]))

    seen = detected[:, 2] > min_conf
    if model_px is not None:
        ok = np.all(np.isfinite(model_px), axis=1)
        for a, b in BONES:
            if ok[a] and ok[b]:
                cv2.line(img, pt(model_px[a]), pt(model_px[b]), MODEL_RGB, 1, cv2.LINE_AA)
        for j in np.nonzero(ok & seen)[0]:  # residual: model joint to its detection
            cv2.line(img, pt(model_px[j]), pt(detected[j, :2]), (255, 255, 255), 1, cv2.LINE_AA)
    for a, b in BONES:
        if seen[a] and seen[b]:
            c = confidence_rgb(min(detected[a, 2], detected[b, 2]))
            cv2.line(img, pt(detected[a, :2]), pt(detected[b, :2]), c, 2, cv2.LINE_AA)
    for j in np.nonzero(seen)[0]:
        cv2.circle(img, pt(detected[j, :2]), r + 1, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(img, pt(detected[j, :2]), r, confidence_rgb(detected[j, 2]), -1, cv2.LINE_AA)
    if outlier is not None:
        for j in np.nonzero(seen & np.asarray(outlier, bool))[0]:
            cv2.circle(img, pt(detected[j, :2]), 2 * r + 3, OUTLIER_RGB, 2, cv2.LINE_AA)
    if model_px is not None:
        for j in np.nonzero(ok)[0]:
            cv2.drawMarker(img, pt(model_px[j]), (0, 0, 0), cv2.MARKER_TILTED_CROSS,
                           2 * r + 4, 3, cv2.LINE_AA)
            cv2.drawMarker(img, pt(model_px[j]), MODEL_RGB, cv2.MARKER_TILTED_CROSS,
                           2 * r + 4, 1, cv2.LINE_AA)


def keypoints_picture(image_rgb: np.ndarray, detected: np.ndarray,
                      model_px: np.ndarray | None = None, outlier: np.ndarray | None = None, *,
                      title: str = "", config: PicturesConfig = PRESETS["default"]
                      ) -> np.ndarray:
    """Detected keypoints and reprojected model joints on a frame, plus a zoom on the hand.

    Parameters
    ----------
    image_rgb : (h, w, 3) uint8
        The frame (colour, or :func:`colorize_depth` of the depth).
    detected : (21, 3) float
        Detected keypoints (x_px, y_px, confidence); confidence 0 = not detected.
    model_px : (21, 2) float, optional
        The model's joints projected into the frame (NaN: not projected).
    outlier : (21,) bool, optional
        Detections ``reconstruct_hand`` rejected as outliers (ringed in magenta).
    title : str
        Written on the top left.

    Returns
    -------
    (h, w + h, 3) uint8
        The frame on the left, an ``h`` x ``h`` zoom around the keypoints on the right.
    """
    import cv2

    frame = np.ascontiguousarray(image_rgb, dtype=np.uint8).copy()
    h, w = frame.shape[:2]
    detected = np.asarray(detected, dtype=float)
    pts = [detected[detected[:, 2] > config.min_confidence, :2]]
    if model_px is not None:
        model_px = np.asarray(model_px, dtype=float)
        pts.append(model_px[np.all(np.isfinite(model_px), axis=1)])
    pts = np.concatenate(pts)
    if len(pts):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        side = max(float((hi - lo).max()) * (1 + 2 * config.zoom_margin), 40.0)
        centre = (lo + hi) / 2
    else:
        side, centre = float(min(h, w)), np.array([w / 2, h / 2])
    offset = centre - side / 2
    scale = h / side
    M = np.array([[scale, 0, -offset[0] * scale], [0, scale, -offset[1] * scale]])
    zoom = cv2.warpAffine(frame, M, (h, h), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
    _draw_hand(frame, detected, model_px, outlier, np.zeros(2), 1.0, config.min_confidence)
    _draw_hand(zoom, detected, model_px, outlier, offset, scale, config.min_confidence)
    if len(pts):
        p0 = tuple(int(v) for v in np.rint(offset))
        p1 = tuple(int(v) for v in np.rint(offset + side))
        cv2.rectangle(frame, p0, p1, (255, 255, 255), 1)
    out = np.concatenate([frame, zoom], axis=1)
    label(out, title, (8, 20), 0.55)
    y = h - 30
    if outlier is not None:
        cv2.circle(out, (23, y - 24), 7, OUTLIER_RGB, 2, cv2.LINE_AA)
        label(out, "rejected as outlier by stage 2", (42, y - 20))
    cv2.circle(out, (16, y - 4), 5, confidence_rgb(0.0), -1)
    cv2.circle(out, (30, y - 4), 5, confidence_rgb(1.0), -1)
    label(out, "detected keypoints (red: low, green: high confidence)", (42, y))
    cv2.drawMarker(out, (23, y + 16), MODEL_RGB, cv2.MARKER_TILTED_CROSS, 10, 2)
    label(out, "model joints, white line to their detection", (42, y + 20))
    return out


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_c_x`` (4, 4) of an OpenCV camera at ``eye`` looking at ``target`` with ``up`` up
    (all in frame x)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    y = -(np.asarray(up, float) - np.dot(up, z) * z)
    if np.linalg.norm(y) < 1e-9:  # looking along up: any perpendicular will do
        y = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    y /= np.linalg.norm(y)
    R = np.stack([np.cross(y, z), y, z])
    return make_T(R, -R @ np.asarray(eye, float))


def _view(object_mesh, contact, observed, hand_mesh, T_c_o, K, size) -> np.ndarray:
    """One shaded view (size, size, 3) uint8 of the object (and the hand, when given)."""
    V, F = object_mesh
    meshes = [(V, F)] + ([hand_mesh] if hand_mesh is not None else [])
    dirs = pixel_rays(K, size, size).astype(np.float32)
    hits = cast_rays(meshes, [T_c_o] * len(meshes), dirs)
    img = np.empty((size, size, 3), float)
    img[:] = BACKGROUND_RGB
    obs = observed.astype(float)
    w_obs = hits.interpolate(0, F, obs)
    c = hits.interpolate(0, F, obs * contact) / np.maximum(w_obs, 1e-9)
    on_obj = hits.mesh_index == 0
    seen = on_obj & (w_obs >= 0.5)
    shade = (0.3 + 0.7 * hits.cos_incidence)[..., None]
    img[seen] = contact_rgb(c[seen]) * shade[seen]
    img[on_obj & ~seen] = np.array(UNOBSERVED_RGB, float) * shade[on_obj & ~seen]
    on_hand = hits.mesh_index == 1
    img[on_hand] = np.array(SKIN_RGB, float) * shade[on_hand]
    return np.clip(img, 0, 255).astype(np.uint8)


def contact_picture(object_vertices: np.ndarray, object_faces: np.ndarray,
                    contact: np.ndarray, observed: np.ndarray,
                    hand_mesh_o: tuple[np.ndarray, np.ndarray] | None = None, *,
                    up_o: np.ndarray | None = None, title: str = "",
                    config: PicturesConfig = PRESETS["default"]) -> np.ndarray:
    """The contact map on the object from ``config.views`` viewpoints, and beside the hand.

    Parameters
    ----------
    object_vertices : (n, 3) float
        Object mesh in its own frame.
    object_faces : (m, 3) int
    contact : (n,) float
        Contact in [0, 1] per vertex.
    observed : (n,) bool
        Vertices a thermal view saw; the others are grey.
    hand_mesh_o : ((k, 3) float, (l, 3) int), optional
        The refined hand in the object frame; adds a row of the same views with the hand.
    up_o : (3,) float, optional
        The object's up direction (default its z axis); the first view looks from the
        hand's side.

    Returns
    -------
    (30 + rows * view_px + 34, views * view_px, 3) uint8
        Title bar, one row per scene, legend bar.
    """
    V = np.asarray(object_vertices, float)
    F = np.asarray(object_faces, np.int64)
    contact = np.asarray(contact, float)
    observed = np.asarray(observed, bool)
    up = np.array([0.0, 0.0, 1.0]) if up_o is None else np.asarray(up_o, float)
    up = up / np.linalg.norm(up)
    pts = V if hand_mesh_o is None else np.vstack([V, hand_mesh_o[0]])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = (lo + hi) / 2
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    half = np.radians(config.fov_deg) / 2
    distance = radius / np.sin(half) * 1.05
    size = config.view_px
    f = size / 2 / np.tan(half)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    # azimuth 0 faces the hand (or the object's x axis)
    toward = (np.asarray(hand_mesh_o[0], float).mean(axis=0) - centre
              if hand_mesh_o is not None else np.array([1.0, 0.0, 0.0]))
    a0 = toward - np.dot(toward, up) * up
    if np.linalg.norm(a0) < 1e-9:
        a0 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a0 /= np.linalg.norm(a0)
    b0 = np.cross(up, a0)
    el = np.radians(config.elevation_deg)
    rows: list[list[np.ndarray]] = [[], []] if hand_mesh_o is not None else [[]]
    for k in range(config.views):
        az = 2 * np.pi * k / config.views
        e = el if k % 2 == 0 else -el  # every other view from below: the unseen underside
        d = np.cos(e) * (np.cos(az) * a0 + np.sin(az) * b0) + np.sin(e) * up
        T_c_o = look_at(centre + distance * d, centre, up)
        rows[0].append(_view((V, F), contact, observed, None, T_c_o, K, size))
        if hand_mesh_o is not None:
            rows[1].append(_view((V, F), contact, observed, hand_mesh_o, T_c_o, K, size))
    body = np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)
    width = body.shape[1]
    head = np.full((30, width, 3), 40, np.uint8)
    label(head, title, (8, 20), 0.55, box=False)
    legend = np.full((34, width, 3), 255, np.uint8)
    bar = contact_rgb(np.linspace(0, 1, 120))[None].repeat(12, axis=0).astype(np.uint8)
    legend[4:16, 30:150] = bar
    label(legend, "0", (22, 29), 0.4, (0, 0, 0), box=False)
    label(legend, "1 contact", (144, 29), 0.4, (0, 0, 0), box=False)
    legend[4:16, 230:250] = UNOBSERVED_RGB
    label(legend, "unobserved", (256, 15), 0.4, (0, 0, 0), box=False)
    if hand_mesh_o is not None:
        legend[4:16, 350:370] = SKIN_RGB
        label(legend, "hand", (376, 15), 0.4, (0, 0, 0), box=False)
    return np.concatenate([head, body, legend], axis=0)


REASON_RGB = (255, 200, 60)
"""Colour of the QA reasons written under a picture."""


def with_reasons(image_rgb: np.ndarray, reasons: tuple[str, ...] | list[str],
                 notes: tuple[str, ...] | list[str] = ()) -> np.ndarray:
    """``image_rgb`` with a dark band below it listing the QA ``reasons`` (failures and
    flags, amber) and ``notes`` (grey), one per line, cut to the width; the image itself when
    there are none."""
    import cv2

    lines = [(f"QA: {r}", REASON_RGB) for r in reasons] + [(f"note: {n}", (200, 200, 200))
                                                          for n in notes]
    if not lines:
        return image_rgb
    w = image_rgb.shape[1]
    scale = 0.42
    char_w = cv2.getTextSize("M", cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0] * 0.8
    chars = max(int((w - 16) / char_w), 10)
    band = np.full((10 + 18 * len(lines), w, 3), 30, np.uint8)
    for i, (text, colour) in enumerate(lines):
        text = text if len(text) <= chars else text[:chars - 3] + "..."
        label(band, text, (8, 22 + 18 * i), scale, colour, box=False)
    return np.concatenate([image_rgb, band], axis=0)


def reprojection_picture(image_rgb: np.ndarray, object_vertices: np.ndarray,
                         object_faces: np.ndarray, T_c_o: np.ndarray, K: np.ndarray, *,
                         title: str = "") -> np.ndarray:
    """The object model where ``T_c_o`` puts it in the frame: its silhouette tinted, its
    outline, and its axes (x red, y green, z blue, a third of its size) at its origin.

    A pose that is off shows as an outline beside the object in the image.

    Parameters
    ----------
    image_rgb : (h, w, 3) uint8
        The frame (colour, or colourised depth).
    object_vertices, object_faces : (n, 3) float, (m, 3) int
        Object mesh in its own frame (metres).
    T_c_o : (4, 4) float
        The object in the frame's camera.
    K : (3, 3) float
        The camera's intrinsics.

    Returns
    -------
    (h, w, 3) uint8
    """
    import cv2

    V = np.asarray(object_vertices, float)
    F = np.asarray(object_faces, np.int64)
    out = np.ascontiguousarray(image_rgb, dtype=np.uint8).copy()
    mask = silhouette(out.shape[:2], V, F, T_c_o, K)
    tint = np.array(MODEL_RGB, float)
    out[mask] = (out[mask] * 0.55 + tint * 0.45).astype(np.uint8)
    outline(out, mask, MODEL_RGB, 2)
    size = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) / 3 if len(V) else 0.0
    axes_o = np.array([[0, 0, 0], [size, 0, 0], [0, size, 0], [0, 0, size]], float)
    axes_c = transform_points(np.asarray(T_c_o, float), axes_o)
    if size > 0 and np.all(axes_c[:, 2] > 1e-6):
        px = project(K, axes_c)
        if np.all(np.abs(px) < 1e5):
            o = tuple(int(v) for v in np.rint(px[0]))
            for end, colour in zip(px[1:], ((255, 60, 60), (60, 255, 60), (60, 120, 255)),
                                   strict=True):
                cv2.line(out, o, tuple(int(v) for v in np.rint(end)), colour, 2, cv2.LINE_AA)
    label(out, title, (8, 20), 0.55)
    label(out, "object model at the catalog's T_c_o (outline, axes x red y green z blue)",
          (8, out.shape[0] - 10))
    return out


def strip_picture(frames: list[tuple[int, np.ndarray, np.ndarray | None, np.ndarray | None]],
                  object_mesh: tuple[np.ndarray, np.ndarray] | None, K: np.ndarray, *,
                  steady_from: int, height_px: int = 120,
                  min_confidence: float = 0.05) -> np.ndarray:
    """Small frames side by side across the video: each with its index, its detected
    keypoints and, where ``T_c_o`` is given (steady frames), the object's outline.

    ``frames``: ``(index, image_rgb (h, w, 3) uint8, detected (21, 3) or None, T_c_o (4, 4)
    or None)`` in video order; ``K`` the intrinsics of the full-size frames. Returns
    ``(height_px + 22, sum of widths, 3) uint8``.
    """
    import cv2

    tiles = []
    for index, image, detected, T_c_o in frames:
        h, w = image.shape[:2]
        s = height_px / h
        tile = cv2.resize(np.ascontiguousarray(image, np.uint8), (max(int(round(w * s)), 1),
                                                                   height_px),
                          interpolation=cv2.INTER_AREA)
        if T_c_o is not None and object_mesh is not None:
            Ks = np.diag([s, s, 1.0]) @ np.asarray(K, float)
            outline(tile, silhouette(tile.shape[:2], *object_mesh, T_c_o, Ks), MODEL_RGB)
        if detected is not None:
            for x, y, c in np.asarray(detected, float):
                if c > min_confidence and np.isfinite(x) and np.isfinite(y):
                    cv2.circle(tile, (int(round(x * s)), int(round(y * s))), 2,
                               confidence_rgb(c), -1, cv2.LINE_AA)
        head = np.full((22, tile.shape[1], 3), 40, np.uint8)
        steady = "steady" if index >= steady_from else "before steady"
        label(head, f"frame {index} ({steady})", (4, 15), 0.38, box=False)
        tile = np.concatenate([head, tile], axis=0)
        tile[:, -1] = 255  # a white line between frames
        tiles.append(tile)
    return np.concatenate(tiles, axis=1)


def strip_indices(count: int, n: int) -> list[int]:
    """``n`` video frame indices spread evenly over ``count`` frames (first and last
    included), without repeats."""
    if count <= 0 or n <= 0:
        return []
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, min(n, count))})


def contact_ply(object_vertices: np.ndarray, object_faces: np.ndarray, contact: np.ndarray,
                observed: np.ndarray) -> bytes:
    """The object mesh as binary PLY with the contact map as vertex colours (the colours of
    :func:`contact_picture`; unobserved vertices grey), in the object frame, metres."""
    import trimesh

    colours = contact_rgb(np.asarray(contact, float))
    colours[~np.asarray(observed, bool)] = UNOBSERVED_RGB
    rgba = np.concatenate([np.clip(colours, 0, 255).astype(np.uint8),
                           np.full((len(colours), 1), 255, np.uint8)], axis=1)
    mesh = trimesh.Trimesh(np.asarray(object_vertices, float),
                           np.asarray(object_faces, np.int64), vertex_colors=rgba,
                           process=False)
    return mesh.export(file_type="ply", encoding="binary")


def read_frame(session, frame: int) -> tuple[np.ndarray, Background]:
    """Grasp frame ``frame`` of a :class:`~graspcap.tasks.session.load_session.Session` to draw on:
    the colour frame as RGB ``(h, w, 3) uint8`` when the session has colour video, else the
    depth frame in metres ``(h, w)`` (colourised by :func:`pictures`)."""
    import cv2

    path = session.grasp_path("color", frame)
    if path is not None:
        return cv2.cvtColor(session.read_color(path), cv2.COLOR_BGR2RGB), Background.COLOR
    return session.read_depth_m(session.grasp_path("depth", frame)), Background.DEPTH


def model_keypoints(K: np.ndarray, frame: int, frames: np.ndarray, T_w_c: np.ndarray,
                    inlier: np.ndarray, joints_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The hand's joints as the camera of video frame ``frame`` sees them, and which of its
    observations the reconstruction rejected.

    K : (3, 3) colour intrinsics; frames : (m,) the video frames of the reconstruction's
    cameras ``T_w_c`` (m, 4, 4) and its ``inlier`` flags (m, 21); joints_w : (21, 3) the hand
    in the world. Returns the joints' pixels (21, 2) and the outliers (21,) bool. Raises
    ``ValueError`` when the reconstruction has no camera for ``frame``.
    """
    at = np.flatnonzero(np.asarray(frames) == frame)
    if at.size == 0:
        raise ValueError(f"frame {frame} has no camera in the reconstruction")
    i = int(at[0])
    model_px = project(K, transform_points(inv_T(np.asarray(T_w_c[i])), joints_w))
    return model_px, ~np.asarray(inlier[i], bool)


def _drawable(frame_image: np.ndarray, background: Background,
              detected: np.ndarray | None) -> np.ndarray:
    """An RGB image of a frame: itself, or its depth (metres) colourised."""
    if Background(background) == Background.DEPTH:
        kp = np.zeros((0, 3)) if detected is None else np.asarray(detected)
        return colorize_depth(frame_image, hand_depth_range(frame_image, kp))
    return frame_image


def pictures(frame_image: np.ndarray, background: Background, detected: np.ndarray,
             model_px: np.ndarray | None, frame: int, *, session_id: str,
             outlier: np.ndarray | None = None,
             object_mesh: tuple[np.ndarray, np.ndarray] | None = None,
             contact: np.ndarray | None = None, observed: np.ndarray | None = None,
             hand_mesh_o: tuple[np.ndarray, np.ndarray] | None = None,
             up_o: np.ndarray | None = None, note: str = "",
             K: np.ndarray | None = None, T_c_o: np.ndarray | None = None,
             strip: list[tuple[int, np.ndarray, Background, np.ndarray | None,
                               np.ndarray | None]] = (),
             steady_from: int | None = None, reasons: tuple[str, ...] = (),
             notes: tuple[str, ...] = (),
             config: PicturesConfig = PRESETS["default"]) -> Pictures:
    """Every picture of a session as PNG bytes (and the contact map as PLY).

    ``frame_image`` is the RGB frame, or the depth in metres ``(h, w)`` when ``background``
    is ``depth`` (colourised here). ``note`` is appended to the titles (e.g. the verdict);
    ``reasons`` (QA failures and flags) and ``notes`` are written under the pictures.
    ``K`` and ``T_c_o`` (the object in frame ``frame``'s camera) give the reprojection
    picture; ``strip``: ``(index, image, background, detected, T_c_o or None)`` per frame of
    the strip, ``steady_from`` the first steady frame.
    """
    bg = Background(background)
    image = _drawable(frame_image, bg, detected)
    title = f"{session_id}  frame {frame} ({bg})" + (f"  {note}" if note else "")
    kp = keypoints_picture(image, detected, model_px, outlier, title=title, config=config)
    kp = with_reasons(kp, reasons, notes)
    contact_png = ply = None
    if object_mesh is not None and contact is not None and observed is not None:
        img = contact_picture(*object_mesh, contact, observed, hand_mesh_o, up_o=up_o,
                              title=f"{session_id}  contact map" + (
                                  ", below with the hand" if hand_mesh_o is not None else "")
                              + (f"  {note}" if note else ""), config=config)
        contact_png = encode_png(with_reasons(img, reasons))
        ply = contact_ply(*object_mesh, contact, observed)
    reprojection = None
    if object_mesh is not None and K is not None and T_c_o is not None:
        img = reprojection_picture(image, *object_mesh, T_c_o, K, title=title)
        reprojection = encode_png(with_reasons(img, reasons))
    strip_png = None
    if strip and K is not None:
        tiles = [(i, _drawable(im, b, d), d, T) for i, im, b, d, T in strip]
        strip_png = encode_png(strip_picture(
            tiles, object_mesh, K, steady_from=frame if steady_from is None else steady_from,
            height_px=config.strip_height_px, min_confidence=config.min_confidence))
    return Pictures(encode_png(kp), contact_png, int(frame), bg, reprojection, strip_png, ply)


__all__ = [
    "BONES", "PRESETS", "STAGE_VERSION", "Background", "Pictures", "PicturesConfig",
    "contact_picture", "contact_ply", "keypoints_picture", "look_at", "model_keypoints",
    "pictures", "read_frame", "reprojection_picture", "strip_indices", "strip_picture",
    "with_reasons",
]  # fmt: skip
