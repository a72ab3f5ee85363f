"""Real frames: the pipeline's detector and static-hand reconstruction on a CORe50 clip.

    .venv/bin/python bench/core50_consistency.py [--focal 500] [--picture PNG]

``../shared/data/core50_handheld_real/clip_bulb/frames`` holds 20 real colour frames (350 x 350,
cropped from a Kinect v2 colour stream) of a right hand turning a light bulb it grips; no
depth, no intrinsics, no annotation (its SOURCE.txt). This runs, as a user would:

1. the ``detect_keypoints`` stage's MediaPipe backend (``keypoints.mediapipe_detector
   .detect_frames``, the stage's default ``MediaPipeConfig``: video mode, the manifest's hand
   "right") and the stage's corrupt-frame check (``detect_keypoints.corrupt_frames``);
2. the pixels-only part of ``reconstruct_hand`` (stage 2): its two-view start
   (``two_view_init.initialise``) and its robust reprojection-only solve with outlier
   rejection (``solve.solve_visual``), with the stage's default ``ReconstructConfig``, over
   all 20 frames as the steady phase. Without depth there is no metric scale and none of the
   stage's depth steps; the reprojection-only solve is what the pixels alone can say.

The camera is a pinhole with the principal point at the crop's centre and an ASSUMED focal
length (default 500 px: SOURCE.txt's "roughly 350-600 px" for the crop; ``--focals`` repeats
the solve at others to show the figures barely depend on it).

It reports frames with a detection, the inlier share, the inlier reprojection RMSE, the
cameras' turn, and whether one static hand explains the clip by the stage's own acceptance
limits (``min_inlier_ratio``, ``max_reproj_rmse_px``); it draws the reconstructed hand
reprojected on three frames. This is a CONSISTENCY check on real detections (does one rigid
hand seen by moving cameras explain them?), not an accuracy figure: there is no ground truth.
A control shows the check can fail: the same detections with the index and ring fingers'
labels swapped in every other frame.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
FRAMES = REPO.parent / "shared" / "data" / "core50_handheld_real" / "clip_bulb" / "frames"
SIZE = (350, 350)
"""Width, height of the frames (pixels)."""
FOCAL_PX = 500.0
"""The assumed focal length (pixels) of the 350 px crops (SOURCE.txt: roughly 350-600)."""
HAND = "right"


@dataclass(frozen=True)
class Consistency:
    """What the pixels-only static-hand solve says about the clip (module docstring)."""

    focal_px: float
    frames: int
    frames_detected: int
    """Frames with a hand detection (any joint)."""
    corrupt_frames: int
    """Frames the stage's corrupt-frame check drops."""
    detections: int
    """Joint detections used (confidence >= the stage's ``min_confidence``)."""
    inliers: int
    inlier_share: float
    rmse_px: float
    """Reprojection RMSE over the inliers (pixels)."""
    median_px: float
    """Median reprojection residual over every used detection (pixels)."""
    max_px: float
    frames_posed: int
    turn_deg: float
    """Largest rotation of a camera away from the first posed one (``rotation_span_deg``)."""
    max_step_deg: float
    """Largest rotation between the cameras of consecutive frames of the clip (the GIF's
    frame spacing is not stated): not one of the stage's checks; a mirrored hand needs a
    half turn between neighbours."""
    pair: tuple[int, int]
    """The two-view start's frames."""
    one_static_hand: bool
    """Inlier share >= the stage's ``min_inlier_ratio``, RMSE <= its ``max_reproj_rmse_px``,
    every usable frame posed, and the cameras turned at least its ``min_rotation_deg``."""


def frame_paths(frames_dir: Path = FRAMES) -> list[Path]:
    paths = sorted(frames_dir.glob("*.png"))
    if not paths:
        raise SystemExit(f"no frames (*.png) in {frames_dir}")
    return paths


def detect(paths: list[Path]) -> tuple[np.ndarray, dict[int, str]]:
    """(n, 21, 3) keypoints (x, y, confidence; 0 = missed) and the corrupt frames (dropped)."""
    from graspcap.tasks.keypoints.detect_keypoints import DetectKeypointsConfig, corrupt_frames
    from graspcap.tasks.keypoints.mediapipe_detector import detect_frames

    config = DetectKeypointsConfig()
    found = detect_frames(paths, SIZE, HAND, config.mediapipe)
    kp = np.array(found.keypoints, dtype=float).reshape(len(paths), 21, 3)
    kp[kp[..., 2] < config.min_confidence] = 0.0
    corrupt = corrupt_frames(kp, config)
    for i in corrupt:
        kp[i] = 0.0
    return kp, corrupt


def intrinsics(focal_px: float) -> np.ndarray:
    return np.array([[focal_px, 0.0, SIZE[0] / 2], [0.0, focal_px, SIZE[1] / 2],
                     [0.0, 0.0, 1.0]])


