"""Where the wild joints' error comes from: stage 2 re-run on oracle detections (an experiment on
the evidence, not a stage; the truth is used to make the inputs, never by the pipeline).

    .venv/bin/python bench/wild_joint_floor.py --profile wild --seed 16432 --sessions 12 \\
        --frames 40 60 [--root /tmp/floor] [--variants detected truth ...] \\
        [--shares 0.02 0.04 0.06]

Per session (generated under ``--root``, reused when there), the upstream stages
(``load_session``, ``detect_keypoints``, ``select_steady``) run once; then ``joint_solve``,
``reconstruct_hand`` and ``fit_hand`` run on each variant of the detections, with the build's
own configs (``mode = auto``: the staged path where the detections are clean), and stage 2's
joints and cameras are scored as ``bench/accuracy.py`` scores them (``synth.evaluate``); beside
them, each joint triangulated from the same detections with the TRUE cameras and no hand model
(``bench/keypoint_floor.py``'s robust DLT): what the detections carry when the cameras are
perfect:

- ``detected``: the session's detections (what the build sees);
- ``no_gross``: the same without the frames the rig corrupted (a frame whose detections miss
  the true projections by more than 15 % of the hand's image size at the median, or one
  finger by more than 30 %: whole-frame failures, label swaps), set missing: a perfect
  whole-frame rejection;
- ``truth``: the true projections of the rig's joints (``ground_truth/keypoints_clean.npy``,
  lens included) where a detection exists: perfect detections, so what is left is the
  model's capacity (the rig's hand is not the 20-DoF model) and the cameras;
- ``truth_iid``: the true projections plus independent Gaussian noise of the RMS of the
  detections on the frames ``no_gross`` keeps: the detector's noise level without its
  correlation over frames and joints;
- ``truth+S``, one per ``--shares`` value S: the true projections plus independent Gaussian
  noise whose mean per-joint error is S of the hand's image size (the rig's detector: 5-10 %
  on visible joints, twice that on hidden ones, ``docs/synth.md``): how accurate detections
  must be for stage 2 to reach a given joint error;
- ``object_free``: the detections, with the depth refinement's cloud cleared of every point
  within 5 mm of the object's true surface (``hand_sfm.hand_depth.hand_cloud`` patched): a
  perfect hand / object segmentation of the depth.

Prints one line per session and the medians per variant (``docs/benchmarks.md``, "Session
31").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from keypoint_floor import true_camera_errors_mm  # bench/ is the script's directory

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import evaluate, load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.hand_sfm import hand_depth
from graspcap.tasks.hand_sfm.frame_screen import FINGERS
from graspcap.tasks.pipeline import STAGES, _ideal_keypoints, configs_for, run_stage

VARIANTS = ("detected", "no_gross", "truth", "truth_iid", "object_free")
UPSTREAM = ("load_session", "detect_keypoints", "select_steady")
STAGE2 = ("joint_solve", "reconstruct_hand", "fit_hand")
GROSS_MEDIAN, GROSS_FINGER = 0.15, 0.30
"""A frame is gross when its median joint misses by more than this share of the hand's image
size (bounding-box diagonal of the true projections), or one finger's mean by more."""
OBJECT_CUT_M = 0.005


def gross_frames(kp: np.ndarray, clean: np.ndarray) -> np.ndarray:
    """(n,) bool: frames whose detections ``kp`` (n, 21, 3) the rig corrupted, judged against
    the true projections ``clean`` (n, 21, 2)."""
    seen = kp[..., 2] > 0
    err = np.where(seen, np.linalg.norm(kp[..., :2] - clean, axis=2), np.nan)
    size = np.linalg.norm(np.ptp(clean, axis=1), axis=1)
    with warnings.catch_warnings():  # frames or fingers without a detection: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(np.where(seen.any(1)[:, None], err, 0.0), axis=1) / size
        finger = np.stack([np.nanmean(err[:, list(f)], axis=1) for f in FINGERS], 1)
        worst = np.nanmax(np.nan_to_num(finger, nan=0.0), axis=1) / size
    return seen.any(1) & ((median > GROSS_MEDIAN) | (worst > GROSS_FINGER))


