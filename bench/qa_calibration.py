"""Calibration of qa_metrics: every QA metric beside the truth errors, per session.

    .venv/bin/python bench/qa_calibration.py --profile wild=60 --seed 9700 --out /tmp/qa_wild
    .venv/bin/python bench/qa_calibration.py [--profile realistic=20 hard=6] [--out /tmp/qa_cal]
    .venv/bin/python bench/qa_calibration.py ... --fresh   # re-run the stages (after code changes)
    .venv/bin/python bench/qa_calibration.py ... --cached-only   # re-judge the pickled sessions
    .venv/bin/python bench/qa_calibration.py --profile wild=30 --seed 9750 --out /tmp/qa_wild_r
        # a held-out report set: seeds drawn once, written down before the run, never tuned on

Sessions of profile P are generated with seeds ``[seed_P, i]`` (``--seed``, else 9400
realistic, 9401 hard, 9700 wild: the tuning sets; ``bench/accuracy.py``'s 9000 and every report
set of ``docs/benchmarks.md`` are disjoint from them); their lengths cycle through ``--frames``
(60, 90, 120). Every stage but ``pictures`` runs bare, in the order of
``tasks.pipeline.STAGES``, ``--jobs`` sessions at a time; the stage results are pickled under
``--out``, and a later run re-uses them (unless ``--fresh``), re-running only ``qa_metrics``
(the current code and preset) on them.

A session is *good* when every error against the truth is within its tolerance
(``graspcap.synth.evaluate.GOOD_IF``, ``docs/qa.md``); a session a stage rejected is not good.
The table (one row per session: good or not and why, verdict, reasons, every QA metric, the
truth errors) is printed with the confusion table (good / not good x ok / flagged / failed),
QA's precision (good among ``ok``) and yield (``ok`` among good), and written to
``<out>/qa_calibration.csv``.
"""

from __future__ import annotations

import argparse
import csv
import pickle
import re
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import (
    confusion_markdown,
    estimate_from_results,
    evaluate,
    misses,
    qa_confusion,
)
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.outputs.qa_metrics import METRICS
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

SEEDS = {"realistic": 9400, "hard": 9401, "wild": 9700}
"""The tuning seeds of each profile (module docstring)."""

TRUTH_COLUMNS = ("steady_from_err_frames", "joints_mpjpe_mm", "fit_joints_mm",
                 "refined_joints_mm", "camera_rot_deg", "camera_trans_mm",
                 "frame_object_rot_deg", "frame_object_trans_mm", "object_stage1_rot_deg",
                 "frame_object_rot_sym_deg", "frame_object_trans_sym_mm",
                 "object_stage1_rot_sym_deg", "camera_rot_aligned_deg", "joints_aligned_mm",
                 "contact_near_hand_refined", "contact_iou")  # fmt: skip


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
    """The current ``qa_metrics`` stage (default preset) on pickled stage results, through
    the pipeline's own glue (the final hand, the object mesh, the hand's image size)."""
    return run_stage(STAGES["qa_metrics"], session_dir, configs_for()["qa_metrics"], results)


def _cache(out: Path, session_dir: Path) -> Path:
    return out / "results" / f"{session_dir.name}.pkl"


def _one(out: Path, profile: str, seed: int, i: int, length: int, fresh: bool,
         cached_only: bool) -> dict[str, Any] | None:
    """Session ``[seed, i]`` of ``profile``: generated (or found), its stages run (or their
    pickled results read) and judged; None when the rig cannot stage the seed."""
    root = out / "sessions" / profile
    done = sorted(root.glob(f"synth-s{seed}-{i:03d}-*"))
    if cached_only and not (done and _cache(out, done[0]).exists()):
        return None
    try:
        d = (done[0] if done and (done[0] / "ground_truth").exists() else
             generate_session(root, [seed, i], config_for(profile, length), None))
    except StageError:
        print(f"{profile} {i}: the rig could not stage this seed, skipped", flush=True)
        return None
    cache = _cache(out, d)
    if not fresh and cache.exists():
        results, error = pickle.loads(cache.read_bytes())
    else:
        results, error = run_stages(d)
        cache.parent.mkdir(parents=True, exist_ok=True)
        cache.write_bytes(pickle.dumps((results, error)))
    r = row(d, profile, length, results, error)
    print(_line(r), flush=True)
    return r


