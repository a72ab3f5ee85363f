"""The error lens distortion makes when ignored, and what honouring it leaves.

    .venv/bin/python bench/lens_distortion.py [--sessions 4] [--seed 9800] [--frames 40]

Each realistic session (seeds ``[seed, i]``) is built three ways, every stage but
``pictures``, bare: ``pinhole`` (the rig's own renders), ``honoured`` (put behind a wide webcam
lens and a wide thermal lens by ``tests/lens_rig.py``: depth, colour, keypoints and thermal
resampled, ``dist`` written into ``session.json``) and ``ignored`` (the same distorted
session with both ``dist`` zeroed, what every stage did before). Prints the errors against the
truth per session and their medians per variant.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from graspcap.synth import config_for, generate_session  # noqa: E402
from graspcap.synth.evaluate import estimate_from_results, evaluate  # noqa: E402
from graspcap.tasks.pipeline import STAGES, configs_for, run_stage  # noqa: E402
from tests.lens_rig import THERMAL_DIST, WEBCAM_DIST, distort_session, without_dist  # noqa: E402

COLUMNS = ("object_stage1_rot_deg", "object_stage1_trans_mm", "camera_rot_deg",
           "camera_trans_mm", "joints_mpjpe_mm", "fit_joints_mm", "frame_object_rot_deg",
           "frame_object_trans_mm", "contact_iou")
VARIANTS = ("pinhole", "honoured", "ignored")


def _build(session: Path) -> dict[str, float]:
    configs, results = configs_for(), {}
    for name, stage in STAGES.items():
        if name == "pictures":
            continue
        try:
            results[name] = run_stage(stage, session, configs[name], results)
        except Exception as exc:  # a failed stage: report it, keep the others' errors
            print(f"  {session.name}: {name} failed: {str(exc).splitlines()[0][:120]}")
            break
    return evaluate(session, estimate_from_results(results))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--seed", type=int, default=9800)
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    cfg = config_for("realistic", frames=args.frames)
    rows: dict[str, list[dict[str, float]]] = {v: [] for v in VARIANTS}
    print(f"webcam dist {WEBCAM_DIST}, thermal dist {THERMAL_DIST}")
    print("session variant " + " ".join(COLUMNS))
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.sessions):
            root = Path(tmp) / f"s{i}"
            pinhole = generate_session(root / "pinhole", [args.seed, i], cfg)
            honoured = distort_session(pinhole, root / "honoured", thermal_dist=THERMAL_DIST)
            ignored = without_dist(without_dist(honoured, root / "tmp"), root / "ignored",
                                   "thermal_camera")
            for variant, path in zip(VARIANTS, (pinhole, honoured, ignored), strict=True):
                err = _build(path)
                rows[variant].append(err)
                print(f"{pinhole.name} {variant} " + " ".join(
                    f"{err.get(c, float('nan')):.3f}" for c in COLUMNS), flush=True)
    print("\nmedian over sessions")
    for variant in VARIANTS:
        print(f"{variant:9s} " + " ".join(
            f"{c}={np.nanmedian([r.get(c, np.nan) for r in rows[variant]]):.3f}"
            for c in COLUMNS))


if __name__ == "__main__":
    main()
