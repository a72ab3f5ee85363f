"""A page of randomised ``wild`` sessions: each one's first colour frame, one picture.

    .venv/bin/python bench/wild_gallery.py [--seed 0] [--sessions 12] [--out docs/wild_sessions.png]

Each tile is session i of ``graspcap synth --profile wild --seed SEED`` (4 frames, the
first shown), letterboxed to 4:3, with the written detection of that frame drawn as dots
(green: the right hand's 21 keypoints; none when the detector missed the frame) and a
caption: object and size, the turn aimed at, image size and k1, hand size, and the palm's
depth at the first steady frame (frame 0 is the approach, the hand still near the platter).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np

from graspcap.synth import config_for, generate_session

TILE = (320, 240)
CAPTION_PX = 30
COLUMNS = 4


def _tile(session: Path) -> np.ndarray:
    manifest = json.loads((session / "session.json").read_text())
    truth = json.loads((session / "ground_truth/truth.json").read_text())
    image = cv2.imread(str(session / manifest["grasp"]["color"].format(index=0)))
    doc = json.loads((session / manifest["grasp"]["keypoints"].format(index=0)).read_text())
    h, w = image.shape[:2]
    s = min(TILE[0] / w, TILE[1] / h)
    small = cv2.resize(image, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    tile = np.full((TILE[1] + CAPTION_PX, TILE[0], 3), 255, np.uint8)
    y0, x0 = CAPTION_PX + (TILE[1] - small.shape[0]) // 2, (TILE[0] - small.shape[1]) // 2
    tile[y0: y0 + small.shape[0], x0: x0 + small.shape[1]] = small
    if doc["people"]:
        kp = np.array(doc["people"][0]["hand_right_keypoints_2d"]).reshape(21, 3)
        for x, y, c in kp:
            if c > 0:
                cv2.circle(tile, (round(x0 + x * s), round(y0 + y * s)), 2, (60, 220, 60), -1)
    rnd = truth["randomisation"]
    palm = np.array(truth["joints_w"])[[0, 1, 5, 9, 13, 17]].mean(axis=0)
    lines = [f"{truth['object_id']}  turn {rnd['motion_turn_deg']:.0f} deg",
             f"{w}x{h} k1 {rnd['dist'][0]:+.2f}  hand x{truth['hand_scale']:.2f}  "
             f"held at {palm[2]:.2f} m"]
    if not doc["people"]:
        lines[0] += "  (no detection)"
    for k, text in enumerate(lines):
        org = (4, 12 + 13 * k)
        cv2.putText(tile, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return tile


def gallery(seed: int, sessions: int, work: Path) -> np.ndarray:
    """The page (rows of ``COLUMNS`` tiles) of ``sessions`` wild sessions of ``seed``."""
    cfg = config_for("wild", frames=4)
    tiles = [_tile(generate_session(work, [seed, i], cfg)) for i in range(sessions)]
    while len(tiles) % COLUMNS:
        tiles.append(np.full_like(tiles[0], 255))
    rows = [np.hstack(tiles[r: r + COLUMNS]) for r in range(0, len(tiles), COLUMNS)]
    return np.vstack(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sessions", type=int, default=12)
    parser.add_argument("--out", type=Path, default=Path("docs/wild_sessions.png"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as work:
        page = gallery(args.seed, args.sessions, Path(work))
    page = (page // 8 * 8).astype(np.uint8)  # 32 levels per channel: a much smaller PNG
    cv2.imwrite(str(args.out), page, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
