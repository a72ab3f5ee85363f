"""Compare a session's stage results with its ground truth (synthetic sessions only).

The builder never reads ``ground_truth/``; this module is for the demo, the
accuracy benchmark and tests. Every metric is named with its unit.

Object poses are scored twice: raw (``*_rot_deg``, ``*_trans_mm``: the mesh's origin and full
rotation, the older tables' figures) and symmetry-aware (``*_rot_sym_deg``, ``*_trans_sym_mm``
at the mesh's centroid, ``*_mssd_mm``, ``*_adds_mm``: over the symmetries found in the mesh,
``graspcap.synth.symmetry``), which ``GOOD_IF`` judges. The contact map and the hand in the
object frame are scored in the estimate's own object frame: for a symmetric object the truth is
carried into it by the symmetry the grasp's per-frame poses make of the true ones
(:func:`grasp_symmetry`), so a spin no sensor can see moves neither metric; the hand and the
contact map must still agree with each other. Cameras and joints are scored
relative to one anchor camera (``camera_*_deg``, ``joints_mpjpe_mm``: ``GOOD_IF``'s) and after
one robust rigid alignment of the whole trajectory (``*_aligned_*``,
``graspcap.synth.alignment``), which one bad camera does not move.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.synth.alignment import aligned_errors, aligned_mpjpe_mm
from graspcap.synth.symmetry import (
    closest_symmetry,
    find_symmetries,
    rotation_error_sym_deg,
    surface_scene,
    sym_pose_metrics,
)
from graspcap.tasks.core.geometry import inv_T, make_T, pose_error, transform_points


def load_truth(session_dir: Path) -> dict[str, Any]:
    """``ground_truth/truth.json`` with every ``T_*`` and joint list as numpy arrays."""
    truth = json.loads((Path(session_dir) / "ground_truth" / "truth.json").read_text())
    return {k: np.asarray(v, dtype=float) if isinstance(v, list) else v for k, v in truth.items()}


def _pose_metrics(prefix: str, T_est: np.ndarray, T_true: np.ndarray, object_sym: Any = None
                  ) -> dict[str, float]:
    """Raw rotation / translation error, and given ``(symmetries, scene)`` of the object mesh
    (:func:`_object_symmetries`) the symmetry-aware ones of the object pose."""
    rot_deg, trans_m = pose_error(T_est, T_true)
    out = {f"{prefix}_rot_deg": rot_deg, f"{prefix}_trans_mm": 1e3 * trans_m}
    if object_sym is not None:
        out |= sym_pose_metrics(prefix, T_est, T_true, *object_sym)
    return out


def _object_symmetries(session_dir: Path) -> tuple[Any, Any]:
    """(symmetries, raycasting scene) of the session's object mesh (``session.json``'s
    ``object_mesh``), cached per mesh file."""
    manifest = json.loads((Path(session_dir) / "session.json").read_text())
    path = Path(session_dir) / manifest["object_mesh"]
    return find_symmetries(path), surface_scene(path)


def estimate_from_results(
    results: Mapping[str, Any], timings_s: Mapping[str, float] | None = None
) -> dict[str, Any]:
    """Stage results (by stage name, as ``run_session`` returns them) -> the estimate dict
    :func:`evaluate` takes, keyed by the catalog's column names (plus the refinement's hands
    and, given ``run_session``'s ``timings_s``, its time)."""
    est: dict[str, Any] = {}
    get = results.get
    if get("register_object") is not None:
        est["T_w_o_stage1"] = results["register_object"].T_w_o
    if get("register_scan") is not None:
        est["T_turntable_o_scan"] = results["register_scan"].T_turntable_o_scan
    if get("estimate_adjustment") is not None:
        est["T_adj"] = results["estimate_adjustment"].T_adj
    if get("select_steady") is not None:
        est["steady_from"] = results["select_steady"].steady_from
    if get("reconstruct_hand") is not None:
        rec = results["reconstruct_hand"]
        est |= {
            "joints_w": rec.joints_w,
            "T_w_c": rec.T_w_c,
            "camera_solved": rec.pose_valid,
            "qa_reproj_rmse_px": rec.reproj_rmse_px,
        }
    if get("crosscheck_sfm") is not None:
        est["qa_crosscheck_mm"] = 1e3 * float(results["crosscheck_sfm"].max_joint_discrepancy_m)
    if get("fit_hand") is not None:
        est["joints_fit_w"] = results["fit_hand"].joints_fit_w
    if get("build_contactmap") is not None:
        est |= {"contact": results["build_contactmap"].contact,
                "observed": results["build_contactmap"].observed}
    if get("refine_grasp") is not None and get("estimate_adjustment") is not None:
        est |= _refinement_estimate(results)
        if timings_s is not None and "refine_grasp" in timings_s:
            est["refine_time_s"] = float(timings_s["refine_grasp"])
    if get("propagate_poses") is not None:
        prop = results["propagate_poses"]
        est |= {"frame": np.asarray(prop.frame_indices), "T_c_o": prop.T_c_o,
                "joints_c": prop.joints_c}
        if prop.T_w_c is not None and "T_w_c" in est:
            # the catalog's frames.T_w_c: stage 2's cameras, or where the object was tracked in
            # the frame's depth the camera that tracking defines (as estimate_from_catalog reads)
            est |= {"T_w_c_sfm": est["T_w_c"], "T_w_c": prop.T_w_c}
    return est


