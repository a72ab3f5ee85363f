"""Is a wrong steady onset marked uncertain? select_steady's onset against the truth, with the
signals it decides from, on synthetic sessions generated (once) under ``--root``.

    OMP_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/onset_uncertainty.py \
        --root /tmp/onset --frames 60 \
        --set wild:9700:12 --set wild:82100:12 --set real-detector:35746:8 \
        --set realistic:9400:8 --set realistic:31170:6

``--set PROFILE:SEED:N`` takes sessions ``[SEED, 0..N-1]`` of that profile
(``graspcap.synth.generate_session(root/PROFILE-FRAMES, [SEED, i],
config_for(PROFILE, FRAMES))``). Each runs load_session, detect_keypoints and select_steady
(``pipeline.run_stage``, default configs); the selection's arrays are written to
``root/results/LABEL/NAME.json`` (``--label``, default the stage version) so that
``--report-only`` re-reads them without re-running.

Per session: the error (frames, onset - truth), the keypoint onset's and the depth onset's
error, the depth signals (share of frames with a surface, the change point's contrast, the
depth share after the onset against the steady frames) and ``uncertain``. Per profile: the
share within 3 frames, the share of wrong onsets (|error| > 3) marked uncertain (recall) and
of right ones marked (false alarms).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.hand_sfm.select_steady import STAGE_VERSION
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage

STAGE_NAMES = ("load_session", "detect_keypoints", "select_steady")


def session_dir(root: Path, profile: str, frames: int, seed: int, i: int) -> Path | None:
    """The session ``[seed, i]`` of ``profile``, generated when missing (None if the rig cannot
    stage it)."""
    out = root / f"{profile}-{frames}"
    found = [d for d in out.glob(f"synth-s{seed}-{i:03d}*") if (d / "ground_truth").exists()]
    if found:
        return found[0]
    try:
        return generate_session(out, [seed, i], config_for(profile, frames))
    except StageError as e:
        print(f"[{seed}, {i}] {profile}: not generated: {e}", flush=True)
        return None


def run(d: Path, out: Path) -> dict:
    """select_steady on ``d``; its result (arrays as lists) written to ``out``."""
    configs = configs_for()
    up: dict = {}
    row: dict = {"name": d.name, "truth": int(load_truth(d)["steady_from"])}
    try:
        for name in STAGE_NAMES:
            up[name] = run_stage(STAGES[name], d, configs[name], up)
    except StageError as e:
        row["error"] = e.reason
        out.write_text(json.dumps(row))
        return row
    sel = up["select_steady"]
    row |= {
        "steady_from": int(sel.steady_from), "keypoint_from": int(sel.keypoint_from),
        "depth_from": int(sel.depth_from), "coarse_from": int(sel.coarse_from),
        "uncertain": sel.uncertain, "n": len(sel.scores_px),
        "scores_px": [None if not np.isfinite(v) else float(v) for v in sel.scores_px],
        "depth_share": [None if not np.isfinite(v) else float(v) for v in sel.depth_share],
    }
    for key in ("depth_moving_to",):
        if hasattr(sel, key):
            row[key] = getattr(sel, key)
    out.write_text(json.dumps(row))
    return row


def _arr(values) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def signals(row: dict) -> dict[str, float]:
    """Candidate separating signals, from the stored share."""
    share = _arr(row.get("depth_share", []))
    n, t = row.get("n", 0), row.get("steady_from", -1)
    out = {"have": float(np.isfinite(share).mean()) if len(share) else float("nan")}
    if len(share) == 0 or t < 0:
        return out
    before = share[max(t - 6, 0):t]
    after = share[t:]
    after = after[np.isfinite(after)]
    ref = after[-20:] if len(after) else after
    med = float(np.median(ref)) if len(ref) else float("nan")
    out["pre"] = float(np.nanmean(before)) if np.isfinite(before).any() else float("nan")
    out["post"] = med
    out["late_max"] = float(np.max(after[:-3])) if len(after) > 3 else float("nan")
    del n
    return out


def report(rows: list[tuple[str, dict]]) -> None:
    by: dict[str, list] = {}
    for profile, row in rows:
        by.setdefault(profile, []).append(row)
        if "error" in row:
            print(f"{profile:14s} {row['name']:28s} failed: {row['error'][:80]}")
            continue
        err = row["steady_from"] - row["truth"]
        sig = signals(row)
        sig_s = " ".join(f"{k} {v:.2f}" for k, v in sig.items())
        kp = row["keypoint_from"] - row["truth"]
        print(f"{profile:14s} {row['name']:28s} err {err:+3d} kp {kp:+3d} "
              f"moving to {row.get('depth_moving_to', -1):3d} depth {row['depth_from']:3d} "
              f"truth {row['truth']:3d} {sig_s} "
              f"{'WRONG' if abs(err) > 3 else 'ok   '} unc: {row['uncertain'][:90]!r}")
    print()
    print(f"{'profile':14s} {'sessions':>8s} {'within 3':>9s} {'wrong marked':>13s} "
          f"{'right marked':>13s} {'failed':>6s}")
    for profile, rs in by.items():
        ok = [r for r in rs if "error" not in r]
        good = [r for r in ok if abs(r["steady_from"] - r["truth"]) <= 3]
        bad = [r for r in ok if abs(r["steady_from"] - r["truth"]) > 3]
        print(f"{profile:14s} {len(rs):8d} {len(good):4d}/{len(ok):<4d} "
              f"{sum(bool(r['uncertain']) for r in bad):6d}/{len(bad):<6d} "
              f"{sum(bool(r['uncertain']) for r in good):6d}/{len(good):<6d} "
              f"{len(rs) - len(ok):6d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--set", action="append", required=True,
                        help="PROFILE:SEED:N, or PROFILE:SEED:FIRST-LAST")
    parser.add_argument("--label", default=STAGE_VERSION.replace("/", "-"))
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args()
    results = args.root / "results" / args.label
    results.mkdir(parents=True, exist_ok=True)
    rows = []
    for spec in args.set:
        profile, seed, count = spec.split(":")
        lo, hi = (int(x) for x in count.split("-")) if "-" in count else (0, int(count) - 1)
        for i in range(lo, hi + 1):
            out = results / f"{profile}-{args.frames}-s{seed}-{i:03d}.json"
            if out.exists():
                rows.append((profile, json.loads(out.read_text())))
                continue
            if args.report_only:
                continue
            d = session_dir(args.root, profile, args.frames, int(seed), i)
            if d is None:
                continue
            rows.append((profile, run(d, out)))
            r = rows[-1][1]
            print(f"  {profile} [{seed}, {i}]: "
                  + (f"err {r['steady_from'] - r['truth']:+d}" if "error" not in r else "failed"),
                  flush=True)
    report(rows)


if __name__ == "__main__":
    main()
