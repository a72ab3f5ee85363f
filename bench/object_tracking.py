"""Per-frame object tracking in depth (``estimate_adjustment``'s ``tracking`` and ``average``,
used by ``propagate_poses``): every steady frame's object pose and virtual camera against the
truth, with stage 2's cameras alone and the first frame's ``T_w_o`` (tracking off) and with the
object tracked in each frame's depth and ``T_w_o`` the mean over the tracked frames (tracking
on), per session and pooled.

    .venv/bin/python bench/object_tracking.py --profile wild-nodet --seed 9700 --sessions 8 \
        --frames 40 [--root /tmp/objtrack]

Sessions and the stages before the object ones are :mod:`object_stages`' (generated and
cached under ``--root``); register_object and estimate_adjustment run once per session and are
cached beside it (``bench_objects_<version>.pkl``); propagate_poses runs twice; the tracking's
time (in estimate_adjustment) is added to the "on" time. Per-frame object error:
each steady frame's ``T_c_o`` against the truth (rotation deg / translation mm), pooled over
the frames of all sessions (median, p90); camera error: ``graspcap.synth.evaluate``'s
``camera_rot_deg`` / ``camera_trans_mm`` (medians, per session) of ``PosePropagation.T_w_c``;
ADD-S (mm, :func:`object_stages.adds_mm`) beside the object errors: a can's or a bottle's turn
about its own axis costs nothing there. ``--truth-object`` replaces register_object and
estimate_adjustment by the true object pose in the detected first steady frame: what is left
is stage 2's cameras (the real-detector profile ``wild`` puts them degrees off) and what
tracking makes of them.
"""

from __future__ import annotations

import argparse
import pickle
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from object_stages import UPSTREAM, adds_mm, session_dir, upstream

from graspcap.synth.evaluate import _T_adj_at, evaluate, load_truth
from graspcap.tasks import pipeline
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, pose_error
from graspcap.tasks.object_pose.estimate_adjustment import STAGE_VERSION as EA_VERSION
from graspcap.tasks.object_pose.estimate_adjustment import Adjustment, AdjustmentPath
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage


def objects(d: Path, configs: dict, up: dict) -> dict[str, Any]:
    """register_object and estimate_adjustment (cached in ``d``), or ``{"failed": why}``."""
    cache = d / f"bench_objects_{EA_VERSION.replace('/', '_')}.pkl"
    if cache.exists():
        return pickle.loads(cache.read_bytes())
    out: dict[str, Any] = {}
    try:
        for name in ("register_object", "estimate_adjustment"):
            out[name] = run_stage(STAGES[name], d, configs[name], {**up, **out})
    except StageError as e:
        out = {"failed": f"{e.stage}: {e.reason[:90]}"}
    cache.write_bytes(pickle.dumps(out))
    return out


def frame_errors(prop, truth: dict, points_o: np.ndarray) -> np.ndarray:
    """(k, 3) rotation deg / translation m / ADD-S mm of each steady frame's object pose."""
    s = int(truth["steady_from"])
    T_true = truth["T_adj"] @ truth["T_w_o_stage1"]
    out = []
    for f, T in zip(prop.frame_indices, prop.T_c_o, strict=True):
        if 0 <= f - s < len(truth["T_w_c"]):
            T_f = inv_T(truth["T_w_c"][f - s]) @ T_true
            out.append((*pose_error(T, T_f), adds_mm(points_o, T, T_f)))
    return np.array(out)


