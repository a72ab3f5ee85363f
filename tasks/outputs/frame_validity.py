"""Per-frame validity: was a steady frame's hand detection used, its camera solved, and does its
depth support the object pose there? (The catalog's ``frames`` columns ``hand_used``,
``camera_solved``, ``object_supported`` and their reasons, format 6; ``docs/catalog.md``.)

Each answer is True, False, or None where the frame cannot say (with the reason):

- hand: the frame's detection was used when at least ``min_hand_inliers`` of its keypoints are
  inliers of ``reconstruct_hand``'s final solve (the static hand explains them); False with
  "no detection" or "3 of 17 detected keypoints inliers (need 6)"; None for a frame outside
  ``reconstruct_hand``'s window (not part of the static-hand problem; the ``frames`` table
  starts at the first steady frame, so today no row is);
- camera: ``reconstruct_hand`` posed the frame from its own keypoints (``pose_valid``), else
  interpolated it from its neighbours (reason: what the frame had);
- object: the object mesh and the final hand (static in the object frame during the steady
  phase) are ray cast at the frame's pose ``T_c_o``; over the object pixels the hand does not
  cover (the rendered hand and the detected keypoints' bones, grown by a margin), a pixel
  agrees when its measured depth is within ``depth_tol_m`` of the rendered one. Supported
  when at least ``min_agreement`` of them agree; False (reason: the median difference)
  below; None when fewer than ``min_pixels`` object pixels with depth are visible (the hand
  covers it, it is out of view, the depth has holes there): such a frame neither supports
  nor contradicts the pose.

Pure numpy and Open3D (one ray-casting scene per session, rays moved into the object frame);
no Prefect.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.hand.image_masks import grow_mask, hand_mask_from_keypoints
from graspcap.tasks.object_pose.registration.depth_agreement import image_box

# open3d: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d

OUTSIDE_WINDOW = "outside the steady window"


class FrameValidityConfig(StageConfig):
    """Tolerances of the per-frame checks (``propagate_poses.validity``)."""

    detect_confidence: float = 0.2
    """A keypoint counts as detected at or above this confidence (``reconstruct_hand``'s
    ``min_confidence``)."""
    min_hand_inliers: int = 6
    """A frame's hand detection counts as used with at least this many keypoints that are
    inliers of ``reconstruct_hand``'s final solve (its ``min_points_per_frame``)."""
    depth_tol_m: float = 0.01
    """An object pixel agrees when its measured depth is within this of the rendered model's
    (sensor noise and the model's fit, well under the 2 cm of a wrong pose)."""
    min_agreement: float = 0.5
    """Share of the judged object pixels that must agree for the frame to support the pose."""
    min_pixels: int = 50
    """Fewest judged object pixels (visible outside the hand, with depth) for a verdict; with
    fewer the frame cannot say (None). Counted on the ``stride_px`` grid."""
    stride_px: int = 2
    """Every ``stride_px``-th pixel of every ``stride_px``-th row of the object's pixel box is
    judged (a quarter of the rays at 2)."""
    hand_margin_px: int = 4
    """The hand's pixels (rendered hand, keypoint bones) are grown by this much before the
    object pixels under them are left out: its silhouette's flying pixels, a finger the fit
    misses by a few pixels."""
    bone_radius_px: float = 6.0
    """Half-thickness of the detected keypoints' bones drawn into the hand's pixels."""


DEFAULT = FrameValidityConfig()


@dataclass(frozen=True)
class ObjectSupport:
    """Whether one frame's depth supports the object pose.

    supported : True, False, or None when the frame cannot say; reason : why not (None when
    supported); agreement : share of the judged pixels that agree (NaN without a verdict);
    pixels : object pixels outside the hand with a depth reading, on the ``stride_px`` grid
    (the judged ones; fewer than ``min_pixels`` without a verdict); median_diff_m : their
    median |measured - rendered| depth (NaN without a verdict).
    """

    supported: bool | None
    reason: str | None
    agreement: float
    pixels: int
    median_diff_m: float


@dataclass(frozen=True)
class FrameValidity:
    """Per frame (``frames``, the rows of ``PosePropagation``): the catalog's validity columns.

    Every field is a tuple of one value per frame; a reason is None where the answer is True.
    ``object_depth_agreement`` is None where no pixel was judged.
    """

    frames: tuple[int, ...]
    hand_used: tuple[bool | None, ...]
    hand_reason: tuple[str | None, ...]
    camera_solved: tuple[bool, ...]
    camera_reason: tuple[str | None, ...]
    object_supported: tuple[bool | None, ...]
    object_reason: tuple[str | None, ...]
    object_depth_agreement: tuple[float | None, ...]


