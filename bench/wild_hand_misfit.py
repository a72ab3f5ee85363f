"""How far the pipeline's 20-DoF hand model is from the wild rig's hands.

    .venv/bin/python bench/wild_hand_misfit.py [--hands 12]

Random wild hands (sizes 0.8-1.2) in a power-grasp pose with +-0.15 rad of noise; the
20-DoF model is fitted to each one's 21 joints with every parameter free (palm pose, scale,
20 angles; best of three starts) and the RMS joint residual printed in millimetres: with the
template's proportions (one global scale), and with the per-subject shape too (20 per-bone
length factors under ``hand.shape``'s prior, weighed as ``fit_hand`` weighs it:
``shape_noise_mm`` 2 mm), so the prior's pull is part of what is measured (fit_hand's
likelihood-ratio test, which keeps the template where the shape explains little, is not
applied: this is the model's capacity).
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


def misfit_mm(seed: int, hm: HandModel, shape: bool = False) -> float:
    """RMS joint residual (mm) of the best 20-DoF fit to wild hand ``seed`` (with ``shape``:
    and 20 per-bone length factors under their prior)."""
    rng = np.random.default_rng(seed)
    wild = WildHand(WildHandShape.sample(WildHandConfig(), rng))
    scale = rng.uniform(0.8, 1.2)
    angles = hm.clip(GRASP + rng.normal(0, 0.15, 20))
    target = wild.keypoints(angles, np.eye(4), scale)

    noise_m = 1e-3 * PRESETS["default"].shape_noise_mm

    def resid(x: np.ndarray) -> np.ndarray:
        T = from_rotvec(x[:3], x[3:6])
        b = np.exp(x[27:]) if shape else None
        joints = (hm.keypoints(hm.clip(x[7:27]), T, x[6], b) - target).ravel()
        return np.concatenate([joints, noise_m * prior_residuals_log(x[27:])]) if shape else joints

    extra = np.zeros(20 if shape else 0)
    starts = [np.concatenate([np.zeros(6), [scale], angles + d, extra]) for d in (0.0, 0.1, -0.1)]
    best = min((least_squares(resid, x0, x_scale="jac", max_nfev=600) for x0 in starts),
               key=lambda r: r.cost)
    return float(np.sqrt((best.fun[:63].reshape(21, 3) ** 2).sum(1).mean()) * 1000)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hands", type=int, default=12)
    args = parser.parse_args()
    hm = HandModel("right")
    for shape in (False, True):
        res = np.array([misfit_mm(s, hm, shape) for s in range(args.hands)])
        print("per-bone shape" if shape else "template proportions",
              "RMS joint residual, mm:", np.round(res, 2), "median",
              round(float(np.median(res)), 2))


if __name__ == "__main__":
    main()
