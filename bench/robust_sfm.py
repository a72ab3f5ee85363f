"""Stage 2 under detector noise: select_steady and reconstruct_hand on cached synthetic sessions
of one profile, scored against the written truth (issue 19 items 2-3, the staged path).

    OMP_NUM_THREADS=1 .venv/bin/python bench/robust_sfm.py --profile real-detector \
        --seed 9700 --sessions 12 --frames 60 [--root /tmp/robust] [--true-onset]

Session i is seed ``[seed, i]`` (``graspcap.synth.generate_session``, written once under
``root/profile`` and reused). Per session: the detected onset's error (frames), then
``reconstruct_hand`` from the detected onset (or from the true one with ``--true-onset``, which
isolates stage 2 from the onset), its cameras (median deg / mm), SfM joints (mm), the frames it
rejected whole, or its failure reason. Prints the share built, the medians, onset within 3
frames and the failures per reason.
"""

from __future__ import annotations

import argparse
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import evaluate, load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage


def _dir(root: Path, profile: str, frames: int, seed: int, i: int) -> Path | None:
    """Session ``[seed, i]`` under ``root/profile``: reused when written, else generated."""
    found = [d for d in sorted((root / profile).glob(f"synth-s{seed}-{i:03d}-*"))
             if (d / "ground_truth").exists()]
    if found:
        return found[0]
    try:
        return generate_session(root / profile, [seed, i], config_for(profile, frames), None)
    except StageError:
        return None


def session_row(d: Path, true_onset: bool, legacy: bool = False) -> dict:
    configs = configs_for()
    if legacy:  # reconstruct_hand/12: fixed-pixel gates, no whole-frame rejection
        rh = configs["reconstruct_hand"]
        configs["reconstruct_hand"] = rh.model_copy(update={
            "frame_rejection": False,
            "depth_links": rh.depth_links.model_copy(update={"consecutive_from_rest": False})})
    up: dict = {}
    for name in ("load_session", "detect_keypoints"):
        up[name] = run_stage(STAGES[name], d, configs[name], up)
    truth = load_truth(d)
    row: dict = {"name": d.name, "steady_true": int(truth["steady_from"])}
    try:
        sel = run_stage(STAGES["select_steady"], d, configs["select_steady"], up)
        row["onset_err"] = int(sel.steady_from - truth["steady_from"])
        row["uncertain"] = bool(getattr(sel, "uncertain", ""))
    except StageError as e:
        row["onset_failed"] = e.reason[:100]
        sel = None
    if true_onset or sel is None:
        from graspcap.tasks.hand_sfm.select_steady import select_steady
        sel = select_steady(np.zeros((int(truth["steady_from"]) + 1, 21, 3)), np.eye(3),
                            int(truth["steady_from"]))
    up["select_steady"] = sel
    try:
        rec = run_stage(STAGES["reconstruct_hand"], d, configs["reconstruct_hand"], up)
    except StageError as e:
        row["failed"] = e.reason
        return row
    ev = evaluate(d, {"steady_from": sel.steady_from, "joints_w": rec.joints_w,
                      "T_w_c": rec.T_w_c})
    diag = rec.diagnostics
    rejected = [r for r in getattr(diag, "frame_rejected", ()) if r]
    row |= {"joints_mm": ev["joints_mpjpe_mm"], "cam_deg": ev["camera_rot_deg"],
            "cam_mm": ev["camera_trans_mm"], "inlier_ratio": float(rec.inlier_ratio),
            "rmse_px": float(rec.reproj_rmse_px), "rejected": len(rejected),
            "sigma_px": float(getattr(diag, "noise_sigma_px", np.nan)),
            "hand_px": float(getattr(diag, "hand_size_px", np.nan)),
            "restarted": bool(diag.restarted_after)}
    return row


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--profile", default="real-detector")
    p.add_argument("--seed", type=int, default=9700)
    p.add_argument("--sessions", type=int, default=12)
    p.add_argument("--first", type=int, default=0)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--root", default=None)
    p.add_argument("--true-onset", action="store_true")
    p.add_argument("--legacy", action="store_true",
                   help="reconstruct_hand without frame_rejection (the stage before it)")
    a = p.parse_args()
    root = Path(a.root) if a.root else Path(tempfile.mkdtemp(prefix="robust_sfm_"))
    rows = []
    for i in range(a.first, a.first + a.sessions):
        d = _dir(root, a.profile, a.frames, a.seed, i)
        if d is None:
            print(f"[{a.seed}, {i}] skipped: the rig cannot stage it")
            continue
        r = session_row(d, a.true_onset, a.legacy)
        rows.append(r)
        print(f"[{a.seed}, {i:2d}] onset {r.get('onset_err', r.get('onset_failed'))!s:>6}"
              f"{'?' if r.get('uncertain') else ' '} "
              + (f"FAILED {r['failed']}" if "failed" in r else
                 f"joints {r['joints_mm']:6.1f} mm  cams {r['cam_deg']:5.2f} deg "
                 f"{r['cam_mm']:6.1f} mm  inliers {r['inlier_ratio']:.2f} "
                 f"rmse {r['rmse_px']:.1f} px  rejected {r['rejected']}  "
                 f"sigma {r['sigma_px']:.1f} hand {r['hand_px']:.0f} px"
                 f"{'  restarted' if r['restarted'] else ''}"),
              flush=True)
    built = [r for r in rows if "failed" not in r]
    med = {k: np.median([r[k] for r in built]) if built else np.nan
           for k in ("joints_mm", "cam_deg", "cam_mm")}
    onset = [r["onset_err"] for r in rows if "onset_err" in r]
    print(f"\n{a.profile} seeds [{a.seed}, {a.first}..{a.first + a.sessions - 1}] x {a.frames} "
          f"frames, onset {'true' if a.true_onset else 'detected'}: built {len(built)}/{len(rows)}"
          f"; medians joints {med['joints_mm']:.1f} mm, cameras {med['cam_deg']:.2f} deg / "
          f"{med['cam_mm']:.1f} mm")
    print(f"onset within 3: {sum(abs(e) <= 3 for e in onset)}/{len(rows)}; errors "
          f"{sorted(onset)}; onset refused {len(rows) - len(onset)}")
    said = [r for r in rows if r.get("uncertain")]
    plain = [r["onset_err"] for r in rows if "onset_err" in r and not r.get("uncertain")]
    print(f"onset marked uncertain (QA flag): {len(said)}/{len(rows)}; of the rest within 3: "
          f"{sum(abs(e) <= 3 for e in plain)}/{len(plain)}; silently wrong (> 3 frames, not "
          f"marked): {sum(abs(e) > 3 for e in plain)}")
    for why, k in Counter(r["failed"][:60] for r in rows if "failed" in r).most_common():
        print(f"  {k} x {why}")


if __name__ == "__main__":
    main()