class SupportScene:
    """The object mesh and (optionally) the hand, both in the object frame, each in a
    ray-casting scene built once; :meth:`cast` renders them from any camera pose."""

    def __init__(self, object_mesh: tuple[np.ndarray, np.ndarray],
                 hand_mesh_o: tuple[np.ndarray, np.ndarray] | None = None):
        self.vertices_o = np.asarray(object_mesh[0], dtype=float)
        self._object = self._scene(object_mesh)
        self._hand = None if hand_mesh_o is None else self._scene(hand_mesh_o)

    @staticmethod
    def _scene(mesh: tuple[np.ndarray, np.ndarray]) -> o3d.t.geometry.RaycastingScene:
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(np.ascontiguousarray(mesh[0], dtype=np.float32),
                            np.ascontiguousarray(mesh[1], dtype=np.uint32))
        return scene

    def cast(self, K: np.ndarray, T_c_o: np.ndarray, width: int, height: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Of a pinhole camera ``K`` at ``T_c_o``: the object's depth (h, w), 0 where it is
        not hit (as if nothing covered it); where it is hit (h, w) bool; where the hand is the
        nearer surface (h, w) bool (in front of the object, or where it is not)."""
        import open3d as o3d

        u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
        d_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        d_c /= np.linalg.norm(d_c, axis=-1, keepdims=True)
        T_o_c = inv_T(np.asarray(T_c_o, dtype=float))
        d_o = d_c @ T_o_c[:3, :3].T
        rays = o3d.core.Tensor(np.ascontiguousarray(np.concatenate(
            [np.broadcast_to(T_o_c[:3, 3], d_o.shape), d_o], axis=-1), dtype=np.float32))
        t_obj = self._object.cast_rays(rays)["t_hit"].numpy()
        seen = np.isfinite(t_obj)
        hand = np.zeros_like(seen)
        if self._hand is not None:
            t_hand = self._hand.cast_rays(rays)["t_hit"].numpy()
            hand = np.isfinite(t_hand) & ~(t_obj <= t_hand)
        return np.where(seen, t_obj * d_c[..., 2], 0.0), seen, hand


def object_support(
    depth_m: np.ndarray,
    K: np.ndarray,
    scene: SupportScene,
    T_c_o: np.ndarray,
    config: FrameValidityConfig = DEFAULT,
    keypoints: np.ndarray | None = None,
) -> ObjectSupport:
    """Does the frame's depth (h, w) metres, 0 = no reading, show the object at ``T_c_o``?

    ``scene`` holds the object mesh and the hand in the object frame (the hand occludes the
    object where it is in front); ``keypoints`` (21, 3) (pixels, confidence), when given, add
    the detected hand's bones to the pixels left out. Module docstring for the verdicts.
    """
    depth_m = np.asarray(depth_m)
    h, w = depth_m.shape
    K = np.asarray(K, dtype=float)
    T_c_o = np.asarray(T_c_o, dtype=float)
    need = config.min_pixels
    u0, v0, u1, v1 = image_box(K, transform_points(T_c_o, scene.vertices_o), w, h)
    if u1 <= u0 or v1 <= v0:
        return ObjectSupport(None, "object out of view", float("nan"), 0, float("nan"))
    s = max(int(config.stride_px), 1)
    K_box = K.copy()
    K_box[:2, 2] -= (u0, v0)
    K_box[:2] /= s  # pixel (u0 + s i, v0 + s j) of the image is pixel (i, j) of the grid
    K_box[2] = (0.0, 0.0, 1.0)
    measured = depth_m[v0:v1:s, u0:u1:s]
    rendered, model, hand = scene.cast(K_box, T_c_o, measured.shape[1], measured.shape[0])
    n_model = int(model.sum())
    if n_model < need:
        return ObjectSupport(None, f"object barely in view: {n_model} pixels (need {need})",
                             float("nan"), 0, float("nan"))
    if keypoints is not None:
        kp = np.asarray(keypoints, dtype=float)
        bones = hand_mask_from_keypoints(kp[:, :2], kp[:, 2], (h, w), config.bone_radius_px,
                                         config.detect_confidence)
        hand |= bones[v0:v1:s, u0:u1:s]
    hand = grow_mask(hand, int(np.ceil(config.hand_margin_px / s)))
    visible = model & ~hand
    n_visible = int(visible.sum())
    judged = visible & (measured > 0)
    n = int(judged.sum())
    if n_visible < need:
        return ObjectSupport(None, f"too few object pixels visible: {n_visible} of {n_model} "
                             f"outside the hand (need {need}; the hand covers it)",
                             float("nan"), n, float("nan"))
    if n < need:
        return ObjectSupport(None, f"too few object pixels with depth: {n} of {n_visible} "
                             f"visible (need {need})", float("nan"), n, float("nan"))
    diff = np.abs(measured[judged] - rendered[judged])
    share = float(np.mean(diff <= config.depth_tol_m))
    median = float(np.median(diff))
    if share >= config.min_agreement:
        return ObjectSupport(True, None, share, n, median)
    return ObjectSupport(False, f"depth disagrees: median {median * 1e3:.0f} mm, {share:.0%} of "
                         f"{n} pixels within {config.depth_tol_m * 1e3:g} mm", share, n, median)


def _detected(keypoints: np.ndarray, config: FrameValidityConfig) -> np.ndarray:
    kp = np.asarray(keypoints, dtype=float)
    return (kp[..., 2] >= config.detect_confidence) & np.all(np.isfinite(kp[..., :2]), axis=-1)


def hand_used(keypoints: np.ndarray, inlier: np.ndarray | None,
              config: FrameValidityConfig = DEFAULT
              ) -> tuple[bool | None, str | None]:
    """Whether one frame's hand detection was used: ``keypoints`` (21, 3) (pixels,
    confidence), ``inlier`` (21,) bool, its keypoints that are inliers of the final solve
    (None: the frame is outside ``reconstruct_hand``'s window). (used, reason)."""
    if inlier is None:
        return None, OUTSIDE_WINDOW
    n_det = int(_detected(keypoints, config).sum())
    if n_det == 0:
        return False, "no detection"
    n_inl = int(np.asarray(inlier, bool).sum())
    if n_inl < config.min_hand_inliers:
        return False, (f"{n_inl} of {n_det} detected keypoints inliers "
                       f"(need {config.min_hand_inliers})")
    return True, None


def camera_solved(keypoints: np.ndarray, pose_valid: bool | None,
                  config: FrameValidityConfig = DEFAULT) -> tuple[bool, str | None]:
    """Whether ``reconstruct_hand`` solved the frame's camera (``pose_valid``; None: the frame
    is outside its window, so it has no camera), with the reason where not."""
    if pose_valid is None:
        return False, f"no camera: {OUTSIDE_WINDOW}"
    if pose_valid:
        return True, None
    n_det = int(_detected(keypoints, config).sum())
    what = "no detection" if n_det == 0 else f"{n_det} keypoints detected"
    return False, f"interpolated from its neighbours: {what}"


def frame_validity(
    frames: np.ndarray,
    keypoints: np.ndarray,
    sfm_frames: np.ndarray,
    pose_valid: np.ndarray,
    inlier: np.ndarray,
    T_c_o: np.ndarray,
    read_depth: Callable[[int], np.ndarray],
    K: np.ndarray,
    object_mesh: tuple[np.ndarray, np.ndarray],
    hand_mesh_o: tuple[np.ndarray, np.ndarray] | None,
    config: FrameValidityConfig = DEFAULT,
    rejected: tuple[str, ...] = (),
) -> FrameValidity:
    """The validity of every frame.

    Parameters
    ----------
    frames : (m,) int, video frame indices (``PosePropagation.frame_indices``).
    keypoints : (m, 21, 3) float, their detections (pixels, confidence).
    sfm_frames, pose_valid, inlier : ``reconstruct_hand``'s frames (k,), ``pose_valid`` (k,)
        and ``inlier`` (k, 21).
    T_c_o : (m, 4, 4) the object in each frame's camera.
    read_depth : video frame index -> its depth (h, w) metres.
    object_mesh, hand_mesh_o : (vertices, faces), both in the object frame (the final hand).
    rejected : per ``reconstruct_hand`` frame, why it was rejected whole ("" where accepted;
        ``SfmDiagnostics.frame_rejected``): such a frame's hand is not used, with that reason.
    """
    scene = SupportScene(object_mesh, hand_mesh_o)
    row = {int(f): i for i, f in enumerate(np.asarray(sfm_frames))}
    out: dict[str, list] = {k: [] for k in ("hu", "hr", "cs", "cr", "os", "or", "oa")}
    for j, f in enumerate(np.asarray(frames, dtype=int)):
        i = row.get(int(f))
        used, why = hand_used(keypoints[j], None if i is None else inlier[i], config)
        if i is not None and i < len(rejected) and rejected[i]:
            used, why = False, f"rejected whole: {rejected[i]}"
        solved, cwhy = camera_solved(keypoints[j], None if i is None else bool(pose_valid[i]),
                                     config)
        if i is None:
            sup = ObjectSupport(None, f"no camera: {OUTSIDE_WINDOW}", float("nan"), 0,
                                float("nan"))
        else:
            sup = object_support(read_depth(int(f)), K, scene, T_c_o[j], config, keypoints[j])
        for k, value in zip(out, (used, why, solved, cwhy, sup.supported, sup.reason,
                                  None if np.isnan(sup.agreement) else sup.agreement),
                            strict=True):
            out[k].append(value)
    return FrameValidity(
        frames=tuple(int(f) for f in frames), hand_used=tuple(out["hu"]),
        hand_reason=tuple(out["hr"]), camera_solved=tuple(out["cs"]),
        camera_reason=tuple(out["cr"]), object_supported=tuple(out["os"]),
        object_reason=tuple(out["or"]), object_depth_agreement=tuple(out["oa"]),
    )


__all__ = [
    "FrameValidity", "FrameValidityConfig", "ObjectSupport", "SupportScene", "camera_solved",
    "frame_validity", "hand_used", "object_support",
]  # fmt: skip