def variant_keypoints(name: str, kp: np.ndarray, clean: np.ndarray, rng: np.random.Generator
                      ) -> np.ndarray:
    """The detections (n, 21, 3) of variant ``name`` (see the module docstring)."""
    seen = kp[..., 2] > 0
    gross = gross_frames(kp, clean)
    out = kp.copy()
    if name == "no_gross":
        out[gross, :, 2] = 0.0
    elif name.startswith("truth"):
        out[..., :2] = np.where(seen[..., None], clean, kp[..., :2])
        if name.startswith("truth+"):  # a 2-D Gaussian's mean length is sigma sqrt(pi / 2)
            size = np.linalg.norm(np.ptp(clean, axis=1), axis=1)[:, None, None]
            sigma = float(name[len("truth+"):].rstrip("%")) / 100 * size / np.sqrt(np.pi / 2)
            out[..., :2] += np.where(seen[..., None], rng.normal(size=out[..., :2].shape) * sigma,
                                     0.0)
        elif name == "truth_iid":
            keep = seen & ~gross[:, None]
            rms = float(np.sqrt(np.mean(np.sum((kp[..., :2] - clean)[keep] ** 2, axis=1))))
            noise = rng.normal(0.0, rms / np.sqrt(2.0), out[..., :2].shape)
            out[..., :2] += np.where(seen[..., None], noise, 0.0)
    return out


class ObjectFreeCloud:
    """``hand_depth.hand_cloud`` without the points near the object's true surface, while
    active (a context manager around one stage-2 run)."""

    def __init__(self, session_dir: Path, truth: dict[str, Any]):
        import open3d as o3d
        import trimesh

        manifest = json.loads((session_dir / "session.json").read_text())
        mesh = trimesh.load(session_dir / manifest["object_mesh"], process=False)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        self.truth = truth
        self.original = hand_depth.hand_cloud

    def cloud(self, depth_frame, K, first_frame, rows, T_w_c, joints_w, T_ct, cfg):
        import open3d as o3d

        truth, steady = self.truth, int(self.truth["steady_from"])
        T_w_o = truth["T_adj"] @ truth["T_w_o_stage1"]
        out = []
        for row in rows:
            pts = self.original(depth_frame, K, first_frame, np.array([row]), T_w_c, joints_w,
                                T_ct, cfg)
            i = first_frame + int(row) - steady
            if len(pts) and 0 <= i < len(truth["T_w_c"]):
                T_o_c = inv_T(inv_T(truth["T_w_c"][i]) @ T_w_o)
                p_o = transform_points(T_o_c @ inv_T(T_w_c[row]), pts).astype(np.float32)
                d = self.scene.compute_distance(o3d.core.Tensor(p_o)).numpy()
                pts = pts[d > OBJECT_CUT_M]
            out.append(pts)
        return np.concatenate(out) if out else np.zeros((0, 3))

    def __enter__(self):
        hand_depth.hand_cloud = self.cloud

    def __exit__(self, *exc):
        hand_depth.hand_cloud = self.original


def triangulated_mm(upstream: dict[str, Any], kp: np.ndarray, truth: dict[str, Any]) -> float:
    """Mean joint error (mm) of the joints triangulated from detections ``kp`` with the true
    cameras of the steady frames (no hand model, no frame rejection)."""
    ideal = _ideal_keypoints(upstream["load_session"], kp)
    errors = true_camera_errors_mm(ideal, upstream["load_session"].color_K, truth)
    return float(np.mean(errors)) if len(errors) else float("nan")


