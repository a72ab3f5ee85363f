"""Stage 2 benchmark: per-stage time for 120 frames, accuracy over synthetic sessions.

Run: OMP_NUM_THREADS=1 .venv/bin/python bench/bench_sfm.py [n_sessions]

or, on session directories (e.g. ``graspcap synth /tmp/s --sessions 6 --seed 9400 --frames 120
--difficulty realistic``), reconstruct_hand alone after its upstream stages, with its wall
time, process CPU and this thread's CPU (the critical path when the second threads overlap):

    OMP_NUM_THREADS=1 .venv/bin/python bench/bench_sfm.py --sessions-dir /tmp/s [repeats]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from graspcap.synth.hand_video import make_hand_video
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import pose_error
from graspcap.tasks.hand_sfm.crosscheck_sfm import crosscheck_sfm
from graspcap.tasks.hand_sfm.reconstruct_hand import reconstruct_hand
from graspcap.tasks.hand_sfm.select_steady import select_steady


def main(n_sessions: int = 10) -> None:
    rows, onset_err = [], []
    for seed in range(n_sessions):
        rng = np.random.default_rng(100 + seed)
        steady = int(rng.integers(15, 45))
        video = make_hand_video(
            n_frames=120,
            steady_from=steady,
            seed=seed,
            closing_deg_per_frame=float(rng.uniform(1.0, 3.0)),
        )
        t0 = time.perf_counter()
        try:
            found = select_steady(video.keypoints, video.K, None).steady_from
            onset_err.append(found - steady)
        except StageError:
            onset_err.append(np.nan)
        t1 = time.perf_counter()
        rec = reconstruct_hand(
            video.keypoints, video.K, steady, video.depth_at, video.surface_offset_m
        )
        t2 = time.perf_counter()
        check = crosscheck_sfm(video.keypoints, video.K, rec)
        t3 = time.perf_counter()
        errs = np.array(
            [pose_error(a, b) for a, b in zip(rec.T_w_c, video.T_w_c[steady:], strict=True)]
        )
        mpjpe = np.linalg.norm(rec.joints_w - video.joints_w, axis=1).mean()
        rows.append(
            (
                t1 - t0,
                t2 - t1,
                t3 - t2,
                mpjpe * 1e3,
                np.median(errs[:, 0]),
                np.median(errs[:, 1]) * 1e3,
                check.median_joint_discrepancy_m * 1e3,
                check.max_joint_discrepancy_m * 1e3,
            )
        )
        print(
            f"seed {seed}: steady {steady} found {onset_err[-1] + steady}; times "
            f"{t1 - t0:.2f}/{t2 - t1:.2f}/{t3 - t2:.2f} s; mpjpe {mpjpe * 1e3:.2f} mm; "
            f"cam median {np.median(errs[:, 0]):.2f} deg {np.median(errs[:, 1]) * 1e3:.1f} mm; "
            f"crosscheck median/max {rows[-1][6]:.2f}/{rows[-1][7]:.2f} mm",
            flush=True,
        )
    r = np.array(rows)
    e = np.abs(np.array(onset_err, dtype=float))
    print(
        f"median time select_steady {np.median(r[:, 0]):.2f} s, reconstruct_hand "
        f"{np.median(r[:, 1]):.2f} s, crosscheck_sfm {np.median(r[:, 2]):.2f} s"
    )
    print(
        f"mpjpe mean {r[:, 3].mean():.2f} mm max {r[:, 3].max():.2f}; camera median rot "
        f"{np.median(r[:, 4]):.2f} deg, trans {np.median(r[:, 5]):.1f} mm; crosscheck max "
        f"{r[:, 7].max():.2f} mm"
    )
    print(f"steady onset within 3 frames: {np.mean(e <= 3):.0%} (errors {onset_err})")


def on_sessions(root: Path, repeats: int = 1) -> None:
    """reconstruct_hand on every session under ``root``: times and accuracy per session."""
    from graspcap.synth.evaluate import evaluate
    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

    cfgs, rows = configs_for(), []
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        up: dict = {}
        for name in ("load_session", "detect_keypoints", "select_steady"):
            up[name] = run_stage(STAGES[name], d, cfgs[name], up)
        for _ in range(repeats):
            w, c, t = time.perf_counter(), time.process_time(), time.thread_time()
            rec = run_stage(STAGES["reconstruct_hand"], d, cfgs["reconstruct_hand"], up)
            w, c, t = time.perf_counter() - w, time.process_time() - c, time.thread_time() - t
            m = evaluate(d, {"steady_from": up["select_steady"].steady_from,
                             "joints_w": rec.joints_w, "T_w_c": rec.T_w_c})
            rows.append((w, c, t, m["joints_mpjpe_mm"], m["camera_rot_deg"],
                         m["camera_trans_mm"]))
            print(f"{d.name}: wall {w:.2f} s, CPU {c:.2f} s (this thread {t:.2f}); MPJPE "
                  f"{rows[-1][3]:.2f} mm, cameras {rows[-1][4]:.2f} deg {rows[-1][5]:.1f} mm"
                  + (f"; restarted: {rec.diagnostics.restarted_after}"
                     if rec.diagnostics.restarted_after else ""), flush=True)
    r = np.array(rows)
    for k, name in enumerate(("wall s", "CPU s", "thread CPU s", "MPJPE mm", "cam deg",
                              "cam mm")):
        print(f"{name}: median {np.median(r[:, k]):.3f}, p90 {np.percentile(r[:, k], 90):.3f}, "
              f"max {r[:, k].max():.3f}")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--sessions-dir":
        on_sessions(Path(sys.argv[2]), int(sys.argv[3]) if len(sys.argv) > 3 else 1)
    else:
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 10)
