"""The first steady frame from the keypoints (``select_steady``) against the one from the depth's
residual non-rigidity (``hand_sfm.steady_depth``), on sessions already generated.

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

from graspcap.tasks.hand_sfm import steady_depth
from graspcap.tasks.hand_sfm.steady_stats import cusum, standardise
from graspcap.tasks.pipeline import STAGES, _ideal_keypoints, configs_for, run_stage

UPSTREAM = ("load_session", "detect_keypoints", "select_steady")


def depth_onset(z_signal: np.ndarray, kp_onset: int, before: int, after: int, drift: float,
                ref_from: int) -> tuple[int, np.ndarray]:
    """Change point of the signal standardised by the frames from ``ref_from``, searched in
    ``kp_onset - before .. kp_onset + after``; (onset, z)."""
    n = len(z_signal)
    found = standardise(z_signal, np.arange(min(ref_from, n - 3), n))
    if found is not None:  # a share: at least 1 % of spread (a flat floor is no noise scale)
        found = ((z_signal - found[1]) / max(found[2], 0.01), found[1], max(found[2], 0.01))
    if found is None:
        return kp_onset, np.full(n, np.nan)
    z = found[0]
    sums = cusum(z, drift)
    lo, hi = max(kp_onset - before, 0), min(kp_onset + after, n - 1)
    sums[:lo], sums[hi + 1:] = -np.inf, -np.inf
    return int(np.argmax(sums)), z


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sessions", type=Path, nargs="+")
    parser.add_argument("--gap", type=int, default=4)
    parser.add_argument("--far-mm", type=float, default=3.0)
    parser.add_argument("--drift", type=float, default=2.0)
    parser.add_argument("--before", type=int, default=3)
    parser.add_argument("--after", type=int, default=20)
    parser.add_argument("--show", type=int, nargs="*", default=[])
    args = parser.parse_args()
    configs = configs_for()
    link = configs["reconstruct_hand"].depth_links
    kp_err, d_err = [], []
    for k, d in enumerate(args.sessions):
        res: dict = {}
        for name in UPSTREAM:
            res[name] = run_stage(STAGES[name], d, configs[name], res)
        session, sel = res["load_session"], res["select_steady"]
        kp = _ideal_keypoints(session, res["detect_keypoints"].keypoints)
        uv, ok = kp[..., :2], (kp[..., 2] >= 0.2) & np.all(np.isfinite(kp), axis=2)
        read = session.grasp_depth_reader()
        K = session.color_K
        centres = steady_depth.hand_centres(read, K, uv, ok, below_skin_m=0.01, min_points=6)
        signal = steady_depth.deformation(
            read, K, centres, session.T_color_turntable, gap=args.gap,
            radius_m=link.radius_m, stride_px=link.stride_px, min_height_m=link.min_height_m,
            max_points=600, max_distance_m=link.max_distance_m, huber_m=link.huber_m,
            iterations=link.iterations, far_m=args.far_mm / 1000)
        truth = int(json.loads((d / "ground_truth" / "truth.json").read_text())["steady_from"])
        n = len(signal)
        onset, z = depth_onset(signal, sel.steady_from, args.before, args.after, args.drift,
                               max(sel.steady_from + 12, n - n // 3))
        kp_err.append(sel.steady_from - truth)
        d_err.append(onset - truth)
        print(f"{d.name}: truth {truth} keypoint {kp_err[-1]:+d} depth {d_err[-1]:+d}"
              f"{' uncertain' if sel.uncertain else ''}", flush=True)
        if k in args.show:
            for i in range(n):
                mark = " <truth" if i == truth else ""
                print(f"  {i:3d} {signal[i]:.3f} z {z[i]:7.1f}{mark}")
    for name, e in (("keypoint", kp_err), ("depth", d_err)):
        e = np.abs(e)
        print(f"{name}: median |error| {np.median(e):.1f}, within 3: {np.sum(e <= 3)}/{len(e)}; "
              f"errors {[int(x) for x in (kp_err if name == 'keypoint' else d_err)]}")


if __name__ == "__main__":
    main()
