"""Calibration of qa_metrics: every QA metric beside the truth errors, per session.

    .venv/bin/python bench/qa_calibration.py [--realistic 20] [--hard 6] [--out /tmp/qa_cal]
    .venv/bin/python bench/qa_calibration.py --fresh   # re-run the stages (after code changes)
    .venv/bin/python bench/qa_calibration.py --cached-only   # re-judge the pickled sessions
    .venv/bin/python bench/qa_calibration.py --seed 9000 --hard 0 --realistic 12 --frames 120 \
        --out /tmp/qa_acc120   # the independent check: bench/accuracy.py's sessions

Sessions are generated with seeds ``[9400, i]`` (realistic) and ``[9401, i]`` (hard), disjoint
from the tests' and from ``bench/accuracy.py``'s (9000; ``--seed 9000`` judges those sessions
instead, the independent check of limits set here: never tune on them); their lengths cycle
through ``--frames`` (60, 90, 120). Every stage but ``pictures`` runs bare, in the order of
``tasks.pipeline.STAGES``; the stage results are pickled under ``--out``, and a later run
re-uses them (unless ``--fresh``), re-running only ``qa_metrics`` (the current code and
preset) on them.

A session is labelled ``wrong`` when any of its errors against the truth exceeds twice the
issue's target (the targets are medians over sessions; twice is what one session may miss by
and still be trustworthy): cameras > 1 deg or > 10 mm, MPJPE > 6 mm, fitted joints > 12 mm,
per-frame object pose > 4 deg or > 12 mm (median over frames), contact IoU < 0.7; or when a
stage rejected it (then it cannot be silently wrong). Else ``trustworthy``. The table (one row
per session: label, verdict, reasons, every QA metric, the truth errors) is printed and
written to ``<out>/qa_calibration.csv``.
"""

from __future__ import annotations

import argparse
import csv
import pickle
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import estimate_from_results, evaluate
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.hand.final import final_hand
from graspcap.tasks.outputs.qa_metrics import METRICS, qa_metrics
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

SEEDS = {"realistic": 9400, "hard": 9401}

WRONG_IF: dict[str, tuple[float, str]] = {
    "camera_rot_deg": (1.0, ">"),
    "camera_trans_mm": (10.0, ">"),
    "joints_mpjpe_mm": (6.0, ">"),
    "fit_joints_mm": (12.0, ">"),
    "frame_object_rot_deg": (4.0, ">"),
    "frame_object_trans_mm": (12.0, ">"),
    "contact_iou": (0.7, "<"),
}
"""Truth error -> (limit, side): beyond it the session is wrong (twice the issue's target)."""

TRUTH_COLUMNS = ("steady_from_err_frames", *WRONG_IF)


def label(truth: dict[str, float], stage_error: str | None) -> tuple[str, str]:
    """("trustworthy" | "wrong", why) by :data:`WRONG_IF`."""
    if stage_error:
        return "wrong", f"stage failed: {stage_error}"
    why = [
        f"{k} {truth[k]:.2f}"
        for k, (limit, op) in WRONG_IF.items()
        if k in truth and (truth[k] > limit if op == ">" else truth[k] < limit)
    ]
    return ("wrong", "; ".join(why)) if why else ("trustworthy", "")


def run_stages(session_dir: Path) -> tuple[dict[str, Any], str | None]:
    """Every stage but ``pictures`` (a QA aid); (results, the failing stage's reason or None)."""
    configs = configs_for()
    results: dict[str, Any] = {}
    for name, stage in STAGES.items():
        if name in ("pictures", "qa_metrics"):
            continue
        try:
            results[name] = run_stage(stage, session_dir, configs[name], results)
        except StageError as e:
            return results, f"{e.stage}: {e.reason}"
    return results, None


def judge(session_dir: Path, results: dict[str, Any]):
    """The current ``qa_metrics`` (default preset) on pickled stage results."""
    session = results["load_session"]
    hand = final_hand(results["fit_hand"], results.get("refine_grasp"),
                      results["estimate_adjustment"].T_w_o)
    return qa_metrics(results, object_mesh=session.read_mesh(), hand_mesh_o=hand.mesh_o)


def _cache(out: Path, session_dir: Path) -> Path:
    return out / "results" / f"{session_dir.name}.pkl"


