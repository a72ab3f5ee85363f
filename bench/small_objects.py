"""estimate_adjustment on the small objects of generated sessions (issue 19, item 4): a ball,
a bulb or a small box held in the fist.

    .venv/bin/python bench/small_objects.py --root /tmp/small --frames 40 \\
        --set wild:44199:30 --set wild:50832:30 [--set PROFILE:SEED:N ...] [--compare]

Each set's sessions ``[SEED, i]``, i < N (or FIRST <= i <= LAST), are generated under
``ROOT/PROFILE-FRAMES`` (skipped where already there); those whose object is a ball, a bulb or a
small box run the stages up to ``fit_hand`` once (their results pickled beside the session,
``upstream.pkl``), then ``estimate_adjustment`` (default preset; ``--compare`` also with
``consensus_views=0``, i.e. estimate_adjustment/24). Printed per session: the path that found
the object or the refusal, the fitness, frames, and the object's pose the stage delivers at the
first steady frame against the truth (``adjustment_rerun.steady_object_error``: over the
object's symmetries; where the detected onset precedes the true one the truth is the onset's
pose, so a settling object reads off there: the full pipeline's per-frame errors are
``bench/accuracy.py``'s).
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path

from adjustment_rerun import steady_object_error  # bench/, beside this script
from onset_uncertainty import session_dir

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

SMALL = ("ball", "bulb", "small_box")


def upstream(d: Path) -> dict:
    """The stages before estimate_adjustment, run once (pickled beside the session)."""
    cache = d / "upstream.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    configs, up = configs_for(), {}
    for name, stage in STAGES.items():
        if name == "estimate_adjustment":
            break
        up[name] = run_stage(stage, d, configs[name], up)
    cache.write_bytes(pickle.dumps(up))
    return up


def line(d: Path, up: dict, config) -> str:
    t0 = time.perf_counter()
    try:
        adj = run_stage(STAGES["estimate_adjustment"], d, config, up)
    except StageError as e:
        return f"refused ({time.perf_counter() - t0:.0f} s): {e.reason}"
    rot_deg, trans_mm = steady_object_error(d, {**up, "estimate_adjustment": adj})
    return (f"{adj.path} fitness {adj.fitness:.2f} frames {adj.views} "
            f"{rot_deg:.1f} deg {trans_mm:.1f} mm "
            f"({time.perf_counter() - t0:.0f} s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--set", action="append", required=True,
                    metavar="PROFILE:SEED:N or PROFILE:SEED:FIRST-LAST")
    ap.add_argument("--compare", action="store_true", help="also with consensus_views=0")
    args = ap.parse_args()
    default = configs_for()["estimate_adjustment"]
    before = default.model_copy(update={"consensus_views": 0})
    for spec in args.set:
        profile, seed, count = spec.split(":")
        lo, hi = (int(x) for x in count.split("-")) if "-" in count else (0, int(count) - 1)
        for i in range(lo, hi + 1):
            d = session_dir(args.root, profile, args.frames, int(seed), i)
            if d is None or not any(f"-{kind}-" in d.name for kind in SMALL):
                continue
            try:
                up = upstream(d)
            except StageError as e:
                print(f"| {d.name} | upstream refused: {e.stage}: {e.reason[:80]} |", flush=True)
                continue
            cells = [line(d, up, before)] if args.compare else []
            print(f"| {d.name} | {' | '.join([*cells, line(d, up, default)])} |", flush=True)


if __name__ == "__main__":
    main()