def _refinement_estimate(results: Mapping[str, Any]) -> dict[str, Any]:
    """The refined and fit_hand's hands in the object frame, refined joints in the world."""
    ref, fit = results["refine_grasp"], results["fit_hand"]
    hand_fit = fit.mesh()
    T_o_w = inv_T(results["estimate_adjustment"].T_w_o)
    return {
        "hand_vertices_o": ref.hand_vertices_o, "hand_faces": ref.hand_faces,
        "hand_vertices_fit_o": transform_points(T_o_w, hand_fit.vertices),
        "hand_faces_fit": hand_fit.faces, "joints_refined_w": ref.joints_w,
        "penetration_max_mm_fit": ref.before.penetration_max_mm,
        "penetration_max_mm_refined": ref.after.penetration_max_mm,
        "refine_accepted": bool(ref.accepted),
    }  # fmt: skip


def estimate_from_catalog(session: Mapping[str, Any], frames: Any) -> dict[str, Any]:
    """A ``sessions`` row (dict) and that session's ``frames`` rows (a pandas DataFrame) ->
    the estimate dict :func:`evaluate` takes."""

    def mat(v, shape):
        return None if v is None else np.asarray(v, dtype=float).reshape(shape)

    est = {k: mat(session.get(k), (4, 4)) for k in ("T_w_o_stage1", "T_turntable_o_scan", "T_adj")}
    est |= {k: mat(session.get(k), (21, 3)) for k in ("joints_w", "joints_fit_w")}
    est |= {k: session.get(k) for k in ("steady_from", "qa_reproj_rmse_px", "qa_crosscheck_mm")}
    frames = frames.sort_values("frame")
    est["frame"] = frames["frame"].to_numpy()
    est["T_w_c"] = np.stack([mat(v, (4, 4)) for v in frames["T_w_c"]])
    est["T_c_o"] = np.stack([mat(v, (4, 4)) for v in frames["T_c_o"]])
    if "joints_c" in frames and not frames["joints_c"].isna().any():
        est["joints_c"] = np.stack([mat(v, (21, 3)) for v in frames["joints_c"]])
    # null in a catalog written before format 4: unknown which cameras reconstruct_hand solved
    solved = frames["camera_solved"] if "camera_solved" in frames else None
    if solved is not None and not solved.isna().any():
        est["camera_solved"] = solved.to_numpy(dtype=bool)
    return {k: v for k, v in est.items() if v is not None}


