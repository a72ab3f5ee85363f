"""Accuracy of the pipeline against synthetic ground truth, one table per profile.

    .venv/bin/python bench/accuracy.py [--sessions 12] [--frames 120] [--profile realistic hard]
        [--seed 9000] [--jobs 2]
    .venv/bin/python bench/accuracy.py --profile wild --seed S --sessions 30 --frames 60 --jobs 2

Session i is generated with seed ``[seed, i]`` (9000 by default; the tests use small seeds;
a report set is a seed drawn once and written down before the run, never tuned on afterwards:
``docs/benchmarks.md`` names the tuning and report seeds of every figure), every stage runs
bare (``graspcap.tasks.pipeline.run_session``), and per profile it prints the share of sessions
built, the median and p90 of every metric next to its target, the QA confusion table (good /
not good by ``graspcap.synth.evaluate.GOOD_IF`` x ok / flagged / failed, with precision and
yield) and the failures per reason. A session a stage rejects is counted as failed with its
reason, never dropped silently. ``--out`` appends each session's errors, timings, verdict, QA
metrics and stage diagnostics (``_diagnostics``) as a JSON line, for calibrating QA offline.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import (
    confusion_markdown,
    estimate_from_results,
    evaluate,
    load_truth,
    misses,
    qa_confusion,
)
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.pipeline import STAGES, configs_for, run_session, steady_hand_size_px

SEED = 9000
"""The default seed; the reported runs in docs/benchmarks.md use it unless they say."""

# metric -> (target, "<=" or ">=") from the target table
# (the raw object pose errors and the anchored camera / joint errors are the older tables';
# ``_sym_`` / ``_mssd_`` / ``_adds_`` are over the object's symmetries and ``_aligned_`` after one
# robust alignment of the whole trajectory: graspcap.synth.evaluate, docs/qa.md)
TARGETS = {
    "object_stage1_rot_deg": (1.0, "<="),
    "object_stage1_rot_sym_deg": (1.0, "<="),
    "object_stage1_trans_mm": (3.0, "<="),
    "object_stage1_trans_sym_mm": (3.0, "<="),
    "object_stage1_mssd_mm": (None, ""),
    "steady_from_err_frames": (3.0, "<="),
    "joints_mpjpe_mm": (3.0, "<="),
    "joints_aligned_mm": (3.0, "<="),
    "camera_rot_deg": (0.5, "<="),
    "camera_rot_aligned_deg": (0.5, "<="),
    "camera_trans_mm": (5.0, "<="),
    "camera_trans_aligned_mm": (5.0, "<="),
    # stage 2's own cameras and joints (the rows above: the catalog's frames.T_w_c, which the
    # object tracking in each frame's depth corrects where it can)
    "sfm_camera_rot_deg": (None, ""),
    "sfm_camera_trans_mm": (None, ""),
    "sfm_joints_mpjpe_mm": (None, ""),
    "frame_joints_mm": (None, ""),
    "crosscheck_max_mm": (1.0, "<="),
    "fit_joints_mm": (6.0, "<="),
    "frame_object_rot_deg": (2.0, "<="),
    "frame_object_rot_sym_deg": (2.0, "<="),
    "frame_object_trans_mm": (6.0, "<="),
    "frame_object_trans_sym_mm": (6.0, "<="),
    "frame_object_mssd_mm": (None, ""),
    "frame_object_adds_mm": (None, ""),
    "T_adj_rot_deg": (None, ""),
    "T_adj_rot_sym_deg": (None, ""),
    "T_adj_trans_mm": (None, ""),
    "T_adj_trans_sym_mm": (None, ""),
    "object_scan_rot_deg": (1.0, "<="),
    "object_scan_rot_sym_deg": (1.0, "<="),
    "object_scan_trans_mm": (3.0, "<="),
    "object_scan_trans_sym_mm": (3.0, "<="),
    "reproj_rmse_px": (None, ""),
    "contact_mae": (0.06, "<="),
    "contact_iou": (0.85, ">="),
    "contact_seen_share": (0.95, ">="),
    # issue 6: refinement
    "contact_near_hand_fit": (None, ""),
    "contact_near_hand_refined": (0.85, ">="),
    "penetration_max_mm_fit": (None, ""),
    "penetration_max_mm_refined": (2.0, "<="),
    "refined_joints_mm": (None, ""),
    "refined_joints_aligned_mm": (None, ""),
    "refine_time_s": (5.0, "<="),
}


OFF_LIMITS = {"object_stage1_rot_sym_deg": 5.0, "joints_mpjpe_mm": 10.0, "camera_rot_deg": 2.0,
              "frame_object_rot_sym_deg": 5.0, "frame_object_trans_sym_mm": 15.0}
"""A session beyond any of these (several times its target) is off: QA must not pass it."""

POSE_STAGES = ("register_object", "select_steady", "reconstruct_hand", "crosscheck_sfm",
               "fit_hand", "estimate_adjustment", "propagate_poses")  # fmt: skip
"""The stages of issue 3, whose total per session has the 6 s target."""


def _median(x) -> float:
    """Median of the finite values (NaN where none is)."""
    x = np.asarray(x, float)
    return float(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else float("nan")


def _diagnostics(results: dict) -> dict[str, float]:
    """What the stages measured besides QA's metrics, for calibrating QA offline from the JSON
    lines: the detections' noise, the joint solve's dropped frames and depth refinement, and
    the stage-2 cameras against the object tracked in each frame's depth."""
    out: dict[str, float] = {}
    rec = results.get("reconstruct_hand")
    if rec is not None:
        dia = rec.diagnostics
        out |= {"noise_sigma_px": dia.noise_sigma_px, "hand_size_px": dia.hand_size_px,
                "reproj_rmse_px": rec.reproj_rmse_px, "frames": len(rec.frames),
                "pose_valid_share": float(np.mean(rec.pose_valid))}
        out["hand_image_px"] = steady_hand_size_px(results)
        cam_w = np.asarray(rec.T_w_c)[:, :3, 3]
        dist = np.linalg.norm(cam_w - np.nanmean(rec.joints_w, axis=0), axis=1)
        out["hand_distance_m"] = float(np.median(dist))
    js = results.get("joint_solve")
    if js is not None:
        out |= {"js_joint": float(js.path == "joint"),
                "js_rejected_share": float(np.mean(js.frame_rejected)),
                "js_frame_median_px": _median(js.frame_median_px)}
        if js.depth_refine is not None:
            dr = js.depth_refine
            out |= {"dr_kept": float(dr.kept), "dr_rms_before_mm": 1e3 * dr.rms_before_m,
                    "dr_rms_after_mm": 1e3 * dr.rms_after_m, "dr_points": dr.points,
                    "dr_reproj_before_px": dr.reproj_before_px,
                    "dr_reproj_after_px": dr.reproj_after_px,
                    "dr_moved_mm": 1e3 * float(np.median(np.linalg.norm(
                        dr.joints_w_before - js.reconstruction.joints_w, axis=1)))}
    adj = results.get("estimate_adjustment")
    avg = None if adj is None else adj.average
    if avg is not None:
        out |= {"avg_frames": avg.frames, "avg_dropped": avg.dropped,
                "avg_spread_deg": avg.spread_deg, "avg_spread_mm": 1e3 * avg.spread_m}
    tr = None if adj is None else adj.tracking
    if tr is not None:
        out |= {"tracked_share": float(np.mean(tr.tracked)),
                "registered_share": float(np.mean(tr.registered))
                if tr.registered is not None else float("nan"),
                "track_corr_deg": _median(tr.correction_deg)}
    return {k: float(v) for k, v in out.items() if v is not None}


