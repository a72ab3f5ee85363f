"""The joint solve's depth refinement (``joint_solve.depth_refine``) on and off, side by side.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/hand_depth.py \
        --root /tmp/s13/tune --set real-detector:82100:8 --set wild:9700:8 --frames 60

``--set PROFILE:SEED:N`` takes sessions ``[SEED, 0..N-1]`` of that profile, found under
``root/PROFILE`` or generated there (``graspcap.synth.generate_session``). Each runs the
stages up to ``select_steady`` once, then ``joint_solve`` (default config, ``mode = auto``)
with ``depth_refine.enabled`` false and true; both scored by ``graspcap.synth.evaluate``:
cameras (median deg / mm), SfM joints (the hand in the first steady camera) and the hand in
each frame (``frame_joints_mm``: the median over frames of the mean joint error of the solved
hand carried by each frame's camera, what ``frames.joints_c`` delivers), and the CPU seconds
of each solve. Sessions where ``mode = auto`` keeps the staged result (clean detections) do
not refine, and show equal rows. Prints one row per session and the medians.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import evaluate
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

UPSTREAM = ("load_session", "detect_keypoints", "select_steady")
KEYS = ("camera_rot_deg", "camera_trans_mm", "joints_mpjpe_mm", "frame_joints_mm")


def session_dir(root: Path, profile: str, frames: int, seed: int, i: int) -> Path:
    """The session ``[seed, i]`` of ``profile`` under ``root/profile``, generated when missing."""
    found = sorted((root / profile).glob(f"synth-s{seed}-{i:03d}-*"))
    found = [d for d in found if (d / "ground_truth").exists()]
    return found[0] if found else generate_session(root / profile, [seed, i],
                                                   config_for(profile, frames))


def score(d: Path, solve) -> dict:
    """``KEYS`` of one joint solve's hand and cameras against the truth."""
    rec, joints = solve.reconstruction, solve.fit.joints_fit_w
    est = {"steady_from": rec.steady_from, "joints_w": joints, "T_w_c": rec.T_w_c,
           "camera_solved": rec.pose_valid, "frame": rec.frames,
           "joints_c": np.stack([transform_points(inv_T(T), joints) for T in rec.T_w_c])}
    e = evaluate(d, est)
    return {k: float(e[k]) for k in KEYS}


def run(d: Path) -> dict:
    """Both variants on one session: {"off": scores, "on": scores, "cpu_off", "cpu_on",
    "refined": the report's note} or {"failed": why}."""
    configs = configs_for()
    up: dict = {}
    for name in UPSTREAM:
        up[name] = run_stage(STAGES[name], d, configs[name], up)
    base = configs["joint_solve"]
    row: dict = {}
    for label, enabled in (("off", False), ("on", True)):
        cfg = base.model_copy(update={"depth_refine": base.depth_refine.model_copy(
            update={"enabled": enabled})})
        t0 = time.process_time()
        try:
            solve = run_stage(STAGES["joint_solve"], d, cfg, up)
        except StageError as e:
            return {"failed": e.reason[:100]}
        row[f"cpu_{label}"] = time.process_time() - t0
        row[label] = score(d, solve)
        if enabled:
            r = solve.depth_refine
            row["refined"] = ("not run" if r is None else
                              "kept" if r.kept else f"not kept: {r.note}")
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--set", action="append", required=True, help="PROFILE:SEED:N")
    parser.add_argument("--frames", type=int, default=60)
    args = parser.parse_args()
    rows = []
    for spec in args.set:
        profile, seed, n = spec.split(":")
        for i in range(int(n)):
            d = session_dir(args.root, profile, args.frames, int(seed), i)
            row = run(d)
            rows.append(row)
            if "failed" in row:
                print(f"{profile} [{seed}, {i}] failed: {row['failed']}", flush=True)
                continue
            off, on = row["off"], row["on"]
            print(f"{profile:13s} [{seed}, {i}] {d.name[:30]:30s} cameras "
                  f"{on['camera_rot_deg']:.2f} deg / {on['camera_trans_mm']:.0f} mm  SfM joints "
                  f"{off['joints_mpjpe_mm']:5.1f} -> {on['joints_mpjpe_mm']:5.1f}  hand in each "
                  f"frame {off['frame_joints_mm']:5.1f} -> {on['frame_joints_mm']:5.1f} mm  CPU "
                  f"{row['cpu_off']:.1f} -> {row['cpu_on']:.1f} s  ({row['refined']})", flush=True)
    done = [r for r in rows if "failed" not in r]
    if done:
        med = {label: {k: float(np.median([r[label][k] for r in done])) for k in KEYS}
               for label in ("off", "on")}
        print(f"median of {len(done)} (off -> on): " + ", ".join(
            f"{k} {med['off'][k]:.2f} -> {med['on'][k]:.2f}" for k in KEYS)
            + f", CPU {np.median([r['cpu_off'] for r in done]):.1f} -> "
              f"{np.median([r['cpu_on'] for r in done]):.1f} s")


if __name__ == "__main__":
    main()