def static_hand(kp: np.ndarray, focal_px: float, corrupt: int = 0):
    """The reprojection-only static-hand solve of ``reconstruct_hand`` (module docstring):
    (:class:`Consistency`, T_c_w (n, 4, 4), points_w (21, 3), residuals (n, 21), inliers)."""
    from graspcap.tasks.core.geometry import rotation_error_deg
    from graspcap.tasks.hand_sfm.reconstruct_hand import PRESETS
    from graspcap.tasks.hand_sfm.solve import rotation_span_deg, solve_visual
    from graspcap.tasks.hand_sfm.two_view_init import initialise

    cfg = PRESETS["default"]
    K = intrinsics(focal_px)
    uv, conf = kp[..., :2], kp[..., 2]
    ok = (conf >= cfg.min_confidence) & np.all(np.isfinite(kp), axis=2)
    init, parallax = initialise(uv, ok, K, n_candidates=cfg.pair_candidates,
                                ransac_px=cfg.ransac_px, min_points=cfg.min_points_per_frame,
                                min_parallax_deg=cfg.min_parallax_deg)
    if init is None:
        raise SystemExit(f"no two-view start: best parallax {parallax:.2f} deg")
    sigma = cfg.sigma_px / np.maximum(conf, cfg.min_sigma_confidence)
    ba, res, inlier, _, _ = solve_visual(cfg, uv, ok, sigma, K, init.T_c_w, init.points_w,
                                      init.pair)
    posed = np.all(np.isfinite(ba.T_c_w.reshape(len(kp), -1)), axis=1)
    usable = ok.sum(1) >= cfg.min_points_per_frame
    share = float(inlier.sum() / ok.sum())
    rmse = float(np.sqrt(np.mean(res[inlier] ** 2)))
    turn = float(rotation_span_deg(ba.T_c_w))
    steps = [rotation_error_deg(b[:3, :3], a[:3, :3])
             for a, b in zip(ba.T_c_w[:-1], ba.T_c_w[1:], strict=True)
             if np.all(np.isfinite(a)) and np.all(np.isfinite(b))]
    facts = Consistency(
        focal_px=focal_px, frames=len(kp), frames_detected=int((kp[..., 2] > 0).any(1).sum()),
        corrupt_frames=corrupt, detections=int(ok.sum()), inliers=int(inlier.sum()),
        inlier_share=share, rmse_px=rmse, median_px=float(np.nanmedian(res[ok])),
        max_px=float(np.nanmax(res[ok])), frames_posed=int(posed.sum()), turn_deg=turn,
        max_step_deg=float(max(steps)) if steps else float("nan"),
        pair=(int(init.pair.a), int(init.pair.b)),
        one_static_hand=bool(share >= cfg.min_inlier_ratio and rmse <= cfg.max_reproj_rmse_px
                             and posed[usable].all() and turn >= cfg.min_rotation_deg))
    return facts, ba.T_c_w, ba.points_w, res, inlier


def swapped(kp: np.ndarray, a: slice, b: slice, every: int = 2) -> np.ndarray:
    """``kp`` with the labels of the joints ``a`` and ``b`` swapped in every ``every``-th
    frame: what a detector confusing two fingers would give."""
    out = kp.copy()
    frames = np.arange(0, len(kp), every)
    out[frames, a], out[frames, b] = kp[frames, b], kp[frames, a]
    return out


def mirrored(kp: np.ndarray, every: int = 2) -> np.ndarray:
    """``kp`` mirrored left-right about each frame's median x in every ``every``-th frame: the
    detections of the other hand."""
    out = kp.copy()
    frames = np.arange(0, len(kp), every)
    centre = np.median(kp[frames, :, 0], axis=1, keepdims=True)
    out[frames, :, 0] = 2 * centre - kp[frames, :, 0]
    return out


CONTROLS = {
    "index/ring swapped": lambda kp: swapped(kp, slice(5, 9), slice(13, 17)),
    "thumb/little swapped": lambda kp: swapped(kp, slice(1, 5), slice(17, 21)),
    "mirrored (other hand)": mirrored,
}
"""Detections one static hand should NOT explain, each in every other frame: the controls."""


def project(K: np.ndarray, T_c_w: np.ndarray, X: np.ndarray) -> np.ndarray:
    Xc = X @ T_c_w[:3, :3].T + T_c_w[:3, 3]
    uv = Xc @ K.T
    return uv[:, :2] / uv[:, 2:3]