def run_one(d: Path, configs: dict, truth_object: bool = False) -> dict[str, Any] | str:
    up = {"load_session": run_stage(STAGES["load_session"], d, configs["load_session"], {})}
    pre = upstream(d, configs)
    if "failed" in pre:
        return pre["failed"]
    up |= {k: v for k, v in pre.items() if k in UPSTREAM and k != "load_session"}
    truth = load_truth(d)
    if truth_object:  # the true object in the detected first steady frame: stage 2 alone
        T_adj = _T_adj_at(truth, up["select_steady"].steady_from)
        obj = {"register_object": SimpleNamespace(T_w_o=truth["T_w_o_stage1"]),
               "estimate_adjustment": Adjustment(
                   T_adj=T_adj, T_w_o=T_adj @ truth["T_w_o_stage1"], fitness=1.0,
                   inlier_rmse_m=0.0, n_points=0, path=AdjustmentPath.STAGE1_ICP,
                   ambiguous=False)}  # fmt: skip
    else:
        obj = objects(d, configs, up)
    if "failed" in obj:
        return obj["failed"]
    up |= obj | {"refine_grasp": None}
    adj, t0 = up["estimate_adjustment"], time.process_time()
    if adj.tracking is None:  # the truth: tracked (and averaged) as estimate_adjustment does
        adj = pipeline._track_adjustment(up["load_session"], configs["estimate_adjustment"], adj,
                                         **up)
    track_s = time.process_time() - t0
    first = adj if adj.T_w_o_first is None else replace(
        adj, T_w_o=adj.T_w_o_first, T_adj=adj.T_w_o_first @ inv_T(up["register_object"].T_w_o))
    out: dict[str, Any] = {}
    for mode, mode_adj in (("off", replace(first, tracking=None)), ("on", adj)):
        t0 = time.process_time()
        prop = run_stage(STAGES["propagate_poses"], d, configs["propagate_poses"],
                         {**up, "estimate_adjustment": mode_adj})
        dt = time.process_time() - t0 + (track_s if mode == "on" else 0.0)
        sfm = up["reconstruct_hand"]
        m = evaluate(d, {"steady_from": up["select_steady"].steady_from, "T_w_c": prop.T_w_c,
                         "joints_w": sfm.joints_w, "camera_solved": sfm.pose_valid})
        sup = prop.validity.object_supported
        V = up["load_session"].read_mesh()[0]
        err = frame_errors(prop, truth, V[:: max(1, len(V) // 2000)])
        out[mode] = {"err": err, "cam": (m["camera_rot_deg"], m["camera_trans_mm"]), "time": dt,
                     "tracked": None if prop.tracking is None else int(prop.tracking.tracked.sum()),
                     "supported": sum(v is True for v in sup), "frames": len(sup),
                     "reasons": [] if prop.tracking is None else
                     [r for r in prop.tracking.reason if r]}  # fmt: skip
    return out


def stats(e: np.ndarray) -> str:
    """Median deg / mm [ADD-S mm] (p90 deg / mm [ADD-S mm])."""
    if not len(e):
        return "-"
    med, p90 = np.median(e, axis=0), np.percentile(e, 90, axis=0)
    return (f"{med[0]:.2f} / {1e3 * med[1]:.1f} [{med[2]:.1f}] "
            f"(p90 {p90[0]:.2f} / {1e3 * p90[1]:.1f} [{p90[2]:.1f}])")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--profile", default="wild-nodet")
    p.add_argument("--seed", type=int, default=9700)
    p.add_argument("--sessions", type=int, default=8)
    p.add_argument("--start", type=int, default=0)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--root", type=Path, default=Path("/tmp/objtrack"))
    p.add_argument("--truth-object", action="store_true",
                   help="the true object pose in the detected first steady frame instead of "
                        "register_object and estimate_adjustment: stage 2's cameras alone")
    args = p.parse_args()
    if args.seed >= 20000:
        raise SystemExit("seeds >= 20000 are the integrator's report sets")
    configs = configs_for()
    print("| session | object off: deg / mm [ADD-S mm] (p90) | object on | camera off: deg / mm | "
          "camera on | tracked / frames | supported off / on | track s |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for i in range(args.start, args.start + args.sessions):
        d = session_dir(args.root, args.profile, args.seed, i, args.frames)
        if d is None:
            print(f"| [{args.seed}, {i}] | the rig could not stage it |", flush=True)
            continue
        r = run_one(d, configs, args.truth_object)
        if isinstance(r, str):
            print(f"| {d.name} | failed: {r} |", flush=True)
            continue
        rows.append(r)
        off, on = r["off"], r["on"]
        print(f"| {d.name} | {stats(off['err'])} | {stats(on['err'])} | "
              f"{off['cam'][0]:.2f} / {off['cam'][1]:.1f} | {on['cam'][0]:.2f} / "
              f"{on['cam'][1]:.1f} | {on['tracked']} / {on['frames']} | {off['supported']} / "
              f"{on['supported']} | {on['time'] - off['time']:.1f} |", flush=True)
    if not rows:
        return
    print(f"\n{len(rows)} sessions, pooled over their steady frames:")
    for mode in ("off", "on"):
        e = np.concatenate([r[mode]["err"] for r in rows])
        cam = np.array([r[mode]["cam"] for r in rows])
        within = int(np.sum((e[:, 0] <= 2) & (e[:, 1] <= 0.006)))
        print(f"tracking {mode}: object {stats(e)}, within 2 deg / 6 mm {within} of {len(e)}; "
              f"camera (median of session medians) {np.median(cam[:, 0]):.2f} deg / "
              f"{np.median(cam[:, 1]):.1f} mm; supported "
              f"{sum(r[mode]['supported'] for r in rows)} of "
              f"{sum(r[mode]['frames'] for r in rows)}")
    print(f"tracked {sum(r['on']['tracked'] for r in rows)} of "
          f"{sum(r['on']['frames'] for r in rows)} frames")
    why = Counter(w.split(":")[1].split("(")[0].strip()[:50] for r in rows
                  for w in r["on"]["reasons"])
    for w, c in why.most_common(6):
        print(f"  {c} x {w}")


if __name__ == "__main__":
    main()
