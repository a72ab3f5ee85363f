"""estimate_adjustment's current code on stage results pickled by ``bench/qa_calibration.py``.

    .venv/bin/python bench/qa_calibration.py --profile wild=30 --seed 78643 --frames 40 60 \\
        --jobs 2 --out /tmp/qa_wild78643            # pickles every stage's results (tuning seeds)
    .venv/bin/python bench/adjustment_rerun.py /tmp/qa_wild78643 [--only-changeable]

For each pickled session, the object's pose at the first steady frame (``T_adj @
T_w_o_stage1``, what ``propagate_poses`` carries to every frame) against the truth, over the
object's symmetries (``graspcap.synth.symmetry``): as pickled and as the current
``estimate_adjustment`` (default preset) computes it from the same upstream results. Printed:
the sessions whose error moved by more than 0.3 deg or 1 mm or whose refusal changed, and how
many crossed the 2 deg line of a good per-frame object (``docs/qa.md``) each way.
``--only-changeable`` re-runs only sessions the pickled stage left ambiguous, registered in
several views or refused (a first frame that alone fit unambiguously runs the same code).
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

from graspcap.synth.evaluate import (
    _object_symmetries,
    _T_adj_at,
    estimate_from_results,
    load_truth,
)
from graspcap.synth.symmetry import sym_pose_metrics
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

GOOD_DEG = 2.0


def steady_object_error(session_dir: Path, results: dict) -> tuple[float, float]:
    """(rotation deg, translation mm) of the object at the first steady frame, symmetry-aware."""
    truth, est = load_truth(session_dir), estimate_from_results(results)
    steady = est.get("steady_from")
    T_adj = truth["T_adj"] if steady is None else _T_adj_at(truth, int(steady))
    m = sym_pose_metrics("o", est["T_adj"] @ est["T_w_o_stage1"],
                         T_adj @ truth["T_w_o_stage1"], *_object_symmetries(session_dir))
    return m["o_rot_sym_deg"], m["o_trans_sym_mm"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("outs", type=Path, nargs="+", help="qa_calibration --out folders")
    parser.add_argument("--only-changeable", action="store_true")
    args = parser.parse_args()
    config = configs_for()["estimate_adjustment"]
    better = worse = ran = 0
    for cache in sorted(p for out in args.outs for p in (out / "results").glob("*.pkl")):
        results, _ = pickle.loads(cache.read_bytes())
        if "fit_hand" not in results:
            continue  # stopped upstream: estimate_adjustment never ran
        d = next((cache.parent.parent / "sessions").glob(f"*/{cache.stem}"))
        old_adj = results.get("estimate_adjustment")
        if args.only_changeable and old_adj is not None and not (
            old_adj.ambiguous or old_adj.views > 1
        ):
            continue
        old = steady_object_error(d, results) if old_adj is not None else None
        t = time.process_time()
        try:
            results["estimate_adjustment"] = run_stage(STAGES["estimate_adjustment"], d, config,
                                                       results)  # fmt: skip
            new, why = steady_object_error(d, results), ""
        except StageError as e:
            new, why = None, e.reason[:90]
        ran += 1
        cpu = time.process_time() - t
        moved = (old is None) != (new is None) or (
            old is not None and (abs(old[0] - new[0]) > 0.3 or abs(old[1] - new[1]) > 1.0)
        )
        if moved:
            fmt = "refused" if old is None else f"{old[0]:.2f} deg / {old[1]:.2f} mm"
            now = f"refused ({why})" if new is None else f"{new[0]:.2f} deg / {new[1]:.2f} mm"
            print(f"{cache.stem}: {fmt} -> {now} (cpu {cpu:.1f} s)", flush=True)
        if old is not None and new is not None:
            better += old[0] > GOOD_DEG >= new[0]
            worse += new[0] > GOOD_DEG >= old[0]
    print(f"{ran} sessions re-run; over the {GOOD_DEG:g} deg line: {better} now within, "
          f"{worse} now beyond")


if __name__ == "__main__":
    main()
