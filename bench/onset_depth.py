"""The first steady frame from the keypoints (``select_steady`` steps 1-4) against the one from
the depth's residual non-rigidity (step 5, ``hand_sfm.steady_depth``), on sessions already
generated.

    OMP_NUM_THREADS=1 .venv/bin/python bench/onset_depth.py \
        /tmp/s2bench/sessions/real-detector/synth-s9700-00[0-7]-* --show 0

Per session: the true onset (``ground_truth/truth.json`` ``steady_from``), the keypoint onset's
error and the depth onset's error (frames, estimate - truth); then per run the median absolute
errors and the share within 3 frames. ``--show k`` prints the per-frame signal of the k-th
session.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

UPSTREAM = ("load_session", "detect_keypoints", "select_steady")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sessions", type=Path, nargs="+")
    parser.add_argument("--gap", type=int, default=4)
    parser.add_argument("--far-mm", type=float, default=4.0)
    parser.add_argument("--drift", type=float, default=2.0)
    parser.add_argument("--before", type=int, default=3)
    parser.add_argument("--after", type=int, default=20)
    parser.add_argument("--show", type=int, nargs="*", default=[])
    args = parser.parse_args()
    configs = configs_for()
    configs["select_steady"] = configs["select_steady"].model_copy(update={
        "depth_gap": args.gap, "depth_far_m": args.far_mm / 1000,
        "depth_drift_sigmas": args.drift, "depth_before": args.before,
        "depth_after": args.after})
    kp_err, d_err = [], []
    for k, d in enumerate(args.sessions):
        res: dict = {}
        for name in UPSTREAM:
            res[name] = run_stage(STAGES[name], d, configs[name], res)
        sel = res["select_steady"]
        truth = int(json.loads((d / "ground_truth" / "truth.json").read_text())["steady_from"])
        kp_err.append(sel.keypoint_from - truth)
        d_err.append(sel.steady_from - truth)
        print(f"{d.name}: truth {truth} keypoint {kp_err[-1]:+d} depth {d_err[-1]:+d} "
              f"(depth onset {'used' if sel.depth_from >= 0 else 'not used'})"
              f"{' uncertain' if sel.uncertain else ''}", flush=True)
        if k in args.show:
            for i, v in enumerate(sel.depth_share):
                print(f"  {i:3d} {v:.3f}{' <truth' if i == truth else ''}")
    for name, e in (("keypoint", kp_err), ("depth", d_err)):
        e = np.abs(e)
        print(f"{name}: median |error| {np.median(e):.1f}, within 3: {np.sum(e <= 3)}/{len(e)}; "
              f"errors {[int(x) for x in (kp_err if name == 'keypoint' else d_err)]}")


if __name__ == "__main__":
    main()
