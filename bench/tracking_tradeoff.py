"""What the per-frame object tracking does to the hand in each frame, and two ways of
re-estimating the hand-object relation from the tracked frames (an experiment, not a stage).

    .venv/bin/python bench/tracking_tradeoff.py --profile real-detector --seed 9700 \
        --sessions 6 --frames 60 [--root /tmp/tradeoff]

``propagate_poses`` tracks the object in each steady frame's depth and, where it keeps the
tracked pose, defines that frame's camera from it: ``T_w_c = T_w_o @ inv(T_c_o_tracked)``. The
object in the frame is then as the depth says, and the hand is carried by that camera, so any
error of ``T_w_o`` (``estimate_adjustment``: the object in the hand's world) moves the hand in
every tracked frame. Per session this prints the hand's mean joint error in each steady frame's
camera (median over frames) carried by stage 2's cameras and by the delivered ones, and what it
would be with ``T_w_o`` re-estimated from the tracked frames:

- ``average``: the robust mean over tracked frames of ``T_w_c_stage2[i] @ T_c_o_tracked[i]``
  (each frame measures the object in the hand's world through its stage 2 camera): what
  ``estimate_adjustment/18`` does (``tracked_average``), so on results of that code the
  delivered column already has it;
- ``keypoints``: the rigid correction of the hand's joints in the object frame that best
  reprojects them, carried by each tracked object pose, onto the detected keypoints (Cauchy
  loss, frames no pose explains dropped, one refit).

Moving ``T_w_o`` after ``refine_grasp`` would break the grasp's consistency (the hand in the
object frame), so the mean is taken in ``estimate_adjustment``; the keypoint estimate is not
in the pipeline (one session of five 7.5 -> 18.7 mm: a large hand's 28 px keypoint noise).
Sessions run bare (``run_session``, default configs) and their results are cached under
``--root`` (``results.pkl``).
"""

from __future__ import annotations

import argparse
import pickle
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import from_rotvec, inv_T, transform_points
from graspcap.tasks.object_pose.tracked_average import average_object_pose
from graspcap.tasks.pipeline import _ideal_keypoints, _load, configs_for, run_session


def results_for(d: Path) -> dict | None:
    """``run_session``'s results for session ``d`` (cached; None where a stage refused)."""
    cache = d / "results.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    try:
        res = run_session(d)
        res.pop("pictures", None)
    except StageError as e:
        print(f"| {d.name} | failed: {e.stage}: {str(e.reason)[:80]} |", flush=True)
        res = None
    cache.write_bytes(pickle.dumps(res))
    return res


def average_T_w_o(T_w_c: np.ndarray, T_c_o: np.ndarray, centre_o: np.ndarray) -> np.ndarray:
    """(4, 4) the robust mean of the per-frame object poses in the world ``T_w_c[i] @ T_c_o[i]``
    (``estimate_adjustment``'s :func:`tracked_average.average_object_pose`, every frame given
    as tracked)."""
    out = average_object_pose(T_w_c, T_c_o, np.ones(len(T_w_c), bool), centre_o)
    return out.T_w_o if out.T_w_o is not None else np.full((4, 4), np.nan)


