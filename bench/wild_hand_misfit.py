"""How far the pipeline's 20-DoF hand model is from the wild rig's hands.

    .venv/bin/python bench/wild_hand_misfit.py [--hands 12] [--shape-noise-mm 2] [--palm-sd-mm 0]

Random wild hands (sizes 0.8-1.2) in a power-grasp pose with +-0.15 rad of noise; the
20-DoF model is fitted to each one's 21 joints with every parameter free (palm pose, scale,
20 angles; best of three starts) and the RMS joint residual printed in millimetres: with the
template's proportions (one global scale), and with the per-subject shape too (20 per-bone
length factors under ``hand.shape``'s prior, weighed as ``fit_hand`` weighs it:
``shape_noise_mm`` 2 mm), so the prior's pull is part of what is measured (fit_hand's
likelihood-ratio test, which keeps the template where the shape explains little, is not
applied: this is the model's capacity). ``--shape-noise-mm`` sets that weight (0.1: the
prior almost off); ``--palm-sd-mm`` > 0 adds a 3-D offset of each finger's base in the palm
frame under a Gaussian prior of that SD (the palm's shape beyond the bones' lengths: tried in
the joint solve in session 22 and not kept, ``docs/benchmarks.md``).
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import least_squares

from graspcap.synth.config import WildHandConfig
from graspcap.synth.wild_hand import WildHand, WildHandShape
from graspcap.tasks.core.geometry import from_rotvec
from graspcap.tasks.hand.fit_hand import PRESETS
from graspcap.tasks.hand.model import HandModel
from graspcap.tasks.hand.shape import prior_residuals_log

GRASP = np.array([0.5, 0.2, 0.3, 0.3] + [0.0, 0.9, 1.0, 0.7] * 4)


def misfit_mm(seed: int, hm: HandModel, shape: bool = False, noise_mm: float | None = None,
              palm_sd_mm: float = 0.0) -> float:
    """RMS joint residual (mm) of the best 20-DoF fit to wild hand ``seed`` (with ``shape``:
    and 20 per-bone length factors under their prior, weighed as ``noise_mm`` of joint
    residual, and with ``palm_sd_mm`` > 0 each finger's base offset under its prior)."""
    rng = np.random.default_rng(seed)
    wild = WildHand(WildHandShape.sample(WildHandConfig(), rng))
    scale = rng.uniform(0.8, 1.2)
    angles = hm.clip(GRASP + rng.normal(0, 0.15, 20))
    target = wild.keypoints(angles, np.eye(4), scale)

    noise_m = 1e-3 * (PRESETS["default"].shape_noise_mm if noise_mm is None else noise_mm)
    n_bone, palm = (20 if shape else 0), palm_sd_mm > 0

    def resid(x: np.ndarray) -> np.ndarray:
        T = from_rotvec(x[:3], x[3:6])
        b = np.exp(x[27:27 + n_bone]) if shape else None
        kp = hm.keypoints(hm.clip(x[7:27]), np.eye(4), x[6], b)
        if palm:  # each finger's chain moved by its base offset (palm frame, scaled)
            offsets = np.repeat(x[27 + n_bone:].reshape(5, 3), 4, axis=0)
            kp = kp + x[6] * np.vstack([np.zeros(3), offsets])
        out = [(kp @ T[:3, :3].T + T[:3, 3] - target).ravel()]
        if shape:
            out.append(noise_m * prior_residuals_log(x[27:27 + n_bone]))
        if palm:
            out.append(noise_m * x[27 + n_bone:] / (1e-3 * palm_sd_mm))
        return np.concatenate(out)

    extra = np.zeros(n_bone + (15 if palm else 0))
    starts = [np.concatenate([np.zeros(6), [scale], angles + d, extra]) for d in (0.0, 0.1, -0.1)]
    best = min((least_squares(resid, x0, x_scale="jac", max_nfev=600) for x0 in starts),
               key=lambda r: r.cost)
    return float(np.sqrt((best.fun[:63].reshape(21, 3) ** 2).sum(1).mean()) * 1000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hands", type=int, default=12)
    parser.add_argument("--shape-noise-mm", type=float, default=None,
                        help="the shape prior's weight (default: fit_hand's shape_noise_mm)")
    parser.add_argument("--palm-sd-mm", type=float, default=0.0,
                        help="prior SD of each finger's base offset (0: no offsets)")
    args = parser.parse_args()
    hm = HandModel("right")
    for shape in (False, True):
        res = np.array([misfit_mm(s, hm, shape, args.shape_noise_mm, args.palm_sd_mm)
                        for s in range(args.hands)])
        print("per-bone shape" if shape else "template proportions",
              "RMS joint residual, mm:", np.round(res, 2), "median",
              round(float(np.median(res)), 2))


if __name__ == "__main__":
    main()
