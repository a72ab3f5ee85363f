"""select_steady and reconstruct_hand on synthetic rig sessions: per-session and median table.

Run: OMP_NUM_THREADS=1 .venv/bin/python bench/steady_bench.py [n_sessions] [seed] [out_dir]

Sessions come from ``graspcap.synth.generate(out_dir, sessions=n, seed=seed,
difficulty="realistic", frames=120)`` (written once, reused when ``out_dir`` already holds
them). Times are process CPU seconds (the machine is shared; wall time is noisier).
Each stage runs as in the pipeline (``pipeline.run_stage``, default presets: reconstruct_hand
from the detected onset, with the session's depth frames). ``coarse_err`` is
select_steady's coarse (energy CUSUM) onset before the matched-filter refinement.
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import evaluate, load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

CONFIGS = configs_for()


def session_dirs(out: Path, n: int, seed: int) -> list[Path]:
    """The sessions of seeds ``[seed, 0..n-1]`` under ``out``, generated when missing; a seed
    the rig cannot stage is skipped and said (as bench/accuracy.py does)."""
    found = sorted(out.glob(f"synth-s{seed}-*"))
    if len(found) >= n and all((d / "ground_truth" / "truth.json").exists() for d in found[:n]):
        return found[:n]
    cfg = config_for("realistic", 120)
    dirs = []
    for i in range(n):
        try:
            dirs.append(generate_session(out, [seed, i], cfg, None))
        except StageError as e:
            print(f"seed [{seed}, {i}] skipped: {e}")
    return dirs


def run(d: Path) -> dict[str, float]:
    up: dict = {}
    for name in ("load_session", "detect_keypoints"):
        up[name] = run_stage(STAGES[name], d, CONFIGS[name], up)
    truth = load_truth(d)
    row = {"steady_true": float(truth["steady_from"])}
    t0 = time.process_time()
    try:  # detected: synthetic manifests leave steady_from out
        sel = up["select_steady"] = run_stage(
            STAGES["select_steady"], d, CONFIGS["select_steady"], up
        )
    except StageError as e:
        print(f"  {d.name}: select_steady failed: {e.reason}")
        return row | {"steady_err": np.nan, "steady_s": time.process_time() - t0}
    t1 = time.process_time()
    try:
        rec = run_stage(STAGES["reconstruct_hand"], d, CONFIGS["reconstruct_hand"], up)
    except StageError as e:
        print(f"  {d.name}: reconstruct_hand raised: {e.reason}")
        return row | {"steady_found": float(sel.steady_from),
                      "steady_err": float(sel.steady_from - truth["steady_from"]),
                      "coarse_err": float(sel.coarse_from - truth["steady_from"]),
                      "steady_s": t1 - t0, "recon_s": time.process_time() - t1}  # fmt: skip
    t2 = time.process_time()
    ev = evaluate(d, {"steady_from": sel.steady_from, "joints_w": rec.joints_w, "T_w_c": rec.T_w_c})
    return row | {
        "steady_found": float(sel.steady_from),
        "steady_err": float(sel.steady_from - truth["steady_from"]),
        "coarse_err": float(sel.coarse_from - truth["steady_from"]),
        "steady_s": t1 - t0,
        "recon_s": t2 - t1,
        "mpjpe_mm": ev["joints_mpjpe_mm"],
        "cam_rot_deg": ev["camera_rot_deg"],
        "cam_trans_mm": ev["camera_trans_mm"],
    }


def main(n: int = 10, seed: int = 9000, out: str | None = None) -> None:
    out_dir = Path(out) if out else Path(tempfile.mkdtemp(prefix="steady_bench_"))
    rows = []
    cols = ["steady_true", "steady_found", "steady_err", "coarse_err", "steady_s", "recon_s",
            "mpjpe_mm",
            "cam_rot_deg", "cam_trans_mm"]  # fmt: skip
    print("session".ljust(34) + "".join(c.rjust(13) for c in cols))
    for d in session_dirs(out_dir, n, seed):
        row = run(d)
        rows.append(row)
        print(d.name.ljust(34) + "".join(f"{row.get(c, np.nan):13.2f}" for c in cols), flush=True)
    table = {c: np.array([r.get(c, np.nan) for r in rows]) for c in cols}
    print("median".ljust(34) + "".join(f"{np.nanmedian(table[c]):13.2f}" for c in cols))
    err = np.abs(table["steady_err"])
    print(f"onset within 3 frames: {np.sum(err <= 3)}/{len(rows)} ({np.mean(err <= 3):.0%}); "
          f"coarse onset alone {np.sum(np.abs(table['coarse_err']) <= 3)}/{len(rows)}; errors "
          f"{sorted(int(e) for e in table['steady_err'] if np.isfinite(e))}")  # fmt: skip
    print(f"max camera median rot {np.nanmax(table['cam_rot_deg']):.2f} deg, "
          f"trans {np.nanmax(table['cam_trans_mm']):.1f} mm; max mpjpe "
          f"{np.nanmax(table['mpjpe_mm']):.2f} mm")  # fmt: skip


if __name__ == "__main__":
    args = sys.argv[1:]
    main(int(args[0]) if args else 10, int(args[1]) if len(args) > 1 else 9000,
         args[2] if len(args) > 2 else None)  # fmt: skip