def collect(out: Path, counts: dict[str, int], frames: tuple[int, ...], fresh: bool,
            cached_only: bool = False, seeds: dict[str, int] = SEEDS) -> list[dict[str, Any]]:
    rows = []
    for difficulty, n in counts.items():
        cfg_by_len = {f: config_for(difficulty, f) for f in frames}
        for i in range(n):
            length = frames[i % len(frames)]
            root = out / "sessions" / difficulty
            done = sorted(root.glob(f"synth-s{seeds[difficulty]}-{i:03d}-*"))
            if cached_only and not (done and _cache(out, done[0]).exists()):
                continue
            try:
                d = (done[0] if done and (done[0] / "ground_truth").exists() else
                     generate_session(root, [seeds[difficulty], i], cfg_by_len[length], None))
            except StageError:
                print(f"{difficulty} {i}: the rig could not stage this seed, skipped")
                continue
            cache = _cache(out, d)
            if not fresh and cache.exists():
                results, error = pickle.loads(cache.read_bytes())
            else:
                results, error = run_stages(d)
                cache.parent.mkdir(parents=True, exist_ok=True)
                cache.write_bytes(pickle.dumps((results, error)))
            rows.append(row(d, difficulty, length, results, error))
            print(_line(rows[-1]), flush=True)
    return rows


def row(d: Path, difficulty: str, length: int, results: dict[str, Any], error: str | None
        ) -> dict[str, Any]:
    truth = evaluate(d, estimate_from_results(results))
    tag, why = label(truth, error)
    out: dict[str, Any] = {"session": d.name, "difficulty": difficulty, "frames": length,
                           "label": tag, "wrong_because": why}
    if error:
        out |= {"verdict": "failed", "reasons": f"stage error: {error}"}
    else:
        report = judge(d, results)
        out |= {"verdict": str(report.verdict), "reasons": "; ".join(report.reasons)}
        out |= {f"qa_{k}": v for k, v in report.metrics.items()}
    out |= {f"truth_{k}": truth[k] for k in TRUTH_COLUMNS if k in truth}
    return out


def _line(r: dict[str, Any]) -> str:
    t = {k: r.get(f"truth_{k}", float("nan")) for k in TRUTH_COLUMNS}
    return (f"{r['session'][:34]:34} {r['difficulty'][:4]} {r['frames']:3d} {r['label']:11} "
            f"{r['verdict']:7} cam {t['camera_rot_deg']:.2f}d/{t['camera_trans_mm']:.1f}mm "
            f"mpjpe {t['joints_mpjpe_mm']:.1f} obj {t['frame_object_rot_deg']:.1f}d/"
            f"{t['frame_object_trans_mm']:.1f}mm onset {t['steady_from_err_frames']:.0f} | "
            f"{r['reasons'][:150]}")


def summary(rows: list[dict[str, Any]]) -> None:
    print("\n| label | sessions | ok | flagged | failed |")
    print("|---|---|---|---|---|")
    for tag in ("trustworthy", "wrong"):
        v = Counter(r["verdict"] for r in rows if r["label"] == tag)
        n = sum(v.values())
        print(f"| {tag} | {n} | {v['ok']} | {v['flagged']} | {v['failed']} |")
    print("\n| metric | trustworthy min / median / max | wrong min / median / max |")
    print("|---|---|---|")
    for name in METRICS:
        cells = []
        for tag in ("trustworthy", "wrong"):
            v = [r[f"qa_{name}"] for r in rows if r["label"] == tag and f"qa_{name}" in r]
            cells.append(" / ".join(f"{x:.3g}" for x in (min(v), np.median(v), max(v)))
                         if v else "-")
        print(f"| {name} | {cells[0]} | {cells[1]} |")


def write_csv(rows: list[dict[str, Any]], path: Path) -> None:
    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realistic", type=int, default=20)
    parser.add_argument("--hard", type=int, default=6)
    parser.add_argument("--frames", type=int, nargs="+", default=[60, 90, 120])
    parser.add_argument("--out", type=Path, default=Path("/tmp/qa_calibration"))
    parser.add_argument("--fresh", action="store_true",
                        help="re-run the stages even where pickled results exist")
    parser.add_argument("--cached-only", action="store_true",
                        help="only the sessions with pickled results (re-judge them)")
    parser.add_argument("--seed", type=int, default=None,
                        help="first seed of every difficulty (default: 9400 realistic, 9401 hard)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    seeds = SEEDS if args.seed is None else dict.fromkeys(SEEDS, args.seed)
    rows = collect(args.out, {"hard": args.hard, "realistic": args.realistic},
                   tuple(args.frames), args.fresh, args.cached_only, seeds)
    summary(rows)
    name = "qa_calibration_cached.csv" if args.cached_only else "qa_calibration.csv"
    write_csv(rows, args.out / name)
    print(f"\nwrote {args.out / name}")


if __name__ == "__main__":
    main()
