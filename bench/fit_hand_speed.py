"""Time and score fit_hand on random model hands (both sides), per preset and noise level.

    .venv/bin/python bench/fit_hand_speed.py [--hands 40] [--seed 0]

Prints a markdown table: median / max milliseconds per fit, RMS distance of the fitted joints
to the noise-free truth (mean and worst hand, mm), worst per-joint distance (mm), worst scale
error (%), and the median of each hand's worst angle error (deg).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from graspcap.tasks.core.geometry import from_rotvec
from graspcap.tasks.hand.fit_hand import PRESETS, fit_hand
from graspcap.tasks.hand.model import HandModel, HandSide


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hands", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    models = {side: HandModel(side) for side in HandSide}
    fit_hand(models[HandSide.RIGHT].keypoints(np.zeros(20)), HandSide.RIGHT)  # warm up
    print("| preset | noise (mm, per coord) | ms median | ms max | joint RMS mean / max (mm) "
          "| worst joint (mm) | worst scale err (%) | median worst angle err (deg) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for preset in PRESETS:
        for noise_m in (0.0, 0.002):
            rng = np.random.default_rng(args.seed)
            ms, rms, worst, scale_err, angle_err = [], [], [], [], []
            for i in range(args.hands):
                side = (HandSide.RIGHT, HandSide.LEFT)[i % 2]
                model = models[side]
                angles = rng.uniform(model.lower_rad, model.upper_rad)
                T_w_p = from_rotvec(rng.normal(size=3), rng.uniform(-0.3, 0.3, 3) + [0, 0, 0.6])
                scale = rng.uniform(0.9, 1.1)
                truth = model.keypoints(angles, T_w_p, scale)
                joints = truth + rng.normal(scale=noise_m, size=truth.shape)
                t0 = time.perf_counter()
                fit = fit_hand(joints, side, PRESETS[preset])
                ms.append(1e3 * (time.perf_counter() - t0))
                d = 1e3 * np.linalg.norm(fit.joints_fit_w - truth, axis=1)
                rms.append(np.sqrt(np.mean(d**2)))
                worst.append(d.max())
                scale_err.append(100 * abs(fit.scale / scale - 1))
                angle_err.append(np.degrees(np.abs(fit.angles_rad - angles)).max())
            print(f"| {preset} | {1e3 * noise_m:.0f} | {np.median(ms):.1f} | {np.max(ms):.1f} "
                  f"| {np.mean(rms):.3f} / {np.max(rms):.3f} | {np.max(worst):.3f} "
                  f"| {np.max(scale_err):.2f} | {np.median(angle_err):.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
