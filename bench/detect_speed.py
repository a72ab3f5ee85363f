"""MediaPipe Hands per 640x480 frame, end to end (read + decode + inference + our arrays).

    OMP_NUM_THREADS=1 .venv/bin/python bench/detect_speed.py [--frames 120] [--repeats 3]
        [--parts] [--sessions] [--photo PATH]

Frames: a real hand photo (default ../shared/data/mediapipe_hands/images/thumbs_up.jpg
beside the repository) pasted into 640x480 frames, moving 2 px per frame, written as JPEGs
to a temporary folder. Each setting (model, inference threads, prefetch) runs the stage's
own frame loop, ``iter_detections`` (video mode: one tracker), over all frames; settings
take turns within each repeat, so machine load hits them alike.

- ``median ms/frame``: median over repeats of the median time between two consecutive
  frame results (a result needs the frame read and decoded, MediaPipe run, the landmarks
  turned into our arrays; frame 0, which includes the graph's start-up, is left out);
- ``mean``: the loop's wall time over frames 1..n-1 per frame; ``CPU``: the process CPU
  time (all threads: reader, graph, XNNPACK) per frame over the same frames;
- ``start-up``: graph creation + frame 0.

``--parts`` profiles one tracker per part with decoding inline (read + JPEG check, decode to
RGB, MediaPipe ``process``, conversion to our arrays): wall and CPU per part.
``--sessions`` adds ``detect_frames`` in a fresh process (imports and start-up included)
with 1 and 2 worker processes. Numbers depend on the machine's load.
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

from graspcap.tasks.keypoints.mediapipe_detector import (
    Detector,
    MediaPipeConfig,
    detect_frames,
    iter_detections,
)
from graspcap.tasks.session.files import _jpeg_problem

REPO = Path(__file__).resolve().parents[1]
PHOTO = REPO.parent / "shared/data/mediapipe_hands/images/thumbs_up.jpg"
SETTINGS = [(model, threads, prefetch) for model in (1, 0)
            for threads, prefetch in ((1, 0), (1, 2), (2, 0), (2, 2))]
"""(model_complexity, threads, prefetch); prefetch 0: decoded on the calling thread (which still
overlaps the graph, which runs a frame ahead)."""
PARTS = ("read + JPEG check", "decode to RGB", "MediaPipe process", "to our arrays")


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


def stage_loop(paths: list[Path], config: MediaPipeConfig) -> dict[str, float]:
    """One run of the stage's frame loop: per-frame times, CPU, start-up, frames with a hand."""
    t0 = time.perf_counter()
    stamps, found, cpu0 = [], 0, 0.0
    for r in iter_detections(paths, (640, 480), "right", config):
        stamps.append(time.perf_counter())
        found += bool((r.keypoints[:, 2] > 0).any())
        if r.index == 0:
            cpu0 = time.process_time()
    cpu = time.process_time() - cpu0
    steps = np.diff(stamps)
    return {"median": 1000 * float(np.median(steps)), "mean": 1000 * float(steps.mean()),
            "cpu": 1000 * cpu / len(steps), "startup": stamps[0] - t0, "found": found}


def parts(paths: list[Path], complexity: int) -> None:
    """Wall (median) and CPU (mean) ms per part, decoding inline, one tracker."""
    detector = Detector(MediaPipeConfig(model_complexity=complexity), video=True, max_hands=1)
    rows: dict[str, list[tuple[int, int]]] = {}
    for p in paths:
        marks = [(time.perf_counter_ns(), time.thread_time_ns(), time.process_time_ns())]
        data = p.read_bytes()
        _jpeg_problem(data)
        marks.append((time.perf_counter_ns(), time.thread_time_ns(), time.process_time_ns()))
        rgb = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR_RGB)
        rgb.flags.writeable = False
        marks.append((time.perf_counter_ns(), time.thread_time_ns(), time.process_time_ns()))
        result = detector.process(rgb)
        marks.append((time.perf_counter_ns(), time.thread_time_ns(), time.process_time_ns()))
        detector.candidates(result, rgb.shape[:2])
        marks.append((time.perf_counter_ns(), time.thread_time_ns(), time.process_time_ns()))
        for name, (a, b) in zip(PARTS, zip(marks[:-1], marks[1:], strict=True), strict=True):
            # process: CPU of every thread (the graph's); the other parts: this thread's
            cpu = b[2] - a[2] if name == "MediaPipe process" else b[1] - a[1]
            rows.setdefault(name, []).append((b[0] - a[0], cpu))
    detector.close()
    print(f"\nparts, model {complexity}, decode inline ({len(paths)} frames; "
          "wall median / CPU mean, ms):")
    for name, values in rows.items():
        v = np.array(values[2:]) / 1e6
        print(f"  {name:<18} {np.median(v[:, 0]):7.3f} / {v[:, 1].mean():7.3f}")


def session_wall_ms(paths: list[Path], config: MediaPipeConfig) -> tuple[float, int]:
    """Wall ms per frame of ``detect_frames`` in a fresh process (start-up included)."""
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx) as pool:
        pool.submit(os.getpid).result()  # the calling process is up; not timed
        t0 = time.perf_counter()
        result = pool.submit(detect_frames, paths, (640, 480), "right", config).result()
        return 1000 * (time.perf_counter() - t0) / len(paths), result.workers


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--parts", action="store_true", help="per-part profile as well")
    parser.add_argument("--sessions", action="store_true",
                        help="detect_frames in a fresh process, 1 and 2 workers, as well")
    parser.add_argument("--photo", type=Path, default=PHOTO)
    args = parser.parse_args()
    print(f"{args.frames} frames 640x480, {args.repeats} repeats, {os.cpu_count()} CPU(s), "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}, "
          f"load average {os.getloadavg()[0]:.1f} at the start\n")
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_frames(args.photo, Path(tmp), args.frames)
        runs: dict[tuple[int, int, int], list[dict[str, float]]] = {s: [] for s in SETTINGS}
        for _ in range(args.repeats):
            for model, threads, prefetch in SETTINGS:
                config = MediaPipeConfig(model_complexity=model, threads=threads,
                                         prefetch=prefetch)
                runs[model, threads, prefetch].append(stage_loop(paths, config))
        print("| model | inference threads | prefetch | median ms/frame | per repeat |"
              " mean ms/frame | CPU ms/frame | start-up s | frames with hand |")
        print("|---|---|---|---|---|---|---|---|---|")
        for (model, threads, prefetch), rs in runs.items():
            med = [r["median"] for r in rs]
            print(f"| {'full' if model else 'lite'} ({model}) | {threads} | {prefetch} | "
                  f"{np.median(med):.1f} | {' / '.join(f'{m:.1f}' for m in med)} | "
                  f"{np.median([r['mean'] for r in rs]):.1f} | "
                  f"{np.median([r['cpu'] for r in rs]):.1f} | "
                  f"{np.median([r['startup'] for r in rs]):.2f} | "
                  f"{rs[0]['found']}/{len(paths)} |")
        if args.parts:
            for model in (1, 0):
                parts(paths, model)
        if args.sessions:
            print("\nsession wall ms/frame in a fresh process (full model, threads 1):")
            for workers in (1, 2):
                config = MediaPipeConfig(workers=workers, min_frames_per_worker=1)
                wall, used = session_wall_ms(paths, config)
                print(f"  {workers} worker(s): {wall:.1f} ({used} ran)")
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
