"""Fitted hand joints with and without the per-subject hand shape, on generated sessions.

    .venv/bin/python bench/hand_shape_fit.py collect --profile wild --seed 9700 --sessions 8
    .venv/bin/python bench/hand_shape_fit.py score --profile wild --seed 9700 --sessions 8

``collect`` generates session ``[seed, i]`` of the profile (40 frames) and runs the stages up
to ``reconstruct_hand`` (bare, ``graspcap.tasks.pipeline.run_stage``), keeping what the fit
needs in ``--cache`` (one ``.npz`` per session; a failed stage is recorded with its reason).
``score`` fits the hand to the cached SfM joints with the template's proportions
(``estimate_shape=False``) and with the per-subject shape (``fit_hand``'s default), and prints
per session and as medians:

- ``fit_joints_mm``: mean joint error of the fitted hand against the truth, as
  ``graspcap.synth.evaluate`` measures it (the accuracy bench's ``fit_joints_mm``);
- ``capacity_mm``: the same fits to the *true* joints (moved into the estimate's frame): what
  the model itself cannot take, without the SfM's error;
- ``pa_mm``: mean joint error of the fitted hand against the truth after the best similarity
  (Umeyama): the hand's shape and pose alone, without the SfM's global error (camera, scale);
- ``noisy_pa_mm``: ``pa_mm`` of the fits to the true joints plus Gaussian noise of
  ``--noise-mm`` per coordinate (seeded by the session): an SfM at the issue's target accuracy;
- ``bone_err_pct``: RMS relative error of the fitted hand's 20 bone lengths against the truth's
  (includes the SfM's scale error).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from graspcap.synth import config_for, generate_session
from graspcap.synth.evaluate import _anchor, _mpjpe_mm, load_truth
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, transform_points, umeyama
from graspcap.tasks.hand.fit_hand import PRESETS, fit_hand
from graspcap.tasks.hand.model import SKELETON, HandSide
from graspcap.tasks.pipeline import SESSION_STAGE, STAGES, configs_for, run_stage

UP_TO = "reconstruct_hand"


def _bones(joints: np.ndarray) -> np.ndarray:
    return np.array([np.linalg.norm(joints[k] - joints[p]) for p, k in SKELETON])


def collect(profile: str, seed: int, sessions: int, frames: int, cache: Path) -> None:
    cache.mkdir(parents=True, exist_ok=True)
    configs = configs_for()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(sessions):
            out = cache / f"{profile}_{seed}_{i}.npz"
            if out.exists():
                continue
            try:
                d = generate_session(Path(tmp) / profile, [seed, i], config_for(profile, frames),
                                     None)
            except StageError as e:
                np.savez(out, failed=f"rig: {e.reason[:80]}")
                continue
            truth = load_truth(d)
            results: dict = {}
            failed = ""
            for name, stage in STAGES.items():
                try:
                    results[name] = run_stage(stage, d, configs[name], results)
                except StageError as e:
                    failed = f"{e.stage}: {e.reason[:80]}"
                    break
                if name == UP_TO:
                    break
            if failed:
                np.savez(out, failed=failed)
                print(out.name, failed, flush=True)
                continue
            rec = results[UP_TO]
            np.savez(out, failed="", joints_w=rec.joints_w, joint_valid=rec.joint_valid,
                     T_w_c=rec.T_w_c, pose_valid=rec.pose_valid, steady_from=rec.steady_from,
                     side=str(results[SESSION_STAGE].manifest.hand),
                     truth_joints_w=truth["joints_w"], truth_T_w_c=truth["T_w_c"],
                     truth_steady_from=int(truth["steady_from"]))
            print(out.name, "ok", flush=True)


def _pa_mm(est: np.ndarray, truth: np.ndarray) -> float:
    T, s = umeyama(est, truth)
    return 1e3 * float(np.linalg.norm(transform_points(T, s * est) - truth, axis=1).mean())


SHAPE_NOISE_MM: float | None = None
"""``--shape-noise-mm``: fit_hand's ``shape_noise_mm`` for the shape fits (None: its default)."""
SHAPE_TEST_P: float | None = None
"""``--shape-test-p``: fit_hand's ``shape_test_p`` (None: its default)."""


