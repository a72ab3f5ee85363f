"""Accuracy and speed of the three pose stages on synthetic rig sessions (markdown table).

    OMP_NUM_THREADS=1 .venv/bin/python bench/registration_bench.py --sessions 8 --seed 9000

Generates ``--sessions`` realistic sessions (60 frames) under ``--out`` (reused when they
are already there), runs the real stages in pipeline order and compares with the ground
truth. ``estimate_adjustment`` is judged on the frame it was given (the detected first
steady frame): its pose ``T_adj @ T_w_o_stage1`` against the true object pose in that frame
(``frame``), which isolates the stage from ``select_steady`` and stage-1 symmetry flips;
``T_adj`` against the true ``T_adj`` is reported too. A session whose hand fit fails is run
with the keypoint-bone mask alone (counted in ``bones-only``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from graspcap.synth import generate
from graspcap.synth.evaluate import load_truth
from graspcap.synth.rig import interpolate_pose, smoothstep
from graspcap.tasks import pipeline
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, pose_error
from graspcap.tasks.hand.image_masks import hand_mask_from_keypoints
from graspcap.tasks.object_pose import estimate_adjustment as ea

POSE_STAGES = ("register_object", "estimate_adjustment", "register_scan")
UPSTREAM = ("load_session", "register_object", "detect_keypoints", "select_steady",
            "reconstruct_hand", "fit_hand")  # fmt: skip
LIFT_M = 0.05  # graspcap.synth.session._LIFT_M: the arc of the object while it is lifted


def true_object_pose(session_dir: Path, frame: int) -> np.ndarray:
    """The object's true pose in the colour camera at grasp-video ``frame``."""
    t = load_truth(session_dir)
    steady = int(t["steady_from"])
    T_steady = t["T_adj"] @ t["T_w_o_stage1"]
    if frame >= steady:
        return inv_T(t["T_w_c"][frame - steady]) @ T_steady
    manifest = json.loads((session_dir / "session.json").read_text())
    T_ct = np.asarray(manifest["turntable"]["T_color_turntable"], float)
    s = float(smoothstep((frame / steady - 0.35) / 0.65))
    T = interpolate_pose(t["T_w_o_stage1"], T_steady, s)
    T[:3, 3] += T_ct[:3, 2] * LIFT_M * np.sin(np.pi * s)
    return T


def _adjustment(session, cfg, res) -> tuple[object, bool]:
    """The stage as the pipeline calls it; with the bone mask alone when fit_hand failed."""
    if "fit_hand" in res:
        return pipeline.STAGES["estimate_adjustment"].run(session, cfg, **res), False
    s = res["select_steady"].steady_from
    depth = session.read_depth_m(session.grasp_path("depth", s))
    kp = res["detect_keypoints"].keypoints[s]
    mask = hand_mask_from_keypoints(kp[:, :2], kp[:, 2], depth.shape, 6.0)
    V, F = session.read_mesh()
    K = session.color_K
    return ea.estimate_adjustment(depth, K, V, F, res["register_object"].T_w_o, mask, cfg), True


def run_one(session_dir: Path) -> dict[str, float | str]:
    configs = pipeline.configs_for()
    res: dict = {}
    row: dict[str, float | str] = {"session": session_dir.name}
    for name in UPSTREAM:
        t0 = time.perf_counter()
        try:
            res[name] = pipeline.run_stage(pipeline.STAGES[name], session_dir, configs[name], res)
        except StageError as e:
            if name != "fit_hand":
                row["error"] = str(e)
                return row
            row["bones_only"] = 1.0
        if name == "register_object":
            row["register_object_s"] = time.perf_counter() - t0
    truth = load_truth(session_dir)
    session = res["load_session"]
    row |= _errors("object", res["register_object"].T_w_o, truth["T_w_o_stage1"])
    t0 = time.perf_counter()
    try:
        adj, _ = _adjustment(session, configs["estimate_adjustment"], res)
        row["estimate_adjustment_s"] = time.perf_counter() - t0
        frame = res["select_steady"].steady_from
        row["steady_offset"] = float(frame - int(truth["steady_from"]))
        row |= _errors("frame", adj.T_w_o, true_object_pose(session_dir, frame))
        row |= _errors("T_adj", adj.T_adj, truth["T_adj"])
    except StageError as e:
        row["estimate_adjustment_s"] = time.perf_counter() - t0
        row["error"] = str(e)
    t0 = time.perf_counter()
    scan = pipeline.STAGES["register_scan"].run(session, configs["register_scan"])
    row["register_scan_s"] = time.perf_counter() - t0
    row |= _errors("scan", scan.T_turntable_o_scan, truth["T_turntable_o_scan"])
    return row


def _errors(prefix: str, T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    rot, trans = pose_error(T_est, T_true)
    return {f"{prefix}_deg": rot, f"{prefix}_mm": 1e3 * trans}


def table(rows: list[dict]) -> str:
    def med(key: str) -> str:
        v = [r[key] for r in rows if key in r]
        return f"{np.median(v):.2f}" if v else "-"

    def within(prefix: str, deg: float = 1.0, mm: float = 3.0) -> str:
        ok = [r[f"{prefix}_deg"] <= deg and r[f"{prefix}_mm"] <= mm for r in rows
              if f"{prefix}_deg" in r]
        return f"{sum(ok)}/{len(rows)}"

    lines = [
        "| stage | median rot (deg) | median trans (mm) | within 1 deg / 3 mm | median time (s) |",
        "|---|---|---|---|---|",
        f"| register_object | {med('object_deg')} | {med('object_mm')} | {within('object')} "
        f"| {med('register_object_s')} |",
        f"| estimate_adjustment (frame pose) | {med('frame_deg')} | {med('frame_mm')} "
        f"| {within('frame')} | {med('estimate_adjustment_s')} |",
        f"| estimate_adjustment (T_adj vs truth) | {med('T_adj_deg')} | {med('T_adj_mm')} "
        f"| {within('T_adj')} | |",
        f"| register_scan | {med('scan_deg')} | {med('scan_mm')} | {within('scan')} "
        f"| {med('register_scan_s')} |",
    ]
    totals = [sum(r.get(f"{s}_s", 0.0) for s in POSE_STAGES) for r in rows]
    lines.append(f"\npose stages total per session: median {np.median(totals):.2f} s, "
                 f"max {np.max(totals):.2f} s; failures: {sum('error' in r for r in rows)}; "
                 f"bones-only masks: {sum('bones_only' in r for r in rows)}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=8)
    ap.add_argument("--seed", type=int, default=9000)
    ap.add_argument("--out", type=Path, default=Path("/tmp/graspcap-registration-bench"))
    ap.add_argument("--difficulty", default="realistic")
    ap.add_argument("--per-session", action="store_true", help="print one line per session")
    args = ap.parse_args()
    out = args.out / f"{args.difficulty}-{args.seed}"
    dirs = sorted(out.glob("synth-*")) if out.is_dir() else []
    if len(dirs) < args.sessions:
        dirs = generate(out, sessions=args.sessions, seed=args.seed,
                        difficulty=args.difficulty, frames=60)
    rows = []
    for d in dirs[: args.sessions]:
        rows.append(run_one(Path(d)))
        if args.per_session:
            print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in rows[-1].items()},
                  flush=True)
    print(table(rows))


if __name__ == "__main__":
    main()
