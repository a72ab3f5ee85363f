"""MediaPipe Hands speed on 640x480 frames: video (tracking) vs images mode, 1 vs 2 workers.

    .venv/bin/python bench/detect_speed.py [--frames 120] [--photo PATH]

Frames: a real hand photo (default ../shared/data/mediapipe_hands/images/thumbs_up.jpg
beside the repository) pasted into 640x480 frames, moving 2 px per frame, written as JPEGs
to a temporary folder. For each setting, ``detect_frames`` runs on all of them:

- ``median ms/frame`` is the median time of one ``process`` call inside one tracker (no
  start-up), i.e. the per-frame cost, and ``CPU ms/frame`` the CPU time of all MediaPipe's
  threads per frame (less sensitive to other load on the machine);
- ``session wall ms/frame`` is ``detect_frames`` called in a fresh process (JPEG decode,
  MediaPipe start-up, worker processes) divided by the frame count, with 1 and 2 workers.

Prints a markdown table. Numbers depend on the machine's load: run on an idle machine.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from graspcap.tasks.detect_mediapipe import (
    Detector,
    FrameMode,
    MediaPipeConfig,
    detect_frames,
    read_rgb,
)

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO.parent / "shared/data/mediapipe_hands/images/thumbs_up.jpg"


def write_frames(photo: Path, folder: Path, n: int) -> list[Path]:
    src = cv2.imread(str(photo))
    h, w = src.shape[:2]
    paths = []
    for i in range(n):
        canvas = np.full((480, 640, 3), 90, np.uint8)
        x, y = (i * 2) % (640 - w), (i // 2) % (480 - h) if h < 480 else 0
        part = src[: 480 - y, : 640 - x]
        canvas[y : y + part.shape[0], x : x + part.shape[1]] = part
        paths.append(folder / f"{i:06d}.jpg")
        cv2.imwrite(str(paths[-1]), canvas, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return paths


def per_frame_ms(paths: list[Path], config: MediaPipeConfig) -> tuple[float, float, int]:
    """Median wall ms of one frame, CPU ms per frame (all of MediaPipe's threads), hands."""
    video = config.mode is FrameMode.VIDEO
    detector = Detector(config, video=video, max_hands=1 if video else 2)
    times, cpu, found = [], 0.0, 0
    for p in paths:
        rgb, _ = read_rgb(p, (640, 480))
        t0, c0 = time.perf_counter(), time.process_time()
        found += bool(detector(rgb))
        times.append(time.perf_counter() - t0)
        cpu += time.process_time() - c0
    detector.close()
    return 1000 * float(np.median(times[2:])), 1000 * cpu / len(paths), found


def session_wall_ms(paths: list[Path], config: MediaPipeConfig) -> tuple[float, int, int]:
    """Wall ms per frame of ``detect_frames`` called in a fresh process (start-up included,
    as for a session), with the workers it used and the frames with a hand."""
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx) as pool:
        pool.submit(os.getpid).result()  # the calling process is up; not timed
        t0 = time.perf_counter()
        result = pool.submit(detect_frames, paths, (640, 480), "right", config).result()
        wall = 1000 * (time.perf_counter() - t0) / len(paths)
    return wall, result.workers, int((result.keypoints[:, :, 2] > 0).any(axis=1).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--photo", type=Path, default=PHOTO)
    args = parser.parse_args()
    print(f"{args.frames} frames 640x480, {os.cpu_count()} CPU(s), "
          f"load average {os.getloadavg()[0]:.1f}\n")
    print("| mode | model | median ms/frame (1 tracker) | CPU ms/frame | frames with hand |"
          " session wall ms/frame, 1 worker | 2 workers |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_frames(args.photo, Path(tmp), args.frames)
        for mode in (FrameMode.VIDEO, FrameMode.IMAGES):
            for complexity in (1, 0):
                config = MediaPipeConfig(mode=mode, model_complexity=complexity)
                median, cpu, found = per_frame_ms(paths, config)
                walls = ["-", "-"]
                if mode is FrameMode.VIDEO:
                    for k, workers in enumerate((1, 2)):
                        parallel = config.model_copy(
                            update={"workers": workers, "min_frames_per_worker": 1})
                        wall, used, _ = session_wall_ms(paths, parallel)
                        walls[k] = f"{wall:.1f}" + ("" if used == workers else f" ({used})")
                print(f"| {mode} | {complexity} | {median:.1f} | {cpu:.1f} | "
                      f"{found}/{len(paths)} | {walls[0]} | {walls[1]} |", flush=True)


if __name__ == "__main__":
    main()
