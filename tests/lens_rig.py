"""A synthetic session seen through a real lens: every colour-camera input of a pinhole session
(colour and depth images, keypoint JSONs) resampled as a lens with OpenCV distortion ``dist``
would have recorded it, and ``color_camera.dist`` written into ``session.json``.

The rig renders pinhole images; this puts the lens back, so a test can compare the build
with the distortion honoured, ignored (``dist`` zeroed in the manifest of the distorted
session) and absent (the original session).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from graspcap.tasks.core.camera import Camera

WEBCAM_DIST = (-0.32, 0.14, 0.0008, -0.0012, -0.03)
"""A wide-angle webcam's barrel distortion (k1 k2 p1 p2 k3) at 640x480, f = 615 px: about
30 px at the image corners, 4-8 px where the hand is."""

THERMAL_DIST = (-0.38, 0.2, 0.0005, 0.001, -0.06)
"""A small thermal core's wide lens (k1 k2 p1 p2 k3) at 320x256, f = 360 px."""


def lens_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """For every raw (distorted) pixel, where its ray lands in the ideal pinhole image
    (two (h, w) float32 maps for ``cv2.remap`` of an ideal image into the raw one)."""
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    ideal = camera.undistort_px(np.stack([u.ravel(), v.ravel()], axis=1))
    ideal = ideal.reshape(camera.height, camera.width, 2).astype(np.float32)
    return np.ascontiguousarray(ideal[..., 0]), np.ascontiguousarray(ideal[..., 1])


def _remap_png(path: Path, maps, nearest: bool) -> None:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    out = cv2.remap(image, *maps, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    assert cv2.imwrite(str(path), out)


def _distort_keypoints(path: Path, camera: Camera) -> None:
    doc = json.loads(path.read_text())
    for person in doc["people"]:
        for key in ("hand_right_keypoints_2d", "hand_left_keypoints_2d"):
            if not person.get(key):
                continue
            kp = np.asarray(person[key], dtype=float).reshape(-1, 3)
            seen = kp[:, 2] > 0
            kp[seen, :2] = camera.distort_px(kp[seen, :2])
            person[key] = [float(x) for x in kp.ravel()]
    path.write_text(json.dumps(doc))


def distort_session(src: Path, dst: Path, dist=WEBCAM_DIST, *, colour: bool = True,
                    thermal_dist=None) -> Path:
    """A copy of session ``src`` at ``dst`` as a colour camera with OpenCV ``dist`` recorded
    it: depth PNGs (stage 1, grasp, scan) resampled nearest, colour images bilinear (only with
    ``colour``: the keypoint JSONs stand for the detector), keypoints through
    :meth:`Camera.distort_px`, ``color_camera.dist`` set; with ``thermal_dist``, the thermal
    PNGs (nearest) and ``thermal_camera.dist`` likewise. Returns ``dst``."""
    shutil.copytree(src, dst)
    manifest_path = dst / "session.json"
    manifest = json.loads(manifest_path.read_text())
    if thermal_dist is not None:
        th = manifest["thermal_camera"]
        th_maps = lens_maps(Camera(np.asarray(th["K"], float), np.asarray(thermal_dist, float),
                                   th["width"], th["height"]))
        for view in manifest["scan"]["views"]:
            _remap_png(dst / view["thermal"], th_maps, nearest=True)
        th["dist"] = [float(x) for x in thermal_dist]
    if not np.any(np.asarray(dist) != 0):
        manifest_path.write_text(json.dumps(manifest, indent=1))
        return dst
    cam = manifest["color_camera"]
    camera = Camera(np.asarray(cam["K"], float), np.asarray(dist, float), cam["width"],
                    cam["height"])
    maps = lens_maps(camera)
    grasp, count = manifest["grasp"], manifest["grasp"]["count"]
    depth = [manifest["stage1"]["depth"], *(v["depth"] for v in manifest["scan"]["views"]),
             *(grasp["depth"].format(index=i) for i in range(count))]
    for rel in depth:
        _remap_png(dst / rel, maps, nearest=True)
    if colour:
        stage1_colour = manifest["stage1"].get("color")
        colour_files = [grasp["color"].format(index=i) for i in range(count)] if grasp.get(
            "color") else []
        for rel in [*colour_files, *([stage1_colour] if stage1_colour else [])]:
            _remap_png(dst / rel, maps, nearest=False)
    if grasp.get("keypoints"):
        for i in range(count):
            _distort_keypoints(dst / grasp["keypoints"].format(index=i), camera)
    cam["dist"] = [float(x) for x in dist]
    manifest_path.write_text(json.dumps(manifest, indent=1))
    return dst


def without_dist(src: Path, dst: Path, camera: str = "color_camera") -> Path:
    """A copy of session ``src`` whose manifest says ``camera``'s lens is pinhole (the
    distortion ignored). Returns ``dst``."""
    shutil.copytree(src, dst)
    manifest_path = dst / "session.json"
    manifest = json.loads(manifest_path.read_text())
    manifest[camera]["dist"] = [0.0] * len(manifest[camera]["dist"])
    manifest_path.write_text(json.dumps(manifest, indent=1))
    return dst
