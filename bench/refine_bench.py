"""refine_grasp (stage 5) against synthetic ground truth: contact, penetration, joints, time.

    graspcap synth /tmp/refine_eval --sessions 12 --seed 6100 --difficulty realistic --frames 60
    nice .venv/bin/python bench/refine_bench.py /tmp/refine_eval

Every stage up to ``refine_grasp`` runs bare (``graspcap.tasks.pipeline``), in DAG order; each
session's metrics come from ``graspcap.synth.evaluate``. A session a stage rejects is listed
with its reason, never dropped silently. Prints one line per session and the median and worst
of each metric next to its target (issue 6).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from graspcap.synth.evaluate import estimate_from_results, evaluate
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

# metric -> (target, direction of "better"): from the target table
TARGETS = {
    "contact_near_hand_fit": (None, ">="),
    "contact_near_hand_refined": (0.85, ">="),
    "penetration_max_mm_fit": (None, "<="),
    "penetration_max_mm_refined": (2.0, "<="),
    "fit_joints_mm": (None, "<="),
    "refined_joints_mm": (None, "<="),
    "refined_minus_fit_joints_mm": (1.0, "<="),
    "refine_time_s": (5.0, "<="),
    "refine_accepted": (None, ">="),
}


def run_to_refine(session_dir: Path) -> tuple[dict, dict[str, float]]:
    """Stage results up to and including refine_grasp, and each stage's wall time."""
    configs = configs_for()
    results: dict = {}
    timings: dict[str, float] = {}
    for name, stage in STAGES.items():
        t0 = time.perf_counter()
        results[name] = run_stage(stage, session_dir, configs[name], results)
        timings[name] = time.perf_counter() - t0
        if name == "refine_grasp":
            break
    return results, timings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="folder of synthetic sessions")
    args = parser.parse_args()
    rows: dict[str, dict[str, float]] = {}
    for d in sorted(p for p in args.root.iterdir() if (p / "session.json").exists()):
        try:
            results, timings = run_to_refine(d)
        except StageError as e:
            print(f"{d.name}: FAILED {e}", flush=True)
            continue
        m = evaluate(d, estimate_from_results(results, timings))
        m["refined_minus_fit_joints_mm"] = m["refined_joints_mm"] - m["fit_joints_mm"]
        rows[d.name] = m
        ref = results["refine_grasp"]
        print(f"{d.name}: " + ", ".join(f"{k}={m[k]:.3g}" for k in TARGETS if k in m)
              + f" | {ref.reason or 'accepted'}", flush=True)
    print(f"\n{len(rows)} sessions evaluated")
    print("| metric | median | worst | target |\n|---|---|---|---|")
    for k, (target, better) in TARGETS.items():
        vals = np.array([m[k] for m in rows.values() if k in m])
        if not len(vals):
            continue
        worst = vals.min() if better == ">=" else vals.max()
        t = "" if target is None else f"{better} {target}"
        print(f"| {k} | {np.median(vals):.3g} | {worst:.3g} | {t} |")


if __name__ == "__main__":
    main()