def collect(out: Path, counts: dict[str, int], frames: tuple[int, ...], fresh: bool,
            cached_only: bool = False, seeds: dict[str, int] = SEEDS,
            jobs: int = 1) -> list[dict[str, Any]]:
    """Every session of ``counts`` (profile -> sessions), ``jobs`` at a time (processes)."""
    from concurrent.futures import ProcessPoolExecutor

    work = [(out, p, seeds[p], i, frames[i % len(frames)], fresh, cached_only)
            for p, n in counts.items() for i in range(n)]
    if jobs <= 1:
        rows = [_one(*w) for w in work]
    else:
        with ProcessPoolExecutor(jobs) as pool:
            rows = list(pool.map(_one, *zip(*work, strict=True)))
    return [r for r in rows if r is not None]


def row(d: Path, profile: str, length: int, results: dict[str, Any], error: str | None
        ) -> dict[str, Any]:
    truth = evaluate(d, estimate_from_results(results))
    missed = misses(truth, error)
    out: dict[str, Any] = {"session": d.name, "profile": profile, "frames": length,
                           "label": "not good" if missed else "good",
                           "not_good_because": "; ".join(text for _, text in missed),
                           "missed": "; ".join(q for q, _ in missed)}
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
    return (f"{r['session'][:34]:34} {r['profile'][:4]} {r['frames']:3d} {r['label']:8} "
            f"{r['verdict']:7} cam {t['camera_rot_deg']:.2f}d/{t['camera_trans_mm']:.1f}mm "
            f"mpjpe {t['joints_mpjpe_mm']:.1f} obj {t['frame_object_rot_sym_deg']:.1f}d/"
            f"{t['frame_object_trans_sym_mm']:.1f}mm onset {t['steady_from_err_frames']:.0f} | "
            f"{r['reasons'][:150]}")


def summary(rows: list[dict[str, Any]]) -> None:
    for profile in sorted({r["profile"] for r in rows}):
        mine = [r for r in rows if r["profile"] == profile]
        print(f"\n### {profile}: {len(mine)} sessions\n")
        print(confusion_markdown(qa_confusion([(r["label"] == "good", r["verdict"])
                                               for r in mine])))
        missed = Counter(q for r in mine for q in r["missed"].split("; ") if q)
        print("\nnot good because (sessions per quantity; a session may count twice): "
              + ", ".join(f"{k} {n}" for k, n in missed.most_common()))
        stages = Counter(r["reasons"].removeprefix("stage error: ").split(":")[0]
                         for r in mine if r["reasons"].startswith("stage error: "))
        flags = Counter(re.split(r" [-\d.]+", f)[0] for r in mine if r["verdict"] != "ok"
                        and not r["reasons"].startswith("stage error: ")
                        for f in r["reasons"].split("; ") if f)
        print("refused by a stage: " + ", ".join(f"{k} {n}" for k, n in stages.most_common()))
        print("QA reasons of the rest (not ok): "
              + ", ".join(f"{k} {n}" for k, n in flags.most_common(12)))
    print("\n| metric | good min / median / max | not good min / median / max |")
    print("|---|---|---|")
    for name in METRICS:
        cells = []
        for tag in ("good", "not good"):
            v = [r[f"qa_{name}"] for r in rows if r["label"] == tag and f"qa_{name}" in r]
            v = [x for x in v if x is not None and np.isfinite(x)]
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
    parser.add_argument("--profile", nargs="+", default=["realistic=20", "hard=6"],
                        help="PROFILE=SESSIONS ... (a synth profile and how many sessions)")
    parser.add_argument("--frames", type=int, nargs="+", default=[60, 90, 120])
    parser.add_argument("--out", type=Path, default=Path("/tmp/qa_calibration"))
    parser.add_argument("--jobs", type=int, default=1, help="sessions at a time (processes)")
    parser.add_argument("--fresh", action="store_true",
                        help="re-run the stages even where pickled results exist")
    parser.add_argument("--cached-only", action="store_true",
                        help="only the sessions with pickled results (re-judge them)")
    parser.add_argument("--seed", type=int, default=None,
                        help="first seed of every profile (default: SEEDS, the tuning sets)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    counts = {p: int(n) for p, _, n in (x.partition("=") for x in args.profile)}
    seeds = {p: SEEDS.get(p, 9400) if args.seed is None else args.seed for p in counts}
    rows = collect(args.out, counts, tuple(args.frames), args.fresh, args.cached_only, seeds,
                   args.jobs)
    summary(rows)
    name = "qa_calibration_cached.csv" if args.cached_only else "qa_calibration.csv"
    write_csv(rows, args.out / name)
    print(f"\nwrote {args.out / name}")


if __name__ == "__main__":
    main()