def evaluate(session_dir: Path, est: Mapping[str, Any]) -> dict[str, float]:
    """Errors of an estimate against the session's ground truth.

    ``est`` is keyed by the catalog's column names (see :func:`estimate_from_results`,
    :func:`estimate_from_catalog`); what it lacks gives no metric.
    """
    truth = load_truth(session_dir)
    out: dict[str, float] = {}
    object_sym = (_object_symmetries(session_dir)
                  if any(k in est for k in ("T_w_o_stage1", "T_turntable_o_scan", "T_adj", "T_c_o"))
                  else None)  # fmt: skip
    for key, prefix in (
        ("T_w_o_stage1", "object_stage1"),
        ("T_turntable_o_scan", "object_scan"),
    ):
        if key in est:
            out |= _pose_metrics(prefix, est[key], truth[key], object_sym)
    if "T_adj" in est:  # against the frame the pipeline was given as the first steady one
        steady = est.get("steady_from")
        T_adj_true = truth["T_adj"] if steady is None else _T_adj_at(truth, int(steady))
        out |= _pose_metrics("T_adj", est["T_adj"], T_adj_true)
        # symmetry-aware: the object pose each T_adj makes of the true stage-1 pose
        T1 = truth["T_w_o_stage1"]
        out |= sym_pose_metrics("T_adj", est["T_adj"] @ T1, T_adj_true @ T1, *object_sym)
    S = (grasp_symmetry(est["frame"], est["T_c_o"], truth, object_sym[0])
         if object_sym is not None and "T_c_o" in est else None)
    if "contact" in est:
        out |= _contact_metrics(est["contact"], est["observed"], session_dir, S)
    if "hand_vertices_o" in est:
        out |= _refinement_metrics(est, session_dir, S)
    if "steady_from" not in est:
        return out
    steady_est = int(est["steady_from"])
    out["steady_from_err_frames"] = float(abs(steady_est - int(truth["steady_from"])))
    if "joints_w" in est:
        solved = est.get("camera_solved")
        at = _anchor(steady_est, int(truth["steady_from"]), len(est["T_w_c"]),
                     None if solved is None else np.asarray(solved, dtype=bool))
        for key, prefix in (("T_w_c", ""), ("T_w_c_sfm", "sfm_")):
            if key not in est:
                continue
            out[f"{prefix}joints_mpjpe_mm"] = _mpjpe_mm(est["joints_w"], est[key], steady_est,
                                                        truth, at)
            cams = _camera_errors(est[key], steady_est, truth, at)
            out[f"{prefix}camera_rot_deg"] = float(np.median(cams[:, 0]))
            out[f"{prefix}camera_trans_mm"] = 1e3 * float(np.median(cams[:, 1]))
            hands = {} if prefix else {
                name: est[k] for k, name in (("joints_w", "joints"),
                                             ("joints_fit_w", "fit_joints"),
                                             ("joints_refined_w", "refined_joints"))
                if k in est}  # fmt: skip
            out |= _aligned_metrics(prefix, est[key], steady_est, truth, hands)
    if "joints_fit_w" in est:
        out["fit_joints_mm"] = _mpjpe_mm(est["joints_fit_w"], est["T_w_c"], steady_est, truth, at)
    if "joints_refined_w" in est:
        out["refined_joints_mm"] = _mpjpe_mm(est["joints_refined_w"], est["T_w_c"], steady_est,
                                             truth, at)
    for key, name in (
        ("qa_reproj_rmse_px", "reproj_rmse_px"),
        ("qa_crosscheck_mm", "crosscheck_max_mm"),
    ):
        if est.get(key) is not None:
            out[name] = float(est[key])
    if "T_c_o" in est:
        out |= _per_frame_object_errors(est["frame"], est["T_c_o"], truth, object_sym)
    if "joints_c" in est:
        out |= _per_frame_joint_errors(est["frame"], est["joints_c"], truth)
    return out


