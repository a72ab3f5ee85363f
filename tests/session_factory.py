"""An independent minimal writer of grasp-capture-session/1 directories, for tests.

Written from ``session-format.md`` with json, numpy and cv2 only (not the project's
synthetic rig, not its models), so tests check the contract rather than one writer.
Images are tiny: colour and depth 80x60, thermal 40x32; 4 frames, 2 scan views and a
box mesh written as ASCII PLY.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

COLOR_W, COLOR_H = 80, 60
THERMAL_W, THERMAL_H = 40, 32
DELETE = object()
"""An override value that removes the key from the manifest."""


def _rigid(angle_rad: float, t: tuple[float, float, float]) -> list[list[float]]:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    T = np.array([[1, 0, 0, t[0]], [0, c, -s, t[1]], [0, s, c, t[2]], [0, 0, 0, 1]])
    return T.tolist()


def base_manifest(frames: int = 4, views: int = 2) -> dict[str, Any]:
    """A valid manifest for the files :func:`write_session` writes."""
    return {
        "format": "grasp-capture-session/1",
        "session_id": "p01-box-use-01",
        "participant": "p01",
        "object_id": "box",
        "intent": "use",
        "hand": "right",
        "object_mesh": "object.ply",
        "color_camera": {"K": [[70.0, 0, 40.0], [0, 70.0, 30.0], [0, 0, 1]],
                         "dist": [0, 0, 0, 0, 0], "width": COLOR_W, "height": COLOR_H},
        "depth_scale_m": 0.001,
        "thermal_camera": {"K": [[35.0, 0, 20.0], [0, 35.0, 16.0], [0, 0, 1]],
                           "dist": [0.01, -0.002, 0, 0], "width": THERMAL_W,
                           "height": THERMAL_H, "T_color_thermal": _rigid(0.05, (0.05, 0, 0))},
        "turntable": {"T_color_turntable": _rigid(-2.0, (0.0, 0.1, 0.6))},
        "stage1": {"depth": "stage1/depth.png", "color": "stage1/color.png"},
        "grasp": {"fps": 30.0, "count": frames,
                  "color": "grasp/color/{index:06d}.jpg",
                  "depth": "grasp/depth/{index:06d}.png",
                  "keypoints": "grasp/keypoints/{index:06d}_keypoints.json",
                  "steady_from": None},
        "scan": {"views": [{"thermal": f"scan/thermal/{j:03d}.png",
                            "depth": f"scan/depth/{j:03d}.png",
                            "angle_deg": 360.0 * j / views} for j in range(views)]},
    }


def merge(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``overrides`` merged in depth; a :data:`DELETE` value removes a key."""
    out = dict(base)
    for key, value in overrides.items():
        if value is DELETE:
            out.pop(key, None)
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def box_ply(half_m: float = 0.03) -> str:
    """An ASCII PLY of an axis-aligned box (8 vertices, 12 triangles)."""
    v = [(x, y, z) for x in (-half_m, half_m) for y in (-half_m, half_m) for z in (0, 2 * half_m)]
    f = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
         (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(v)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(f)}\n"
            "property list uchar int vertex_indices\nend_header\n")
    return head + "".join(f"{a} {b} {c}\n" for a, b, c in v) + "".join(
        f"3 {a} {b} {c}\n" for a, b, c in f)


def _depth_mm(rng: np.random.Generator) -> np.ndarray:
    return rng.integers(400, 900, size=(COLOR_H, COLOR_W), dtype=np.uint16)


def _keypoints(rng: np.random.Generator) -> dict[str, Any]:
    xyc = np.column_stack([rng.uniform(0, COLOR_W, 21), rng.uniform(0, COLOR_H, 21),
                           rng.uniform(0.2, 1.0, 21)])
    return {"version": 1.3, "people": [{"person_id": [-1], "pose_keypoints_2d": [],
                                        "hand_left_keypoints_2d": [],
                                        "hand_right_keypoints_2d": xyc.ravel().tolist()}]}


def _write(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cv2 could not write {path}")


def write_session(directory: Path, *, frames: int = 4, views: int = 2, seed: int = 0,
                  **overrides: Any) -> Path:
    """Write a valid session into ``directory`` and return it.

    ``frames`` and ``views`` size the files written; ``overrides`` are merged into the
    manifest afterwards (see :func:`merge`), so they can make it disagree with the files.
    """
    rng = np.random.default_rng(seed)
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    (d / "object.ply").write_text(box_ply())
    _write(d / "stage1/depth.png", _depth_mm(rng))
    _write(d / "stage1/color.png", rng.integers(0, 256, (COLOR_H, COLOR_W, 3), dtype=np.uint8))
    for i in range(frames):
        _write(d / f"grasp/color/{i:06d}.jpg",
               rng.integers(0, 256, (COLOR_H, COLOR_W, 3), dtype=np.uint8))
        _write(d / f"grasp/depth/{i:06d}.png", _depth_mm(rng))
        kp = d / f"grasp/keypoints/{i:06d}_keypoints.json"
        kp.parent.mkdir(parents=True, exist_ok=True)
        kp.write_text(json.dumps(_keypoints(rng)))
    for j in range(views):
        thermal_ck = rng.integers(29_500, 31_000, (THERMAL_H, THERMAL_W), dtype=np.uint16)
        _write(d / f"scan/thermal/{j:03d}.png", thermal_ck)
        _write(d / f"scan/depth/{j:03d}.png", _depth_mm(rng))
    manifest = merge(base_manifest(frames, views), overrides)
    (d / "session.json").write_text(json.dumps(manifest, indent=2))
    return d