def _score(z, estimate_shape: bool, oracle: bool, noise_mm: float = 0.0, seed: int = 0
           ) -> tuple[float, float, float]:
    truth = {"joints_w": z["truth_joints_w"], "T_w_c": z["truth_T_w_c"],
             "steady_from": int(z["truth_steady_from"])}
    steady = int(z["steady_from"])
    at = _anchor(steady, truth["steady_from"], len(z["T_w_c"]), z["pose_valid"])
    joints = z["joints_w"]
    if oracle:  # the true joints in the estimate's world (through the anchor camera)
        T_c_w_true = inv_T(truth["T_w_c"][at - truth["steady_from"]])
        joints = transform_points(z["T_w_c"][at - steady] @ T_c_w_true, truth["joints_w"])
        joints = joints + np.random.default_rng(seed).normal(0.0, 1e-3 * noise_mm, (21, 3))
    valid = z["joint_valid"].astype(bool) & np.all(np.isfinite(joints), axis=1)
    update: dict = {"estimate_shape": estimate_shape}
    if SHAPE_NOISE_MM is not None:
        update["shape_noise_mm"] = SHAPE_NOISE_MM
    if SHAPE_TEST_P is not None:
        update["shape_test_p"] = SHAPE_TEST_P
    cfg = PRESETS["default"].model_copy(update=update)
    fit = fit_hand(np.where(valid[:, None], joints, np.nan), HandSide(str(z["side"])), cfg,
                   weights=valid.astype(float))
    err = _mpjpe_mm(fit.joints_fit_w, z["T_w_c"], steady, truth, at)
    rel = fit.bone_lengths_m / _bones(truth["joints_w"]) - 1.0
    est_true = transform_points(z["T_w_c"][at - steady], fit.joints_fit_w)  # estimate's camera
    tru_cam = transform_points(inv_T(truth["T_w_c"][at - truth["steady_from"]]), truth["joints_w"])
    return err, _pa_mm(est_true, tru_cam), 100.0 * float(np.sqrt(np.mean(rel**2)))


def score(profile: str, seed: int, sessions: int, cache: Path, noise_mm: float) -> None:
    rows = []
    failed = 0
    for i in range(sessions):
        path = cache / f"{profile}_{seed}_{i}.npz"
        if not path.exists():
            continue
        z = np.load(path, allow_pickle=False)
        if str(z["failed"]):
            failed += 1
            print(f"[{seed}, {i}] stopped: {z['failed']}")
            continue
        t_err, t_pa, t_bone = _score(z, False, False)
        s_err, s_pa, s_bone = _score(z, True, False)
        t_cap, _, _ = _score(z, False, True)
        s_cap, _, _ = _score(z, True, True)
        _, t_npa, _ = _score(z, False, True, noise_mm, i)
        _, s_npa, _ = _score(z, True, True, noise_mm, i)
        rows.append((t_err, s_err, t_cap, s_cap, t_bone, s_bone, t_pa, s_pa, t_npa, s_npa))
        print(f"[{seed}, {i}] fit_joints_mm {t_err:6.2f} -> {s_err:6.2f}   pa_mm {t_pa:5.2f} -> "
              f"{s_pa:5.2f}   capacity_mm {t_cap:5.2f} -> {s_cap:5.2f}   noisy_pa_mm "
              f"{t_npa:5.2f} -> {s_npa:5.2f}   bone_err_pct "
              f"{t_bone:5.1f} -> {s_bone:5.1f}")
    if rows:
        m = np.median(np.array(rows), axis=0)
        print(f"{profile} seed {seed}: {len(rows)} fitted, {failed} stopped before fit_hand; "
              f"medians template -> shape: fit_joints_mm {m[0]:.2f} -> {m[1]:.2f}, capacity_mm "
              f"{m[2]:.2f} -> {m[3]:.2f}, pa_mm {m[6]:.2f} -> {m[7]:.2f}, noisy_pa_mm "
              f"{m[8]:.2f} -> {m[9]:.2f}, bone_err_pct "
              f"{m[4]:.1f} -> {m[5]:.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("collect", "score"))
    parser.add_argument("--profile", default="wild")
    parser.add_argument("--seed", type=int, default=9700)
    parser.add_argument("--sessions", type=int, default=8)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/hand_shape_cache"))
    parser.add_argument("--shape-noise-mm", type=float, default=None)
    parser.add_argument("--noise-mm", type=float, default=1.5)
    parser.add_argument("--shape-test-p", type=float, default=None)
    args = parser.parse_args()
    global SHAPE_NOISE_MM, SHAPE_TEST_P
    SHAPE_NOISE_MM, SHAPE_TEST_P = args.shape_noise_mm, args.shape_test_p
    if args.command == "collect":
        collect(args.profile, args.seed, args.sessions, args.frames, args.cache)
    else:
        score(args.profile, args.seed, args.sessions, args.cache, args.noise_mm)


if __name__ == "__main__":
    main()
