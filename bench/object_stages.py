"""The object stages alone on synthetic sessions: register_object, estimate_adjustment and
register_scan against the written truth, per session and summarised.

    .venv/bin/python bench/object_stages.py --profile wild-nodet --seed 9700 --sessions 12 \
        --frames 40 [--upstream pipeline|truth] [--root /tmp/objbench]

``wild-nodet`` is the wild profile with the real-detector keypoint model off
(``PRESETS["wild"].model_copy(update={"detector": None})``: wild hands, cameras at 0.6-1.0 m,
lens, wild objects, Kinect v2 depth, ``synth/2``'s keypoint noise), so that stage 2 builds
and the object stages are what is measured; any other name is a ``graspcap.synth`` profile.
Sessions are generated once under ``--root`` and reused. With ``--upstream pipeline`` the
stages before estimate_adjustment run as in a build (their results cached under ``--root``
beside the session: only the object stages rerun); ``--upstream truth`` hands
estimate_adjustment the written truth instead (onset, virtual cameras, the hand fitted to
the true joints), which isolates the object stage from stage 2. Per-frame object errors:
``propagate_poses`` with the pipeline upstream, the estimated object pose carried by the
true cameras with the truth upstream.
"""

from __future__ import annotations

import argparse
import pickle
import time
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from graspcap.synth import PRESETS, SynthConfig, generate_session
from graspcap.synth.evaluate import evaluate, load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, pose_error
from graspcap.tasks.hand import fit_hand
from graspcap.tasks.hand.model import HandSide
from graspcap.tasks.object_pose import adjustment_steady
from graspcap.tasks.pipeline import STAGES, _ideal_keypoints, configs_for, run_stage

UPSTREAM = ("load_session", "detect_keypoints", "select_steady", "reconstruct_hand",
            "crosscheck_sfm", "fit_hand")  # fmt: skip


def synth_config(profile: str, frames: int) -> SynthConfig:
    """The profile's preset with ``frames``; ``wild-nodet`` is wild without the real detector."""
    if profile == "wild-nodet":
        base, update = PRESETS["wild"], {"detector": None}
    else:
        base, update = PRESETS[profile], {}
    return SynthConfig.model_validate({**base.model_dump(), **update, "frames": int(frames)})


def session_dir(root: Path, profile: str, seed: int, i: int, frames: int) -> Path | None:
    """Session ``[seed, i]`` under ``root/profile-frames``, generated when missing."""
    out = root / f"{profile}-{frames}"
    found = sorted(out.glob(f"synth-s{seed}-{i:03d}-*")) if out.exists() else []
    if found:
        return found[0]
    try:
        return generate_session(out, [seed, i], synth_config(profile, frames), None)
    except StageError:
        return None


def upstream(d: Path, configs: dict) -> dict[str, Any]:
    """The stages before the object ones, as a build runs them (cached in ``d``), or the
    stage's failure under ``"failed"``."""
    cache = d / "bench_upstream.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    results: dict[str, Any] = {}
    times: dict[str, float] = {}
    try:
        for name in UPSTREAM:
            t0 = time.process_time()
            results[name] = run_stage(STAGES[name], d, configs[name], results)
            times[name] = time.process_time() - t0
    except StageError as e:
        results["failed"] = f"{e.stage}: {e.reason[:90]}"
    results["times"] = times
    cache.write_bytes(pickle.dumps(results))
    return results


