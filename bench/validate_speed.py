"""Time session validation on a realistic-size session (640x480 RGB-D, 320x256 thermal).

    .venv/bin/python bench/validate_speed.py [--frames 120] [--views 8] [--repeats 3]

Writes one session with numpy/cv2 into a temporary folder, then times
``validate_session`` with and without image decoding. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from graspcap.tasks.session.load_session import validate_session

W, H, TW, TH = 640, 480, 320, 256


def _write_session(d: Path, frames: int, views: int, rng: np.random.Generator) -> None:
    yy, xx = np.mgrid[0:H, 0:W]
    base_mm = (600 + 0.3 * xx + 0.2 * yy).astype(np.uint16)
    base_rgb = np.dstack([xx % 256, yy % 256, (xx + yy) % 256]).astype(np.uint8)
    for sub in ("stage1", "grasp/color", "grasp/depth", "grasp/keypoints", "scan/thermal",
                "scan/depth"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    verts = [(x, y, z) for x in (-0.03, 0.03) for y in (-0.03, 0.03) for z in (0, 0.06)]
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7),
             (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    (d / "object.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
        "property float z\nelement face 12\nproperty list uchar int vertex_indices\nend_header\n"
        + "".join(f"{x} {y} {z}\n" for x, y, z in verts)
        + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces))
    cv2.imwrite(str(d / "stage1/depth.png"), base_mm)
    for i in range(frames):
        noise = rng.integers(0, 8, (H, W), dtype=np.uint16)
        cv2.imwrite(str(d / f"grasp/depth/{i:06d}.png"), base_mm + noise)
        color = base_rgb + noise[..., None].astype(np.uint8)
        cv2.imwrite(str(d / f"grasp/color/{i:06d}.jpg"), color)
        kp = np.column_stack([rng.uniform(0, W, 21), rng.uniform(0, H, 21), rng.uniform(0, 1, 21)])
        people = [{"hand_right_keypoints_2d": kp.ravel().tolist()}]
        (d / f"grasp/keypoints/{i:06d}_keypoints.json").write_text(
            json.dumps({"version": 1.3, "people": people}))
    for j in range(views):
        thermal = (30_000 + rng.integers(0, 300, (TH, TW))).astype(np.uint16)
        cv2.imwrite(str(d / f"scan/thermal/{j:03d}.png"), thermal)
        cv2.imwrite(str(d / f"scan/depth/{j:03d}.png"), base_mm)
    T = [[1, 0, 0, 0.05], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    manifest = {
        "format": "grasp-capture-session/1", "session_id": "bench", "participant": "p0",
        "object_id": "box", "intent": "use", "hand": "right", "object_mesh": "object.ply",
        "color_camera": {"K": [[615.0, 0, 320.0], [0, 615.0, 240.0], [0, 0, 1]],
                         "dist": [0, 0, 0, 0, 0], "width": W, "height": H},
        "depth_scale_m": 0.001,
        "thermal_camera": {"K": [[400.0, 0, 160.0], [0, 400.0, 128.0], [0, 0, 1]],
                           "dist": [0, 0, 0, 0, 0], "width": TW, "height": TH,
                           "T_color_thermal": T},
        "turntable": {"T_color_turntable": T},
        "stage1": {"depth": "stage1/depth.png"},
        "grasp": {"fps": 30.0, "count": frames, "color": "grasp/color/{index:06d}.jpg",
                  "depth": "grasp/depth/{index:06d}.png",
                  "keypoints": "grasp/keypoints/{index:06d}_keypoints.json", "steady_from": None},
        "scan": {"views": [{"thermal": f"scan/thermal/{j:03d}.png",
                            "depth": f"scan/depth/{j:03d}.png", "angle_deg": 360.0 * j / views}
                           for j in range(views)]},
    }
    (d / "session.json").write_text(json.dumps(manifest))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "session"
        _write_session(d, args.frames, args.views, np.random.default_rng(0))
        print(f"| frames | views | check_images | best of {args.repeats} (s) |")
        print("|---|---|---|---|")
        for check in (True, False):
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                problems = validate_session(d, check_images=check)
                times.append(time.perf_counter() - t0)
                assert problems == [], problems
            print(f"| {args.frames} | {args.views} | {check} | {min(times):.2f} |")


if __name__ == "__main__":
    main()