def draw(paths: list[Path], kp: np.ndarray, facts: Consistency, T_c_w: np.ndarray,
         X: np.ndarray, res: np.ndarray, out: Path, frames: tuple[int, ...] = ()) -> Path:
    """Three frames side by side (the first, the middle, the last unless ``frames``), cropped
    to the hand: the detections (green dots) and the one static hand's joints reprojected
    with each frame's camera (magenta skeleton), each frame's RMSE written on it; saved as a
    palette PNG at ``out``."""
    import cv2

    from graspcap.tasks.hand.model import SKELETON

    K = intrinsics(facts.focal_px)
    frames = frames or (0, len(paths) // 2, len(paths) - 1)
    scale = 2  # drawn at twice the size, cropped to the hand and the bulb
    reprojected = {i: project(K, T_c_w[i], X) for i in frames if np.all(np.isfinite(T_c_w[i]))}
    pts = np.concatenate([kp[i, kp[i, :, 2] > 0, :2] for i in frames]
                         + list(reprojected.values()))
    pad = 60
    x0, y0 = np.maximum(np.floor(pts.min(0)) - pad, 0).astype(int)
    x1, y1 = np.minimum(np.ceil(pts.max(0)) + pad, SIZE).astype(int)
    y0 = max(0, y0 - 40)  # room for the label
    tiles = []
    for i in frames:
        img = cv2.imread(str(paths[i]), cv2.IMREAD_COLOR)[y0:y1, x0:x1]
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        seen = kp[i, :, 2] > 0
        if i in reprojected:
            uv = (reprojected[i] - (x0, y0)) * scale
            for a, b in SKELETON:
                cv2.line(img, tuple(np.round(uv[a]).astype(int)),
                         tuple(np.round(uv[b]).astype(int)), (255, 0, 255), 2, cv2.LINE_AA)
        for j in np.flatnonzero(seen):
            cv2.circle(img, tuple(np.round((kp[i, j, :2] - (x0, y0)) * scale).astype(int)),
                       4, (0, 200, 0), -1, cv2.LINE_AA)
        rmse = float(np.sqrt(np.mean(res[i][seen] ** 2))) if seen.any() else float("nan")
        cv2.rectangle(img, (0, 0), (img.shape[1], 34), (255, 255, 255), -1)
        cv2.putText(img, f"frame {i}: RMSE {rmse:.1f} px", (8, 24),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.line(img, (img.shape[1] - 1, 0), (img.shape[1] - 1, img.shape[0]), (255,) * 3, 2)
        tiles.append(img)
    strip = np.concatenate(tiles, axis=1)
    lines = ["green: MediaPipe detections; magenta: ONE static hand (reprojection-only solve, "
             f"f = {facts.focal_px:g} px assumed)",
             f"seen by each frame's camera; all frames: {facts.inliers}/{facts.detections} "
             f"inliers, RMSE {facts.rmse_px:.2f} px (consistency, not accuracy)"]
    caption = np.full((26 * len(lines) + 10, strip.shape[1], 3), 255, np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(caption, line, (8, 24 + 26 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.55,
                    (0, 0, 0), 1, cv2.LINE_AA)
    out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image

    rgb = np.concatenate([strip, caption], axis=0)[..., ::-1]
    Image.fromarray(np.ascontiguousarray(rgb)).quantize(colors=128).save(out, optimize=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=Path, default=FRAMES, help="folder of the PNG frames")
    ap.add_argument("--focal", type=float, default=FOCAL_PX,
                    help="assumed focal length, pixels (default %(default)s)")
    ap.add_argument("--focals", type=float, nargs="*", default=[350.0, 700.0, 1000.0],
                    help="other focal lengths to repeat the solve at (sensitivity)")
    ap.add_argument("--picture", type=Path, default=None,
                    help="write the reprojection picture here (PNG)")
    ap.add_argument("--json", action="store_true", help="print the facts as JSON lines")
    args = ap.parse_args()

    paths = frame_paths(args.frames)
    kp, corrupt = detect(paths)
    rows = []
    for f in [args.focal, *args.focals]:
        facts, T_c_w, X, res, _ = static_hand(kp, f, len(corrupt))
        rows.append(facts)
        if f == args.focal and args.picture:
            print(f"picture: {draw(paths, kp, facts, T_c_w, X, res, args.picture)}")
    controls = {name: static_hand(make(kp), args.focal, len(corrupt))[0]
                for name, make in CONTROLS.items()}
    if args.json:
        for r in rows:
            print(json.dumps(asdict(r)))
        for name, r in controls.items():
            print(json.dumps({"control": name, **asdict(r)}))
        return
    print(f"{len(paths)} frames, {rows[0].frames_detected} with a detection, "
          f"{rows[0].corrupt_frames} dropped as corrupt")
    head = ("  detections  inliers  share  rmse_px  median_px  max_px  posed  turn_deg  "
            "max_step_deg  one static hand")

    def cells(r: Consistency) -> str:
        return (f"  {r.detections:10d}  {r.inliers:7d}  {r.inlier_share:.3f}  {r.rmse_px:7.2f}"
                f"  {r.median_px:9.2f}  {r.max_px:6.1f}  {r.frames_posed:5d}  {r.turn_deg:8.1f}"
                f"  {r.max_step_deg:12.1f}  {r.one_static_hand}")

    print("focal_px" + head)
    for r in rows:
        print(f"{r.focal_px:8.0f}" + cells(r))
    print(f"\ncontrols (every other frame altered), f = {args.focal:g} px\n{'':22s}" + head)
    for name, r in controls.items():
        print(f"{name:22s}" + cells(r))


if __name__ == "__main__":
    main()
