"""What the detections alone can give: each joint triangulated from a session's detections with
the TRUE virtual cameras, against the true joints (an experiment on the evidence, not a stage).

    .venv/bin/python bench/keypoint_floor.py --profile real-detector --seed 82100 \\
        --sessions 8 --frames 60 [--root /tmp/floor]

Per session: the mean and median over the 21 joints of the distance between the true joint and
the joint triangulated from every steady frame's detection of it (confidence >= 0.2) with the
true cameras: a DLT re-weighted under a Cauchy loss of the reprojection (scale twice the median
residual, 10 rounds). No whole-frame rejection and no hand model: what the keypoints carry
when the cameras are perfect. Sessions are generated under ``--root`` (reused when there).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import load_truth
from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.pipeline import STAGES, _ideal_keypoints, configs_for, run_stage


def triangulate_robust(P: np.ndarray, uv: np.ndarray, rounds: int = 10) -> np.ndarray:
    """X (3,) from projection matrices P (n, 3, 4) and pixels uv (n, 2): DLT re-weighted by a
    Cauchy loss of the reprojection error."""
    w = np.ones(len(P))
    X = np.zeros(3)
    for _ in range(rounds):
        A = np.concatenate([(uv[:, :1] * P[:, 2] - P[:, 0]) * w[:, None],
                            (uv[:, 1:] * P[:, 2] - P[:, 1]) * w[:, None]])  # fmt: skip
        h = np.linalg.svd(A)[2][-1]
        X = h[:3] / h[3]
        proj = np.einsum("nij,j->ni", P, np.append(X, 1.0))
        r = np.linalg.norm(proj[:, :2] / proj[:, 2:] - uv, axis=1)
        w = 1.0 / (1.0 + (r / (2.0 * np.median(r) + 1e-9)) ** 2)
    return X


def true_camera_errors_mm(kp: np.ndarray, K: np.ndarray, truth: dict) -> np.ndarray:
    """Error (mm) of each joint seen in >= 3 steady frames, triangulated from the detections
    ``kp`` (n, 21, 3; ideal pixels, confidence) with the true cameras of ``truth``."""
    steady = int(truth["steady_from"])
    frames = [i for i in range(len(truth["T_w_c"])) if steady + i < len(kp)]
    P = np.stack([K @ inv_T(truth["T_w_c"][i])[:3] for i in frames])
    errors = []
    for j in range(21):
        obs = kp[[steady + i for i in frames], j]
        use = np.all(np.isfinite(obs), axis=1) & (obs[:, 2] >= 0.2)
        if use.sum() >= 3:
            X = triangulate_robust(P[use], obs[use, :2])
            errors.append(1e3 * np.linalg.norm(X - truth["joints_w"][j]))
    return np.asarray(errors)


def floor_mm(d: Path) -> tuple[float, float]:
    """Mean and median joint error (mm) of the joints triangulated with the true cameras."""
    truth = load_truth(d)
    configs, up = configs_for(), {}
    for name in ("load_session", "detect_keypoints"):
        up[name] = run_stage(STAGES[name], d, configs[name], up)
    kp = _ideal_keypoints(up["load_session"], up["detect_keypoints"].keypoints)
    errors = true_camera_errors_mm(kp, up["load_session"].color_K, truth)
    return float(np.mean(errors)), float(np.median(errors))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", default="real-detector")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--root", type=Path, default=Path("/tmp/keypoint_floor"))
    args = parser.parse_args()
    print("| session | joints triangulated with the true cameras, mean / median joint mm |")
    print("|---|---|")
    rows = []
    for i in range(args.sessions):
        found = sorted((args.root / args.profile).glob(f"synth-s{args.seed}-{i:03d}-*"))
        d = found[0] if found else generate_session(
            args.root / args.profile, [args.seed, i], config_for(args.profile, args.frames))
        mean, median = floor_mm(d)
        rows.append(mean)
        print(f"| `{d.name}` | {mean:.1f} / {median:.1f} |", flush=True)
    print(f"| **median of {len(rows)}** | **{np.median(rows):.1f}** |")


if __name__ == "__main__":
    main()