def keypoint_correction(T_c_o: np.ndarray, keypoints: np.ndarray, K: np.ndarray,
                        joints_o: np.ndarray, min_confidence: float = 0.3) -> np.ndarray:
    """(4, 4) rigid motion ``A`` of the hand's joints in the object frame (``joints_o`` (21, 3))
    such that ``A @ joints_o`` carried by every ``T_c_o`` (m, 4, 4) best reprojects onto
    ``keypoints`` (m, 21, 3: ideal pixels, confidence)."""
    from scipy.optimize import least_squares

    seen = np.isfinite(keypoints).all(2) & (np.nan_to_num(keypoints[..., 2]) >= min_confidence)
    centre = joints_o.mean(axis=0)

    def moved(x: np.ndarray) -> np.ndarray:
        return (joints_o - centre) @ from_rotvec(x[:3], np.zeros(3))[:3, :3].T + centre + x[3:]

    def residuals(x: np.ndarray, sigma: float, use: np.ndarray) -> np.ndarray:
        J_c = np.einsum("mij,nj->mni", T_c_o[:, :3, :3], moved(x)) + T_c_o[:, None, :3, 3]
        h = J_c @ K.T
        r = (h[..., :2] / h[..., 2:] - np.nan_to_num(keypoints[..., :2])) / sigma
        return np.where((seen & use[:, None])[..., None], r, 0.0).ravel()

    def per_joint(x: np.ndarray, use: np.ndarray) -> np.ndarray:
        return np.linalg.norm(residuals(x, 1.0, use).reshape(len(T_c_o), 21, 2), axis=2)

    use = np.ones(len(T_c_o), bool)
    sigma = max(float(np.median(per_joint(np.zeros(6), use)[seen])) / 1.177, 1.0)
    x = least_squares(residuals, np.zeros(6), args=(sigma, use), loss="cauchy", f_scale=2.0).x
    e = per_joint(x, use)
    frame_err = np.array([np.median(e[i][seen[i]]) if seen[i].sum() >= 6 else np.inf
                          for i in range(len(T_c_o))])  # fmt: skip
    use = frame_err < 3 * np.median(frame_err[np.isfinite(frame_err)])
    x = least_squares(residuals, x, args=(sigma, use), loss="cauchy", f_scale=2.0).x
    A = from_rotvec(x[:3], np.zeros(3))
    A[:3, 3] = centre - A[:3, :3] @ centre + x[3:]
    return A


def session_row(d: Path, res: dict) -> str:
    truth = load_truth(d)
    s = int(truth["steady_from"])
    prop, rec = res["propagate_poses"], res["reconstruct_hand"]
    T_w_o = res["estimate_adjustment"].T_w_o
    tracked = np.asarray(prop.tracking.tracked, bool)
    joints_w = transform_points(prop.T_w_c[0], prop.joints_c[0])  # the joints propagate carried
    T_c_o = np.asarray(prop.tracking.T_c_o)

    def hand_error_mm(T_w_c: np.ndarray) -> float:
        errs = []
        for k, f in enumerate(prop.frame_indices):
            i = int(f) - s
            if 0 <= i < len(truth["T_w_c"]):
                J_true = transform_points(inv_T(truth["T_w_c"][i]), truth["joints_w"])
                J = transform_points(inv_T(T_w_c[k]), joints_w)
                errs.append(1e3 * np.linalg.norm(J - J_true, axis=1).mean())
        return float(np.median(errs))

    def cameras(T_w_o_: np.ndarray) -> np.ndarray:
        out = np.array(prop.T_w_c)
        out[tracked] = T_w_o_ @ np.stack([inv_T(T) for T in T_c_o[tracked]])
        return out

    row = (f"| {d.name} | {tracked.sum()} / {len(tracked)} | {hand_error_mm(rec.T_w_c):.1f} "
           f"| {hand_error_mm(prop.T_w_c):.1f} ")
    if tracked.sum() < 5:
        return row + "| - | - |"
    session = _load(d, configs_for()["load_session"])
    keypoints = _ideal_keypoints(session, res["detect_keypoints"].keypoints[prop.frame_indices])
    T_avg = average_T_w_o(np.asarray(rec.T_w_c)[tracked], T_c_o[tracked],
                          np.asarray(session.read_mesh()[0], float).mean(axis=0))
    A = keypoint_correction(T_c_o[tracked], keypoints[tracked], session.color_K,
                            transform_points(inv_T(T_w_o), joints_w))
    return row + (f"| {hand_error_mm(cameras(T_avg)):.1f} "
                  f"| {hand_error_mm(cameras(T_w_o @ inv_T(A))):.1f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--profile", default="real-detector")
    p.add_argument("--seed", type=int, default=9700)
    p.add_argument("--sessions", type=int, default=6)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--root", type=Path, default=Path("/tmp/tradeoff"))
    args = p.parse_args()
    print("per-frame hand: mean joint error in each steady frame's camera, median over frames, "
          "mm\n")
    print("| session | tracked / frames | stage 2 cameras | delivered (tracked) | T_w_o average "
          "| T_w_o from keypoints |")
    print("|---|---|---|---|---|---|")
    for i in range(args.sessions):
        try:
            d = generate_session(args.root / args.profile, [args.seed, i],
                                 config_for(args.profile, args.frames), None)
        except StageError:
            print(f"| [{args.seed}, {i}] | the rig could not stage it |")
            continue
        res = results_for(d)
        if res is not None:
            print(session_row(d, res), flush=True)


if __name__ == "__main__":
    main()