def stage2(session_dir: Path, upstream: dict[str, Any], kp: np.ndarray,
           configs: dict[str, Any]) -> dict[str, float]:
    """Stage 2 and the hand fit on detections ``kp``, scored against the truth."""
    res = dict(upstream)
    res["detect_keypoints"] = dataclasses.replace(upstream["detect_keypoints"], keypoints=kp)
    try:
        for name in STAGE2:
            res[name] = run_stage(STAGES[name], session_dir, configs[name], res)
    except StageError as e:
        return {"failed": str(e)}
    rec = res["reconstruct_hand"]
    est = {"steady_from": res["select_steady"].steady_from, "joints_w": rec.joints_w,
           "T_w_c": rec.T_w_c, "camera_solved": rec.pose_valid,
           "joints_fit_w": res["fit_hand"].joints_fit_w}
    m = evaluate(session_dir, est)
    joint = res.get("joint_solve")
    return {"joints_mm": m["joints_mpjpe_mm"], "fit_mm": m.get("fit_joints_mm", np.nan),
            "camera_deg": m["camera_rot_deg"],
            "path": "staged" if joint is None else joint.path}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--profile", default="wild")
    ap.add_argument("--seed", type=int, default=16432)
    ap.add_argument("--sessions", type=int, default=12)
    ap.add_argument("--frames", type=int, nargs="+", default=[40, 60])
    ap.add_argument("--root", type=Path, default=Path("/tmp/wild_joint_floor"))
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    ap.add_argument("--shares", type=float, nargs="*", default=[],
                    help="also the true projections plus iid noise of these mean shares")
    args = ap.parse_args()
    configs = configs_for()
    variants = list(args.variants) + [f"truth+{100 * x:g}%" for x in args.shares]
    table: dict[str, list[dict[str, float]]] = {v: [] for v in variants}
    for i in range(args.sessions):
        frames = args.frames[i % len(args.frames)]
        root = args.root / args.profile
        done = sorted(root.glob(f"synth-s{args.seed}-{i:03d}-*"))
        try:
            d = done[0] if done else generate_session(root, [args.seed, i],
                                                      config_for(args.profile, frames), None)
            upstream: dict[str, Any] = {}
            for name in UPSTREAM:
                upstream[name] = run_stage(STAGES[name], d, configs[name], upstream)
        except StageError as e:
            print(f"[{args.seed}, {i}]: upstream failed ({e})", flush=True)
            continue
        kp = np.asarray(upstream["detect_keypoints"].keypoints, dtype=float)
        clean = np.load(d / "ground_truth" / "keypoints_clean.npy")
        truth = load_truth(d)
        line = f"[{args.seed}, {i}] {frames} fr {d.name.split('-', 3)[-1][:18]:18s}"
        for v in variants:
            keypoints = variant_keypoints(v, kp, clean, np.random.default_rng([args.seed, i]))
            if v == "object_free":
                with ObjectFreeCloud(d, truth):
                    row = stage2(d, upstream, keypoints, configs)
            else:
                row = stage2(d, upstream, keypoints, configs)
            row["triangulated_mm"] = triangulated_mm(upstream, keypoints, truth)
            table[v].append(row)
            line += (f" | {v} failed" if "failed" in row else
                     f" | {v} {row['joints_mm']:5.1f} mm {row['camera_deg']:4.2f} deg "
                     f"{row['path']} (true cameras {row['triangulated_mm']:4.1f})")
        print(line, flush=True)
    print(f"\n{args.profile} [{args.seed}, i] i < {args.sessions}, "
          f"{'/'.join(map(str, args.frames))} frames: stage 2's joints and cameras (medians)\n")
    print("| detections | sessions | SfM joints mm | fitted mm | cameras deg | joint solve | "
          "triangulated, true cameras mm |")
    print("|---|---|---|---|---|---|---|")
    for v, rows in table.items():
        ok = [r for r in rows if "failed" not in r]
        med = {k: np.median([r[k] for r in ok]) if ok else np.nan
               for k in ("joints_mm", "fit_mm", "camera_deg")}
        tri = np.nanmedian([r["triangulated_mm"] for r in rows])
        print(f"| {v} | {len(ok)} of {len(rows)} | {med['joints_mm']:.2f} | {med['fit_mm']:.2f}"
              f" | {med['camera_deg']:.2f} | {sum(r['path'] == 'joint' for r in ok)} | {tri:.2f} |")


if __name__ == "__main__":
    main()
