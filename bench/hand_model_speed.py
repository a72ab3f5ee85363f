"""Time the hand model's per-call operations (keypoints, batch, capsules, mesh).

    .venv/bin/python bench/hand_model_speed.py [--repeat 2000] [--batch 41]

Prints a markdown table (median microseconds per call) for docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from graspcap.tasks.core.geometry import from_rotvec
from graspcap.tasks.hand.model import HandModel


def _median_us(fn, repeat: int) -> float:
    fn()  # warm up (builds the mesh template once)
    times = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        times[i] = time.perf_counter() - t0
    return float(np.median(times) * 1e6)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=2000)
    parser.add_argument("--batch", type=int, default=41, help="e.g. 1 + 2 x 20 finite differences")
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    model = HandModel()
    build_ms = (time.perf_counter() - t0) * 1e3
    angles = rng.uniform(model.lower_rad, model.upper_rad)
    batch = rng.uniform(model.lower_rad, model.upper_rad, size=(args.batch, 20))
    T_w_p = from_rotvec(np.array([0.3, -0.2, 0.1]), np.array([0.1, 0.0, 0.5]))
    rows = [
        ("keypoints", lambda: model.keypoints(angles, T_w_p, 1.1)),
        (f"keypoints_batch (b={args.batch})", lambda: model.keypoints_batch(batch, T_w_p, 1.1)),
        ("capsules", lambda: model.capsules(angles, T_w_p, 1.1)),
        ("mesh", lambda: model.mesh(angles, T_w_p, 1.1)),
    ]
    n_vertices = len(model.mesh(angles).vertices)
    print(f"HandModel() first construction (mesh template): {build_ms:.0f} ms; "
          f"mesh {n_vertices} vertices\n")  # fmt: skip
    print("| operation | median per call (us) |")
    print("|---|---|")
    for name, fn in rows:
        print(f"| {name} | {_median_us(fn, args.repeat):.0f} |")


if __name__ == "__main__":
    main()
