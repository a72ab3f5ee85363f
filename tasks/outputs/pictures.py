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

:func:`pictures` is the stage's pure entry point: it returns PNG bytes (``cv2.imencode``);
the build writes them. No display, no Open3D visualizer.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import cv2
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
)

STAGE_VERSION = "pictures/1"
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


def _draw_hand(img: np.ndarray, detected: np.ndarray, model_px: np.ndarray | None,
               outlier: np.ndarray | None, offset: np.ndarray, scale: float,
               min_conf: float) -> None:
    """Skeleton, confidence dots and model crosses, in image coordinates ``(p - offset) *
    scale``."""
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


def read_frame(session, frame: int) -> tuple[np.ndarray, Background]:
    """Grasp frame ``frame`` of a :class:`~graspcap.tasks.session.load_session.Session` to draw on:
    the colour frame as RGB ``(h, w, 3) uint8`` when the session has colour video, else the
    depth frame in metres ``(h, w)`` (colourised by :func:`pictures`)."""
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


def pictures(frame_image: np.ndarray, background: Background, detected: np.ndarray,
             model_px: np.ndarray | None, frame: int, *, session_id: str,
             outlier: np.ndarray | None = None,
             object_mesh: tuple[np.ndarray, np.ndarray] | None = None,
             contact: np.ndarray | None = None, observed: np.ndarray | None = None,
             hand_mesh_o: tuple[np.ndarray, np.ndarray] | None = None,
             up_o: np.ndarray | None = None, note: str = "",
             config: PicturesConfig = PRESETS["default"]) -> Pictures:
    """Both pictures of a session as PNG bytes.

    ``frame_image`` is the RGB frame, or the depth in metres ``(h, w)`` when ``background``
    is ``depth`` (colourised here). ``note`` is appended to the titles (e.g. the verdict).
    """
    bg = Background(background)
    if bg == Background.DEPTH:
        image = colorize_depth(frame_image, hand_depth_range(frame_image, np.asarray(detected)))
    else:
        image = frame_image
    title = f"{session_id}  frame {frame} ({bg})" + (f"  {note}" if note else "")
    kp = keypoints_picture(image, detected, model_px, outlier, title=title, config=config)
    contact_png = None
    if object_mesh is not None and contact is not None and observed is not None:
        img = contact_picture(*object_mesh, contact, observed, hand_mesh_o, up_o=up_o,
                              title=f"{session_id}  contact map" + (
                                  ", below with the hand" if hand_mesh_o is not None else "")
                              + (f"  {note}" if note else ""), config=config)
        contact_png = encode_png(img)
    return Pictures(encode_png(kp), contact_png, int(frame), bg)


__all__ = [
    "BONES", "PRESETS", "STAGE_VERSION", "Background", "Pictures", "PicturesConfig",
    "contact_picture", "keypoints_picture", "look_at", "model_keypoints", "pictures",
    "read_frame",
]  # fmt: skip
