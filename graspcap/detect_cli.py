"""``graspcap detect``: 2D hand keypoints of single images, to check a rig's footage before a
build. Each image on its own (no tracking); defaults come from the stage's config models."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the stage modules load on use: `graspcap --help` stays quick
    from graspcap.tasks.keypoints.detect_keypoints import Backend, DetectKeypointsConfig

BACKENDS = ("mediapipe", "openpose_json")
"""Values of ``graspcap.tasks.keypoints.detect_keypoints.Backend`` (checked in the tests)."""
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")
NAMES = ("wrist", "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
         "index_mcp", "index_pip", "index_dip", "index_tip",
         "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
         "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
         "little_mcp", "little_pip", "little_dip", "little_tip")  # fmt: skip


@dataclass(frozen=True)
class ImageResult:
    """One input's answer: ``keypoints`` (21, 3) x_px, y_px, conf (zeros: none), ``hands``
    found in it, whether the kept one carries the other hand's label, or why it failed."""

    path: Path
    keypoints: np.ndarray
    hands: int
    label_mismatch: bool = False
    error: str = ""

    def as_dict(self) -> dict[str, object]:
        return {"path": str(self.path), "found": bool((self.keypoints[:, 2] > 0).any()),
                "hands": self.hands, "label_mismatch": self.label_mismatch,
                "error": self.error or None,
                "keypoints": np.round(self.keypoints, 3).tolist()}


def expand(inputs: Sequence[Path], backend: Backend) -> list[Path]:
    """Files named, and the matching files inside folders named (sorted)."""
    suffixes = (".json",) if backend == "openpose_json" else IMAGE_SUFFIXES
    out: list[Path] = []
    for p in map(Path, inputs):
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.suffix.lower() in suffixes)
        else:
            out.append(p)
    return out


def detect_paths(
    paths: Sequence[Path], hand: str, backend: Backend, config: DetectKeypointsConfig
) -> list[ImageResult]:
    """Keypoints of ``hand`` in each image (``mediapipe``) or OpenPose JSON file."""
    from graspcap.tasks.keypoints.detect_keypoints import Backend, read_openpose_frame, track_hands

    results = []
    if backend is Backend.OPENPOSE_JSON:
        for path in paths:
            hands, notes = read_openpose_frame(path, hand)
            kp = track_hands([hands], config)[0]
            results.append(ImageResult(path, kp, len(hands), error="; ".join(notes)))
        return results
    from graspcap.tasks.keypoints.mediapipe_detector import Detector, pick, read_rgb

    mp = config.mediapipe
    detector = Detector(mp, video=False, max_hands=2)
    try:
        for path in paths:
            rgb, why = read_rgb(path, None)
            if rgb is None:
                results.append(ImageResult(path, np.zeros((21, 3)), 0, error=why))
                continue
            found = detector(rgb)
            chosen = pick(found, hand, None, mp.handedness)  # type: ignore[arg-type]
            kp = np.zeros((21, 3)) if chosen is None else chosen.keypoints()
            kp = track_hands([[kp]], config)[0]  # min_confidence, as in the stage
            mismatch = chosen is not None and chosen.hand != hand
            results.append(ImageResult(path, kp, len(found), mismatch))
    finally:
        detector.close()
    return results


def format_text(result: ImageResult, hand: str) -> str:
    head = f"{result.path}: "
    if result.error and not (result.keypoints[:, 2] > 0).any():
        return head + f"no detection ({result.error})"
    if not (result.keypoints[:, 2] > 0).any():
        return head + f"no {hand} hand ({result.hands} hand(s) found)"
    label = " (labelled as the other hand)" if result.label_mismatch else ""
    lines = [head + f"{hand} hand{label}, {result.hands} hand(s) found"
             + (f"; {result.error}" if result.error else "")]
    lines += [f"  {k:2d} {NAMES[k]:<11} x {x:8.1f}  y {y:8.1f}  conf {c:.3f}"
              for k, (x, y, c) in enumerate(result.keypoints)]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    missing = [p for p in args.inputs if not Path(p).exists()]
    for path in missing:  # a typo is named before a detector loads
        print(f"graspcap detect: {str(path)!r} does not exist (no such file or folder)",
              file=sys.stderr)
    if missing:
        return 2
    from graspcap.tasks.keypoints.detect_keypoints import Backend, DetectKeypointsConfig
    from graspcap.tasks.keypoints.mediapipe_detector import FrameMode, MediaPipeConfig

    backend = Backend(args.backend)
    mp = MediaPipeConfig(mode=FrameMode.IMAGES, threads=args.threads,
                         **({} if args.model_complexity is None
                            else {"model_complexity": args.model_complexity}))
    config = DetectKeypointsConfig(backend=backend, mediapipe=mp)
    paths = expand(args.inputs, backend)
    if not paths:
        print("no input files found")
        return 2
    results = detect_paths(paths, args.hand, backend, config)
    if args.json:
        print(json.dumps([r.as_dict() for r in results], indent=1))
    else:
        for r in results:
            print(format_text(r, args.hand))
        found = sum((r.keypoints[:, 2] > 0).any() for r in results)
        print(f"{found} of {len(results)} input(s) with a {args.hand} hand")
    return 0 if all(not r.error for r in results) else 1


def add_detect_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("detect", help="print 2D hand keypoints of images (check a rig's footage)")
    p.add_argument("inputs", type=Path, nargs="+", metavar="IMAGE_OR_DIR",
                   help="images or folders of images (OpenPose JSON files with that backend)")
    p.add_argument("--backend", choices=BACKENDS, default="mediapipe")
    p.add_argument("--hand", choices=["right", "left"], default="right",
                   help="the participant's hand (MediaPipe's mirrored labels are undone)")
    p.add_argument("--model-complexity", type=int, choices=[0, 1], default=None,
                   help="MediaPipe landmark model (default: the stage config's)")
    p.add_argument("--threads", type=int, default=min(os.cpu_count() or 1, 8),
                   help="MediaPipe inference threads (default: every core, up to 8; the "
                        "detector runs alone here, unlike in a build)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)