def grasp_symmetry(frames: np.ndarray, T_c_o: np.ndarray, truth: Mapping[str, Any],
                   sym: Any) -> np.ndarray | None:
    """The object symmetry (4, 4; about the centroid) that carries the estimate's object frame
    into the truth's, as the grasp's per-frame poses ``T_c_o`` (m, 4, 4) make it: that of the
    steady frame whose symmetry-aware rotation error is the median (a frame of the estimate,
    ``x``, is ``S x`` of the truth). None where the mesh has no symmetry but the identity, no
    steady frame pairs with the truth, or the closest element is the identity."""
    if sym is None or not (sym.sphere or sym.axis is not None or len(sym.discrete) > 1):
        return None
    pairs = [(rotation_error_sym_deg(T, T_true, sym), T, T_true)
             for T, T_true in _true_object_poses(frames, T_c_o, truth)]
    if not pairs:
        return None
    _, T, T_true = sorted(pairs, key=lambda p: p[0])[len(pairs) // 2]
    R = closest_symmetry(T, T_true, sym)
    if np.allclose(R, np.eye(3), atol=1e-9):
        return None
    c = sym.centroid
    return make_T(R, c - R @ c)


def _contact_metrics(contact: np.ndarray, observed: np.ndarray, session_dir: Path,
                     S: np.ndarray | None = None) -> dict[str, float]:
    """MAE on observed vertices, IoU of contact > 0.4, share of truly contacted (> 0.4)
    vertices that were observed; the truth of each vertex taken at its image under the
    symmetry ``S`` (:func:`grasp_symmetry`; the nearest vertex), where given."""
    truth = np.load(Path(session_dir) / "ground_truth" / "contact.npy")
    if S is not None:
        truth = truth[_symmetric_vertices(session_dir, S)]
    observed = np.asarray(observed, dtype=bool)
    est_on, true_on = (contact > 0.4) & observed, (truth > 0.4) & observed
    union = (est_on | true_on).sum()
    return {
        "contact_mae": float(np.abs(contact[observed] - truth[observed]).mean()),
        "contact_iou": float((est_on & true_on).sum() / union) if union else 1.0,
        "contact_seen_share": float(observed[truth > 0.4].mean()) if (truth > 0.4).any() else 1.0,
    }


def _mesh_vertices(session_dir: Path) -> np.ndarray:
    import trimesh

    manifest = json.loads((Path(session_dir) / "session.json").read_text())
    mesh = trimesh.load(Path(session_dir) / manifest["object_mesh"], force="mesh", process=False)
    return np.asarray(mesh.vertices, dtype=float)


def _symmetric_vertices(session_dir: Path, S: np.ndarray) -> np.ndarray:
    """(n,) index of the vertex nearest each vertex's image under ``S`` (4, 4)."""
    from scipy.spatial import cKDTree

    V = _mesh_vertices(session_dir)
    return cKDTree(V).query(transform_points(S, V))[1]


def _refinement_metrics(est: Mapping[str, Any], session_dir: Path,
                        S: np.ndarray | None = None, near_mm: float = 3.0) -> dict[str, float]:
    """Share of truly contacted (> 0.4) vertices within ``near_mm`` of the refined and of the
    fit_hand's hand mesh (unsigned distance to the surface), penetration max before and after,
    and the refinement time when the estimate has it; the contacted vertices carried into the
    estimate's frame by the inverse of the symmetry ``S`` (:func:`grasp_symmetry`), where
    given."""
    import open3d as o3d

    truth = np.load(Path(session_dir) / "ground_truth" / "contact.npy")
    touched = _mesh_vertices(session_dir)[truth > 0.4]
    if S is not None:
        touched = transform_points(inv_T(S), touched)
    touched = touched.astype(np.float32)
    out: dict[str, float] = {}
    for key, faces, name in (("hand_vertices_o", "hand_faces", "refined"),
                             ("hand_vertices_fit_o", "hand_faces_fit", "fit")):
        if key not in est or not len(touched):
            continue
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(np.asarray(est[key], np.float32), np.asarray(est[faces], np.uint32))
        d_mm = 1e3 * scene.compute_distance(o3d.core.Tensor(touched)).numpy()
        out[f"contact_near_hand_{name}"] = float(np.mean(d_mm <= near_mm))
    for key in ("penetration_max_mm_fit", "penetration_max_mm_refined", "refine_time_s"):
        if est.get(key) is not None:
            out[key] = float(est[key])
    if "refine_accepted" in est:
        out["refine_accepted"] = float(est["refine_accepted"])
    return out


def _T_adj_at(truth: Mapping[str, Any], steady_est: int) -> np.ndarray:
    """The true ``T_adj`` as the pipeline defines it when it is given ``steady_est`` as the
    first steady frame: the object's motion from register_object's pose to its pose in that frame.
    After the true onset the object moves with the hand (``truth["T_w_c"]``); before it, the truth
    holds no per-frame pose, and the onset's is used (the object has nearly settled there)."""
    i = steady_est - int(truth["steady_from"])
    if i <= 0 or i >= len(truth["T_w_c"]):
        return truth["T_adj"]
    T_c_o = inv_T(truth["T_w_c"][i]) @ truth["T_adj"] @ truth["T_w_o_stage1"]
    return T_c_o @ inv_T(truth["T_w_o_stage1"])


def _anchor(steady_est: int, steady_true: int, n_est: int, solved: np.ndarray | None) -> int:
    """Video frame both reconstructions are compared in: the first frame from both first
    steady frames on whose camera the estimate solved from the frame's own keypoints. Each
    world frame is its own first steady camera; when the detected steady frame differs from the
    truth the estimate is re-anchored, and never on a camera reconstruct_hand only interpolated (a
    frame without detections): that camera is a fill, and every camera measured against it would
    carry its error."""
    first = max(steady_est, steady_true)
    if solved is not None:
        later = np.flatnonzero(solved[first - steady_est :])
        if len(later):
            first += int(later[0])
    return min(first, steady_est + n_est - 1)


def _mpjpe_mm(
    joints_w: np.ndarray, T_w_c: np.ndarray, steady_est: int, truth: Mapping[str, Any],
    at: int,
) -> float:
    """Mean joint error in mm, no alignment, compared in the camera of video frame ``at``
    (:func:`_anchor`)."""
    steady_true = int(truth["steady_from"])
    est = transform_points(inv_T(T_w_c[at - steady_est]), joints_w)
    tru = transform_points(inv_T(truth["T_w_c"][at - steady_true]), truth["joints_w"])
    return 1e3 * float(np.linalg.norm(est - tru, axis=1).mean())


def _camera_errors(
    T_w_c: np.ndarray, steady_est: int, truth: Mapping[str, Any], at: int
) -> np.ndarray:
    """(k, 2) rotation deg / translation m of the virtual cameras of the frames both cover
    from video frame ``at`` (:func:`_anchor`) on, each reconstruction expressed relative to its
    camera at ``at``. Interpolated cameras after it count (they are in the output)."""
    steady_true = int(truth["steady_from"])
    est = T_w_c[at - steady_est :]
    tru = truth["T_w_c"][at - steady_true :]
    n = min(len(est), len(tru))
    est_rel = np.einsum("ij,njk->nik", inv_T(est[0]), est[:n])
    tru_rel = np.einsum("ij,njk->nik", inv_T(tru[0]), tru[:n])
    return np.array([pose_error(a, b) for a, b in zip(est_rel, tru_rel, strict=True)])


def _aligned_metrics(prefix: str, T_w_c: np.ndarray, steady_est: int,
                     truth: Mapping[str, Any], hands: Mapping[str, np.ndarray]
                     ) -> dict[str, float]:
    """Anchor-free errors (``graspcap.synth.alignment``): the cameras of every frame both
    cover aligned to the truth by one robust rigid transform; ``{prefix}camera_rot_aligned_deg``
    and ``{prefix}camera_trans_aligned_mm`` (medians over the frames) and, for each of
    ``hands`` (name -> (21, 3) joints in the estimate's world), ``{prefix}{name}_aligned_mm``
    (``joints`` -> ``joints_aligned_mm``), the joints mapped by the same transform."""
    steady_true = int(truth["steady_from"])
    first = max(steady_est, steady_true)
    est = np.asarray(T_w_c)[first - steady_est:]
    tru = np.asarray(truth["T_w_c"])[first - steady_true:]
    n = min(len(est), len(tru))
    if n == 0:
        return {}
    A, cams = aligned_errors(est[:n], tru[:n])
    out = {f"{prefix}camera_rot_aligned_deg": float(np.median(cams[:, 0])),
           f"{prefix}camera_trans_aligned_mm": 1e3 * float(np.median(cams[:, 1]))}
    for name, joints in hands.items():
        out[f"{prefix}{name}_aligned_mm"] = aligned_mpjpe_mm(joints, truth["joints_w"], A)
    return out


def _true_object_poses(frames: np.ndarray, T_c_o: np.ndarray, truth: Mapping[str, Any]
                       ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(estimated, true) object pose in the camera of each of ``frames`` that lies in the
    truth's steady window (``T_c_o`` (m, 4, 4), one per frame)."""
    steady_true = int(truth["steady_from"])
    T_obj_true = truth["T_adj"] @ truth["T_w_o_stage1"]
    for f, T in zip(np.asarray(frames), np.asarray(T_c_o), strict=True):
        i = int(f) - steady_true
        if 0 <= i < len(truth["T_w_c"]):
            yield T, inv_T(truth["T_w_c"][i]) @ T_obj_true


def _per_frame_object_errors(
    frames: np.ndarray, T_c_o: np.ndarray, truth: Mapping[str, Any], object_sym: Any = None
) -> dict[str, float]:
    """The object pose in each steady frame's camera (``frames.T_c_o``) against the truth:
    median and p95 over the frames of the raw errors and, given ``(symmetries, scene)``
    (:func:`_object_symmetries`), the median and p95 of the symmetry-aware rotation and
    centroid errors and the median MSSD and ADD-S."""
    errs, sym = [], []
    for T, T_true in _true_object_poses(frames, T_c_o, truth):
        errs.append(pose_error(T, T_true))
        if object_sym is not None:
            sym.append(sym_pose_metrics("", T, T_true, *object_sym))
    if not errs:
        return {}
    e = np.asarray(errs)
    out = {
        "frame_object_rot_deg": float(np.median(e[:, 0])),
        "frame_object_trans_mm": 1e3 * float(np.median(e[:, 1])),
        "frame_object_rot_p95_deg": float(np.percentile(e[:, 0], 95)),
        "frame_object_trans_p95_mm": 1e3 * float(np.percentile(e[:, 1], 95)),
    }
    for name in (sym[0] if sym else {}):
        v = [m[name] for m in sym]
        out[f"frame_object{name}"] = float(np.median(v))
        if name in ("_rot_sym_deg", "_trans_sym_mm"):
            unit = name.rsplit("_", 1)[1]
            out[f"frame_object{name[: -len(unit) - 1]}_p95_{unit}"] = float(np.percentile(v, 95))
    return out


def _per_frame_joint_errors(
    frames: np.ndarray, joints_c: np.ndarray, truth: Mapping[str, Any]
) -> dict[str, float]:
    """The hand as delivered in each steady frame's camera (``frames.joints_c``: the static
    joints carried by that frame's camera) against the truth: the median and p90 over frames of
    the mean joint error, mm."""
    steady_true = int(truth["steady_from"])
    errs = []
    for f, J in zip(np.asarray(frames), np.asarray(joints_c), strict=True):
        i = int(f) - steady_true
        if 0 <= i < len(truth["T_w_c"]):
            J_true = transform_points(inv_T(truth["T_w_c"][i]), truth["joints_w"])
            errs.append(np.linalg.norm(J - J_true, axis=1).mean())
    if not errs:
        return {}
    return {"frame_joints_mm": 1e3 * float(np.median(errs)),
            "frame_joints_p90_mm": 1e3 * float(np.percentile(errs, 90))}


GOOD_IF: dict[str, tuple[float, str]] = {
    "final_joints_mm": (5.0, "<="),
    "camera_rot_deg": (1.0, "<="),
    "camera_trans_mm": (8.0, "<="),
    "frame_object_rot_sym_deg": (2.0, "<="),
    "frame_object_trans_sym_mm": (6.0, "<="),
    "object_stage1_rot_sym_deg": (2.0, "<="),
    "contact_near_hand_refined": (0.8, ">="),
}
"""What a *good* session is (``docs/qa.md``): every error against the truth within its
tolerance. ``final_joints_mm`` is the hand the catalog holds (refined, else fitted), the poses
are medians over the session's frames, the object's symmetry-aware (a spin no sensor can see is
no error: BOP's convention; the per-frame translation is the centroid's),
``contact_near_hand_refined`` the share of truly contacted vertices within 3 mm of that hand
(which still catches a wrong spin where it moves the contact)."""


def misses(errors: Mapping[str, float], stage_error: str | None = None
           ) -> list[tuple[str, str]]:
    """Why a session is not good by :data:`GOOD_IF`, as (quantity, reason) pairs; empty when
    it is good. A session a stage refused misses ``("stage failed", ...)``; a quantity that
    could not be measured is a miss too."""
    if stage_error:
        return [("stage failed", f"stage failed: {stage_error}")]
    errors = dict(errors)
    final = errors.get("refined_joints_mm", errors.get("fit_joints_mm"))
    if final is not None:
        errors["final_joints_mm"] = final
    out = []
    for name, (limit, op) in GOOD_IF.items():
        value = errors.get(name)
        if value is None or not np.isfinite(value):
            out.append((name, f"{name} not measured"))
        elif not (value <= limit if op == "<=" else value >= limit):
            out.append((name, f"{name} {value:.2f} (good {op} {limit:g})"))
    return out


def good_session(errors: Mapping[str, float], stage_error: str | None = None
                 ) -> tuple[bool, str]:
    """(whether the session is good by :data:`GOOD_IF`, why not): :func:`misses` joined."""
    why = misses(errors, stage_error)
    return not why, "; ".join(text for _, text in why)


def qa_confusion(rows: list[tuple[bool, str]]) -> dict[str, Any]:
    """The QA confusion table of (good, verdict) pairs: counts per (good / not good) x (ok /
    flagged / failed), **precision** (share of ``ok`` sessions that are good) and **yield**
    (share of good sessions marked ``ok``); None where the denominator is 0."""
    table = {g: {v: 0 for v in ("ok", "flagged", "failed")} for g in ("good", "not good")}
    for good, verdict in rows:
        table["good" if good else "not good"][verdict] += 1
    ok = table["good"]["ok"] + table["not good"]["ok"]
    good = sum(table["good"].values())
    return {"table": table,
            "precision": table["good"]["ok"] / ok if ok else None,
            "yield": table["good"]["ok"] / good if good else None}


def confusion_markdown(confusion: Mapping[str, Any]) -> str:
    """:func:`qa_confusion` as a markdown table and a line with precision and yield."""
    t = confusion["table"]
    lines = ["| truth \\ QA | ok | flagged | failed | sessions |", "|---|---|---|---|---|"]
    for g in ("good", "not good"):
        lines.append(f"| {g} | {t[g]['ok']} | {t[g]['flagged']} | {t[g]['failed']} "
                     f"| {sum(t[g].values())} |")

    def share(x: float | None) -> str:
        return "-" if x is None else f"{x:.2f}"

    lines.append(f"\nprecision (good among ok) {share(confusion['precision'])}, "
                 f"yield (ok among good) {share(confusion['yield'])}")
    return "\n".join(lines)
