"""Re-run the object stages and what follows them on cached session results, and score them.

    .venv/bin/python bench/stage_tail.py /tmp/tradeoff/real-detector [more roots ...]

Each ``synth-*`` folder under a root must hold a ``results.pkl`` (``run_session``'s results, as
``bench/tracking_tradeoff.py`` caches them). ``estimate_adjustment``, ``refine_grasp``,
``propagate_poses`` and ``qa_metrics`` run again with the current code and default configs on
the cached upstream results (stage 2, the contact map, the scan registration); every other
stage's result is the cached one. Prints, per session, the errors against the truth
(``graspcap.synth.evaluate``), the CPU seconds of the re-run, ``estimate_adjustment``'s mean
over the tracked frames (frames used, dropped, spread) and the QA verdict: a quick before /
after of a change to the object stages on the same upstream results.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

from graspcap.synth.evaluate import estimate_from_results, evaluate, misses
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.object_pose import track_object
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

TAIL = ("estimate_adjustment", "refine_grasp", "propagate_poses", "qa_metrics")
COLUMNS = ("camera_rot_deg", "camera_trans_mm", "joints_mpjpe_mm", "refined_joints_mm",
           "frame_joints_mm", "frame_object_rot_deg", "frame_object_trans_mm", "T_adj_rot_deg",
           "T_adj_trans_mm", "contact_near_hand_refined")  # fmt: skip

# results cached before track_object moved to object_pose (session 12) still unpickle
sys.modules.setdefault("graspcap.tasks.outputs.track_object", track_object)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("roots", type=Path, nargs="+")
    args = p.parse_args()
    print("| session | " + " | ".join(COLUMNS) + " | CPU s | mean over tracked frames | QA "
          "| not good because |")
    print("|---" * (len(COLUMNS) + 5) + "|")
    configs = configs_for()
    for root in args.roots:
        for d in sorted(root.glob("synth-*")):
            cache = d / "results.pkl"
            results = pickle.loads(cache.read_bytes()) if cache.exists() else None
            if results is None:
                continue
            t0 = time.process_time()
            try:
                for name in TAIL:
                    results[name] = run_stage(STAGES[name], d, configs[name], results)
            except StageError as e:
                print(f"| {d.name} | failed: {e.stage}: {e.reason[:80]} |")
                continue
            m = evaluate(d, estimate_from_results(results))
            avg = results["estimate_adjustment"].average
            mean = ("-" if avg is None else avg.reason if avg.T_w_o is None else
                    f"{avg.frames} used, {avg.dropped} dropped, {avg.spread_deg:.2f} deg / "
                    f"{1e3 * avg.spread_m:.1f} mm")
            print(f"| {d.name} | " + " | ".join(f"{m.get(k, np.nan):.2f}" for k in COLUMNS)
                  + f" | {time.process_time() - t0:.0f} | {mean} "
                  f"| {results['qa_metrics'].verdict} | {', '.join(q for q, _ in misses(m))} |",
                  flush=True)


if __name__ == "__main__":
    main()
