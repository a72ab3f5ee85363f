"""Compare a session's stage results with its ground truth (synthetic sessions only).

The builder never reads ``ground_truth/``; this module is for the demo, the
accuracy benchmark and tests. Every metric is named with its unit.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.tasks.geometry import inv_T, pose_error, transform_points


def load_truth(session_dir: Path) -> dict[str, Any]:
    """``ground_truth/truth.json`` with every ``T_*`` and joint list as numpy arrays."""
    truth = json.loads((Path(session_dir) / "ground_truth" / "truth.json").read_text())
    return {k: np.asarray(v, dtype=float) if isinstance(v, list) else v for k, v in truth.items()}


def _pose_metrics(prefix: str, T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    rot_deg, trans_m = pose_error(T_est, T_true)
    return {f"{prefix}_rot_deg": rot_deg, f"{prefix}_trans_mm": 1e3 * trans_m}


def evaluate(session_dir: Path, results: Mapping[str, Any]) -> dict[str, float]:
    """Errors of whatever stages ran (a missing stage gives no entries).

    ``results`` maps stage name to its result, as :func:`graspcap.tasks.pipeline.run_session`
    returns them.
    """
    truth = load_truth(session_dir)
    out: dict[str, float] = {}
    if "register_object" in results:
        out |= _pose_metrics(
            "object_stage1", results["register_object"].T_w_o, truth["T_w_o_stage1"]
        )
    if "register_scan" in results:
        out |= _pose_metrics(
            "object_scan", results["register_scan"].T_turntable_o_scan, truth["T_turntable_o_scan"]
        )
    if "estimate_adjustment" in results:
        out |= _pose_metrics("T_adj", results["estimate_adjustment"].T_adj, truth["T_adj"])
    steady_true = int(truth["steady_from"])
    if "select_steady" in results:
        out["steady_from_err_frames"] = float(
            abs(results["select_steady"].steady_from - steady_true)
        )
    if "reconstruct_hand" in results:
        rec = results["reconstruct_hand"]
        steady_est = results["select_steady"].steady_from
        out["joints_mpjpe_mm"] = _mpjpe_mm(rec.joints_w, rec.T_w_c, steady_est, truth)
        cams = _camera_errors(rec.T_w_c, steady_est, truth)
        out["camera_rot_deg"] = float(np.median(cams[:, 0]))
        out["camera_trans_mm"] = 1e3 * float(np.median(cams[:, 1]))
        out["reproj_rmse_px"] = float(rec.reproj_rmse_px)
    if "crosscheck_sfm" in results:
        out["crosscheck_max_mm"] = 1e3 * float(
            np.max(results["crosscheck_sfm"].joint_discrepancy_m)
        )
    if "fit_hand" in results:
        out["fit_joints_mm"] = _mpjpe_mm(
            results["fit_hand"].joints_fit_w,
            results["reconstruct_hand"].T_w_c,
            results["select_steady"].steady_from,
            truth,
        )
    if "propagate_poses" in results:
        out |= _per_frame_object_errors(results, truth)
    return out


def _mpjpe_mm(
    joints_w: np.ndarray, T_w_c: np.ndarray, steady_est: int, truth: Mapping[str, Any]
) -> float:
    """Mean joint error in mm, no alignment, compared in the camera of the later of the two
    first steady frames (each world frame is its own first steady camera)."""
    steady_true = int(truth["steady_from"])
    first = max(steady_est, steady_true)
    est = transform_points(inv_T(T_w_c[first - steady_est]), joints_w)
    tru = transform_points(inv_T(truth["T_w_c"][first - steady_true]), truth["joints_w"])
    return 1e3 * float(np.linalg.norm(est - tru, axis=1).mean())


def _camera_errors(T_w_c: np.ndarray, steady_est: int, truth: Mapping[str, Any]) -> np.ndarray:
    """(k, 2) rotation deg / translation m of the virtual cameras on frames both cover.

    Both reconstructions put the world at their own first steady frame; when the detected
    steady frame differs from the truth the estimate is re-anchored at the truth's frame.
    """
    steady_true = int(truth["steady_from"])
    T_true = truth["T_w_c"]
    first = max(steady_est, steady_true)
    est = T_w_c[first - steady_est :]
    tru = T_true[first - steady_true :]
    n = min(len(est), len(tru))
    # express both relative to the first shared frame
    est_rel = np.einsum("ij,njk->nik", inv_T(est[0]), est[:n])
    tru_rel = np.einsum("ij,njk->nik", inv_T(tru[0]), tru[:n])
    return np.array([pose_error(a, b) for a, b in zip(est_rel, tru_rel, strict=True)])


def _per_frame_object_errors(
    results: Mapping[str, Any], truth: Mapping[str, Any]
) -> dict[str, float]:
    steady_true = int(truth["steady_from"])
    prop = results["propagate_poses"]
    frames = np.asarray(prop.frame_indices)
    T_obj_true = truth["T_adj"] @ truth["T_w_o_stage1"]
    errs = []
    for f, T_c_o in zip(frames, prop.T_c_o, strict=True):
        i = int(f) - steady_true
        if 0 <= i < len(truth["T_w_c"]):
            errs.append(pose_error(T_c_o, inv_T(truth["T_w_c"][i]) @ T_obj_true))
    if not errs:
        return {}
    e = np.asarray(errs)
    return {
        "frame_object_rot_deg": float(np.median(e[:, 0])),
        "frame_object_trans_mm": 1e3 * float(np.median(e[:, 1])),
        "frame_object_rot_p95_deg": float(np.percentile(e[:, 0], 95)),
        "frame_object_trans_p95_mm": 1e3 * float(np.percentile(e[:, 1], 95)),
    }
