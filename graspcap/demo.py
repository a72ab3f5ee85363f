"""`graspcap demo`: synthesise sessions, validate them, build the catalog, score it.

Everything runs locally: Prefect on its ephemeral API with a project-local home, the
catalog in a folder. A session a stage rejects is reported with its reason; the build
goes on with the others.
"""

from __future__ import annotations

import time
from pathlib import Path

import graspcap.catalog as gc
from graspcap.flows.runtime import configure
from graspcap.synth import generate
from graspcap.synth.evaluate import estimate_from_catalog, evaluate
from graspcap.tasks.session.load_session import validate_session

SHOWN = (
    ("object_stage1_rot_deg", "stage-1 object rot (deg)"),
    ("object_stage1_trans_mm", "stage-1 object trans (mm)"),
    ("object_stage1_rot_sym_deg", "stage-1 object rot, symmetry-aware (deg)"),
    ("steady_from_err_frames", "steady_from error (frames)"),
    ("joints_mpjpe_mm", "SfM joints MPJPE (mm)"),
    ("camera_rot_deg", "virtual cameras rot (deg)"),
    ("camera_trans_mm", "virtual cameras trans (mm)"),
    ("camera_rot_aligned_deg", "virtual cameras rot, aligned (deg)"),
    ("crosscheck_max_mm", "GTSAM vs pycolmap max (mm)"),
    ("fit_joints_mm", "fitted hand joints (mm)"),
    ("T_adj_rot_deg", "T_adj rot (deg)"),
    ("T_adj_trans_mm", "T_adj trans (mm)"),
    ("frame_object_rot_deg", "per-frame object rot (deg)"),
    ("frame_object_trans_mm", "per-frame object trans (mm)"),
    ("frame_object_rot_sym_deg", "per-frame object rot, symmetry-aware (deg)"),
    ("frame_object_trans_sym_mm", "per-frame object centroid (mm)"),
    ("object_scan_rot_deg", "scan object rot (deg)"),
    ("object_scan_trans_mm", "scan object trans (mm)"),
    ("contact_mae", "contact MAE, observed vertices"),
    ("contact_iou", "contact IoU at 0.4"),
)


def run_demo(out: Path, *, sessions: int = 3, frames: int = 60, seed: int = 7) -> int:
    """Returns a process exit code: 0 when the demo ran end to end (a session the pipeline
    rejects is reported, not an error of the demo)."""
    out = Path(out)
    t0 = time.perf_counter()
    root = out / "sessions"
    print(f"[1/4] synthesising {sessions} realistic sessions of {frames} frames (seed {seed})")
    dirs = generate(root, sessions=sessions, seed=seed, difficulty="realistic", frames=frames,
                    workers=2)
    print(f"      wrote {root} in {time.perf_counter() - t0:.1f} s")

    print("[2/4] validating against the capture-session contract")
    for d in dirs:
        problems = validate_session(d)
        print(f"      {'OK  ' if not problems else 'FAIL'} {d.name}")
        for p in problems:
            print(f"        - {p}")

    catalog_dir = out / "catalog"
    configure(catalog_dir / "work")  # Prefect's home in the work area; before Prefect loads
    from graspcap.flows.build import build_dataset

    print(f"[3/4] building the catalog {catalog_dir} (Prefect, one DAG of tasks per session)")
    report = build_dataset([root], catalog_dir)
    print("      " + report.summary().replace("\n", "\n      "))

    print("[4/4] the committed catalog against the synthetic ground truth")
    cat = gc.open(catalog_dir)
    rows = cat.to_pandas("sessions")
    frames_df = cat.to_pandas("frames")
    for d in dirs:
        row = rows[rows.session_id == d.name]
        if row.empty or row.iloc[0]["status"] == "failed":
            reason = report.failed.get(d.name) or (row.iloc[0]["error"] if not row.empty else "")
            print(f"      {d.name}: failed: {reason}")
            continue
        est = estimate_from_catalog(row.iloc[0].to_dict(),
                                    frames_df[frames_df.session_id == d.name])
        est["contact"], est["observed"] = cat.contactmap(d.name)
        metrics = evaluate(d, est)
        print(f"      {d.name} ({row.iloc[0]['status']}):")
        for key, label in SHOWN:
            if key in metrics:
                print(f"        {label:<30} {metrics[key]:8.2f}")

    print(f"\nsessions: {root}\ncatalog:  {catalog_dir}  (graspcap status --catalog {catalog_dir})")
    print(f"read it:  python -c \"import graspcap.catalog as gc; "
          f"print(gc.open('{catalog_dir}').to_pandas('sessions'))\"")
    print(f"demo finished in {time.perf_counter() - t0:.0f} s")
    return 0