def _session(root: Path, profile: str, frames: int, seed: int, i: int, preset: str = "default"
             ) -> dict | None:
    """Session ``[seed, i]`` of ``profile`` generated and run bare: its errors, timings, QA
    verdict, or the stage's failure; None when the rig cannot stage the seed."""
    try:
        d = generate_session(root / profile, [seed, i], config_for(profile, frames), None)
    except StageError:
        return None
    t: dict[str, float] = {}
    try:
        results = run_session(d, configs_for(preset), timings_s=t)
    except StageError as e:
        return {"name": d.name, "failed": f"{e.stage}: {e.reason[:80]}"}
    qa = results["qa_metrics"]
    return {"name": d.name, "failed": None, "timings": t, "verdict": str(qa.verdict),
            "notes": list(qa.notes), "reasons": list(qa.reasons), "qa": dict(qa.metrics),
            "diagnostics": _diagnostics(results),
            "metrics": evaluate(d, estimate_from_results(results, timings_s=t)),
            "steady_error": results["select_steady"].steady_from
            - int(load_truth(d)["steady_from"]),
            "steady_uncertain": results["select_steady"].uncertain}


def run(profile: str, sessions: int, frames: tuple[int, ...], root: Path, seed: int = SEED,
        jobs: int = 1, out: Path | None = None, preset: str = "default") -> None:
    from concurrent.futures import ProcessPoolExecutor

    args = [(root, profile, frames[i % len(frames)], seed, i, preset) for i in range(sessions)]
    if jobs <= 1:
        done = [_session(*a) for a in args]
    else:
        with ProcessPoolExecutor(jobs) as pool:
            done = list(pool.map(_session, *zip(*args, strict=True)))
    if out is not None:
        with out.open("a") as f:
            for a, r in zip(args, done, strict=True):
                f.write(json.dumps({"profile": profile, "seed": [seed, a[4]], "frames": a[2],
                                    "preset": preset, "result": r}, default=float) + "\n")
    skipped = sum(r is None for r in done)
    ran = [r for r in done if r is not None]
    metrics: dict[str, list[float]] = defaultdict(list)
    timings: dict[str, list[float]] = defaultdict(list)
    failures: Counter[str] = Counter()
    steady_within_3 = []
    steady_errors = []
    steady_silent = []  # off by more than 3 frames and not marked uncertain
    per_session = []
    verdicts: Counter[str] = Counter()
    judged: list[tuple[bool, str]] = []
    not_good: Counter[str] = Counter()
    silent: list[str] = []  # QA ok, but off by OFF_LIMITS
    for r in ran:
        if r["failed"]:
            failures[r["failed"]] += 1
            judged.append((False, "failed"))
            continue
        verdicts[r["verdict"]] += 1
        session_metrics, t = r["metrics"], r["timings"]
        missed = misses(session_metrics)
        good, why = not missed, "; ".join(text for _, text in missed)
        judged.append((good, r["verdict"]))
        not_good.update(q for q, _ in missed)
        for k, v in session_metrics.items():
            metrics[k].append(v)
        off = [k for k, lim in OFF_LIMITS.items() if session_metrics.get(k, 0.0) > lim]
        if off and r["verdict"] == "ok":
            noted = f"; QA notes: {' / '.join(r['notes'])}" if r["notes"] else "; no QA note"
            silent.append(f"{r['name']} ({', '.join(off)}{noted})")
        steady_within_3.append(session_metrics["steady_from_err_frames"] <= 3)
        steady_errors.append(r["steady_error"])
        if not steady_within_3[-1] and not r.get("steady_uncertain"):
            steady_silent.append(f"{r['name']} ({r['steady_error']:+d})")
        for k, v in t.items():
            timings[k].append(v)
        m = session_metrics
        per_session.append(
            f"| {r['name']} | {steady_errors[-1]} | {m.get('joints_mpjpe_mm', np.nan):.2f} "
            f"| {m.get('camera_rot_deg', np.nan):.2f} / {m.get('camera_trans_mm', np.nan):.1f} "
            f"| {m.get('camera_rot_aligned_deg', np.nan):.2f} "
            f"/ {m.get('camera_trans_aligned_mm', np.nan):.1f} "
            f"| {m.get('sfm_camera_rot_deg', np.nan):.2f} "
            f"| {m.get('frame_joints_mm', np.nan):.1f} "
            f"| {m.get('frame_object_rot_deg', np.nan):.2f} "
            f"/ {m.get('frame_object_trans_mm', np.nan):.1f} "
            f"| {m.get('frame_object_rot_sym_deg', np.nan):.2f} "
            f"/ {m.get('frame_object_trans_sym_mm', np.nan):.1f} "
            f"| {sum(t[n] for n in POSE_STAGES):.2f} | {r['verdict']} "
            f"| {'good' if good else why[:60]} |"
        )
    ok = len(ran) - sum(failures.values())
    print(
        f"\n### {profile}: {len(ran)} sessions x {'/'.join(map(str, frames))} frames "
        f"(seed {seed}, preset {preset}), "
        f"{ok} ran every stage"
        + (f" ({skipped} seeds the rig could not stage)" if skipped else "")
        + "\n"
    )
    print("| metric | median | p90 | target | met |")
    print("|---|---|---|---|---|")
    for k, (target, op) in TARGETS.items():
        if k not in metrics:
            continue
        v = np.asarray(metrics[k])
        med = float(np.median(v))
        met = (
            ""
            if target is None
            else ("yes" if (med <= target if op == "<=" else med >= target) else "**no**")
        )
        tgt = "" if target is None else f"{op} {target:g}"
        print(f"| {k} | {med:.3f} | {np.percentile(v, 90):.3f} | {tgt} | {met} |")
    if steady_within_3:
        print(
            f"| steady_from within 3 frames | {100 * np.mean(steady_within_3):.0f} % "
            "| | >= 90 % | |"
        )
        print(f"| steady_from within 3 frames or marked uncertain | "
              f"{100 * (1 - len(steady_silent) / len(steady_within_3)):.0f} % | | | |")
        print(f"\nsteady_from detected - true, per session: {steady_errors}")
        print(f"off by more than 3 frames and not marked uncertain: {len(steady_silent)} "
              + " ".join(steady_silent))
    print(f"\nbuilt (every stage ran): {ok} of {len(ran)} ({100 * ok / max(len(ran), 1):.0f} %)")
    print(f"\nQA verdicts of the sessions that ran every stage: {dict(sorted(verdicts.items()))}")
    print("\nQA confusion (a session a stage refused counts as not good and failed):\n")
    print(confusion_markdown(qa_confusion(judged)))
    print("not good because (sessions per quantity): "
          + ", ".join(f"{k} {n}" for k, n in not_good.most_common()))
    print(f"QA ok although off ({OFF_LIMITS}): {len(silent)}")
    for line in silent:
        print(f"- {line}")
    print("\n| stage | median time (s) |")
    print("|---|---|")
    total = 0.0
    for name in STAGES:
        if timings[name]:
            med = float(np.median(timings[name]))
            total += med if name != "load_session" else 0.0
            print(f"| {name} | {med:.3f} |")
    pose = [sum(t) for t in zip(*(timings[n] for n in POSE_STAGES), strict=True)]
    if pose:
        print(f"| pose stages (issue 3) per session, median | {float(np.median(pose)):.2f} |")
    print(f"| all but load_session | {total:.2f} |")
    for reason, n in failures.items():
        print(f"\nfailed x{n}: {reason}")
    print(
        "\n| session | steady error | MPJPE mm | cameras deg / mm | aligned cameras deg / mm "
        "| stage 2 cameras deg | per-frame hand mm | T_c_o deg / mm | T_c_o sym deg / mm "
        "| pose stages s | QA | good |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(per_session))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=12)
    parser.add_argument("--frames", type=int, nargs="+", default=[120],
                        help="video lengths, cycled over the sessions")
    parser.add_argument("--profile", "--difficulty", nargs="+", dest="profile",
                        default=["easy", "realistic", "hard"])
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--jobs", type=int, default=1, help="sessions at a time (processes)")
    parser.add_argument("--preset", default="default",
                        help="pipeline preset (graspcap.tasks.pipeline.configs_for), e.g. staged")
    parser.add_argument("--out", type=Path, default=None,
                        help="append each session's errors, timings and verdict here (JSON lines)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for profile in args.profile:
            run(profile, args.sessions, tuple(args.frames), Path(tmp), args.seed, args.jobs,
                args.out, args.preset)


if __name__ == "__main__":
    main()