def run_one(d: Path, configs: dict, mode: str) -> dict[str, Any]:
    """Every object stage of session ``d``: errors, times, failures."""
    out: dict[str, Any] = {"name": d.name, "failed": {}, "times": {}, "err": {}}
    truth = load_truth(d)
    up = {"load_session": run_stage(STAGES["load_session"], d, configs["load_session"], {})}
    for name in ("register_object", "register_scan"):
        t0 = time.process_time()
        try:
            up[name] = run_stage(STAGES[name], d, configs[name], up)
        except StageError as e:
            out["failed"][name] = e.reason[:90]
        out["times"][name] = time.process_time() - t0
    V = up["load_session"].read_mesh()[0]
    pts_o = V[:: max(1, len(V) // 2000)]
    out["adds"] = {}
    if "register_object" in up:
        r = up["register_object"]
        out["err"]["stage1"] = pose_error(r.T_w_o, truth["T_w_o_stage1"])
        out["adds"]["stage1"] = adds_mm(pts_o, r.T_w_o, truth["T_w_o_stage1"])
        out["stage1_ambiguous"] = bool(r.ambiguous)
    if "register_scan" in up:
        r = up["register_scan"]
        out["err"]["scan"] = pose_error(r.T_turntable_o_scan, truth["T_turntable_o_scan"])
        out["adds"]["scan"] = adds_mm(pts_o, r.T_turntable_o_scan, truth["T_turntable_o_scan"])
        out["scan_fitness"] = float(r.fitness)
        out["scan_ambiguous"] = bool(r.ambiguous)
    if "register_object" not in up:
        return out
    session = up["load_session"]
    if mode == "pipeline":
        pre = upstream(d, configs)
        if "failed" in pre:
            out["failed"]["upstream"] = pre["failed"]
            return out
        up |= {k: v for k, v in pre.items() if k in UPSTREAM and k != "load_session"}
        t0 = time.process_time()
        try:
            up["estimate_adjustment"] = run_stage(
                STAGES["estimate_adjustment"], d, configs["estimate_adjustment"], up)
        except StageError as e:
            out["failed"]["estimate_adjustment"] = e.reason[:90]
        out["times"]["estimate_adjustment"] = time.process_time() - t0
        if "estimate_adjustment" not in up:
            return out
        adj = up["estimate_adjustment"]
        up["refine_grasp"] = None
        try:
            prop = run_stage(STAGES["propagate_poses"], d, configs["propagate_poses"], up)
        except Exception as e:  # noqa: BLE001 - a bench records every failure
            out["failed"]["propagate_poses"] = str(e)[:90]
            prop = None
        est = {"T_adj": adj.T_adj, "steady_from": up["select_steady"].steady_from}
        if prop is not None:
            est |= {"frame": np.asarray(prop.frame_indices), "T_c_o": prop.T_c_o}
        m = evaluate(d, est)
        i = up["select_steady"].steady_from - int(truth["steady_from"])
        if 0 <= i < len(truth["T_w_c"]):  # the object in the detected first steady frame
            T_true = inv_T(truth["T_w_c"][i]) @ truth["T_adj"] @ truth["T_w_o_stage1"]
            out["adds"]["frame"] = adds_mm(pts_o, adj.T_w_o, T_true)
        out["err"]["T_adj"] = (m["T_adj_rot_deg"], m["T_adj_trans_mm"] / 1e3)
        if "frame_object_rot_deg" in m:
            out["err"]["frame"] = (m["frame_object_rot_deg"], m["frame_object_trans_mm"] / 1e3)
    else:
        s = int(truth["steady_from"])
        T_w_c = truth["T_w_c"]
        cfg_fit = configs["fit_hand"]
        hand = fit_hand.fit_hand(truth["joints_w"], HandSide(session.manifest.hand), cfg_fit).mesh()
        kp = np.load(d / "ground_truth" / "keypoints_clean.npy")[s : s + len(T_w_c)]
        if kp.shape[-1] == 2:  # the clean keypoints carry no confidence
            kp = np.concatenate([kp, np.ones((*kp.shape[:-1], 1))], axis=-1)
        kp = _ideal_keypoints(session, kp)
        stage1 = up["register_object"]
        t0 = time.process_time()
        try:
            adj = adjustment_steady.estimate_adjustment_steady(
                lambda k: session.read_depth_m(session.grasp_path("depth", s + k)),
                session.color_K, *session.read_mesh(), (hand.vertices, hand.faces), kp, T_w_c,
                np.ones(len(T_w_c), bool), stage1.T_w_o, configs["estimate_adjustment"],
                T_w_o_stage1_alt=stage1.second_hypothesis,
            )
        except StageError as e:
            out["failed"]["estimate_adjustment"] = e.reason[:90]
            adj = None
        out["times"]["estimate_adjustment"] = time.process_time() - t0
        if adj is None:
            return out
        T_true = truth["T_adj"] @ truth["T_w_o_stage1"]
        out["err"]["T_adj"] = pose_error(adj.T_adj, truth["T_adj"])
        out["adds"]["frame"] = adds_mm(pts_o, adj.T_w_o, T_true)
        errs = np.array([pose_error(inv_T(T) @ adj.T_w_o, inv_T(T) @ T_true) for T in T_w_c])
        out["err"]["frame"] = (float(np.median(errs[:, 0])), float(np.median(errs[:, 1])))
    out["adj_ambiguous"] = bool(adj.ambiguous)
    out["adj_path"] = str(adj.path)
    out["adj_views"] = int(adj.views)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--profile", default="wild-nodet")
    p.add_argument("--seed", type=int, default=9700)
    p.add_argument("--sessions", type=int, default=12)
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--upstream", choices=("pipeline", "truth"), default="pipeline")
    p.add_argument("--root", type=Path, default=Path("/tmp/objbench"))
    args = p.parse_args()
    if args.seed >= 20000:
        raise SystemExit("seeds >= 20000 are the integrator's report sets")
    configs = configs_for()
    rows = []
    for i in range(args.start, args.start + args.sessions):
        d = session_dir(args.root, args.profile, args.seed, i, args.frames)
        if d is None:
            print(f"| [{args.seed}, {i}] | the rig could not stage it |", flush=True)
            continue
        r = run_one(d, configs, args.upstream)
        rows.append(r)
        print(row(r), flush=True)
    summarise(rows)


def row(r: dict[str, Any]) -> str:
    """One markdown row: deg / mm (ADD-S mm) per pose, ``amb`` where the stage said so."""
    e, t = r["err"], r["times"]

    def f(k: str, amb: str) -> str:
        if k not in e:
            return "-"
        sym = f" ({r['adds'][k]:.1f})" if k in r.get("adds", {}) else ""
        return f"{e[k][0]:.2f} / {1e3 * e[k][1]:.1f}{sym}{' amb' if r.get(amb) else ''}"

    times = " / ".join(f"{t.get(k, np.nan):.1f}" for k in
                       ("register_object", "estimate_adjustment", "register_scan"))
    failed = "; ".join(f"{k}: {v}" for k, v in r["failed"].items())
    return (f"| {r['name']} | {f('stage1', 'stage1_ambiguous')} | {f('T_adj', 'adj_ambiguous')} "
            f"| {f('frame', '')} | {f('scan', 'scan_ambiguous')} | {times} | {failed} |")


def adds_mm(points_o: np.ndarray, T_est: np.ndarray, T_true: np.ndarray) -> float:
    """ADD-S (mm): mean distance from the model's ``points_o`` (n, 3) at ``T_est`` to the
    nearest of them at ``T_true`` (a symmetric object's twin costs nothing)."""
    a = points_o @ T_est[:3, :3].T + T_est[:3, 3]
    b = points_o @ T_true[:3, :3].T + T_true[:3, 3]
    return 1e3 * float(cKDTree(b).query(a)[0].mean())


def summarise(rows: list[dict[str, Any]]) -> None:
    n = len(rows)
    print(f"\n{n} sessions")
    for stage in ("register_object", "estimate_adjustment", "register_scan"):
        ok = sum(stage not in r["failed"] and stage in r["times"] for r in rows)
        ran = sum(stage in r["times"] for r in rows)
        print(f"{stage}: built {ok} of {ran} that ran")
    for k in ("stage1", "T_adj", "frame", "scan"):
        v = np.array([r["err"][k] for r in rows if k in r["err"]])
        a = np.array([r["adds"][k] for r in rows if k in r.get("adds", {})])
        if len(a):
            print(f"{k} ADD-S: median {np.median(a):.1f} mm, <= 5 mm {int(np.sum(a <= 5))} "
                  f"of {len(a)}")
        if len(v):
            print(f"{k}: n={len(v)} median {np.median(v[:, 0]):.2f} deg / "
                  f"{1e3 * np.median(v[:, 1]):.1f} mm; p90 {np.percentile(v[:, 0], 90):.2f} deg"
                  f" / {1e3 * np.percentile(v[:, 1], 90):.1f} mm; within 2 deg/6 mm "
                  f"{int(np.sum((v[:, 0] <= 2) & (v[:, 1] <= 0.006)))}")
    for k, amb in (("stage1", "stage1_ambiguous"), ("frame", "adj_ambiguous"),
                   ("scan", "scan_ambiguous")):
        off = [r for r in rows if k in r["err"] and r["err"][k][0] > 5.0]
        silent = [r["name"] for r in off if not r.get(amb)]
        print(f"{k}: {len(off)} more than 5 deg off, {len(silent)} of them not reported "
              f"ambiguous {silent}")
    times = defaultdict(list)
    for r in rows:
        for k, t in r["times"].items():
            times[k].append(t)
    print("median time: " + ", ".join(f"{k} {np.median(v):.1f} s" for k, v in times.items()))
    reasons = Counter(f"{k}: {v[:60]}" for r in rows for k, v in r["failed"].items())
    for why, c in reasons.most_common():
        print(f"  {c} x {why}")


if __name__ == "__main__":
    main()
