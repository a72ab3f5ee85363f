"""The ``detect_keypoints`` stage: 21 hand keypoints + confidence per grasp-video frame.

Backends are a :class:`Backend`. ``openpose_json`` reads the session's per-frame
OpenPose JSON (the manifest's hand; with several people, the hand nearest the
previous frame's; empty ``people`` means no detection). ``mediapipe`` runs MediaPipe
Hands in-process on the colour frames (``graspcap.tasks.keypoints.mediapipe_detector``,
imported only when it runs). Without a backend in the config the stage takes the keypoint
files when the manifest names them, else MediaPipe; the result records which ran.

A bad frame (keypoint JSON that does not parse or holds 60 numbers instead of 63, NaN
coordinates, a corrupt or truncated JPEG, a frame of the wrong size) is a missing detection
with a :class:`FrameNote`, never a failure of the session.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np
from pydantic import Field

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.keypoints.mediapipe_detector import FrameMode, MediaPipeConfig
from graspcap.tasks.session.files import HAND_KEYS, JsonSyntaxError, load_json
from graspcap.tasks.session.load_session import Session

STAGE_VERSION = "detect_keypoints/2"
N_KEYPOINTS = 21


class Backend(StrEnum):
    OPENPOSE_JSON = "openpose_json"
    """The session's per-frame OpenPose JSON files (``grasp.keypoints``)."""
    MEDIAPIPE = "mediapipe"
    """MediaPipe Hands on the colour frames (``grasp.color``)."""


class DetectKeypointsConfig(StageConfig):
    backend: Backend | None = None
    """None: keypoint files when the manifest names them, else the image detector."""
    min_confidence: float = Field(0.05, ge=0.0, le=1.0)
    """Detections below this confidence are treated as missing (confidence set to 0)."""
    mediapipe: MediaPipeConfig = MediaPipeConfig()
    """The image detector's settings (used when the backend is ``mediapipe``)."""


PRESETS = {
    "default": DetectKeypointsConfig(),
    "fast": DetectKeypointsConfig(mediapipe=MediaPipeConfig(model_complexity=0)),
    "images": DetectKeypointsConfig(mediapipe=MediaPipeConfig(mode=FrameMode.IMAGES)),
}


@dataclass(frozen=True)
class FrameNote:
    """Why frame ``frame`` has no (or a partial) detection; ``file`` relative to the session."""

    frame: int
    file: str
    message: str

    def __str__(self) -> str:
        return f"frame {self.frame} ({self.file}): {self.message}"


@dataclass(frozen=True)
class Keypoints2D:
    """Per-frame hand keypoints of one session.

    Attributes
    ----------
    keypoints : (n_frames, 21, 3) float
        x_px, y_px, confidence in the colour image; confidence 0 where missing.
    backend : Backend
        What produced them.
    notes : tuple of FrameNote
        Frames that could not be read (missing detections) or held bad values.
    label_mismatch : (n_frames,) bool or None
        MediaPipe only: the kept hand carried the other hand's label.
    """

    keypoints: np.ndarray
    backend: Backend
    notes: tuple[FrameNote, ...] = ()
    label_mismatch: np.ndarray | None = field(default=None)

    @property
    def frames_with_hand(self) -> int:
        return int((self.keypoints[:, :, 2] > 0).any(axis=1).sum())

    @property
    def mean_confidence(self) -> float:
        conf = self.keypoints[:, :, 2]
        detected = conf[conf > 0]
        return float(detected.mean()) if detected.size else 0.0

    def summary(self) -> dict[str, object]:
        """Per-session numbers: frames, frames with a hand, mean confidence, backend, notes."""
        return {
            "backend": str(self.backend), "frames": len(self.keypoints),
            "frames_with_hand": self.frames_with_hand,
            "mean_confidence": round(self.mean_confidence, 4), "frame_notes": len(self.notes),
        }


def _clean(hand: np.ndarray, min_confidence: float) -> np.ndarray:
    hand = np.array(hand, dtype=float)
    bad = ~np.isfinite(hand).all(axis=1) | (hand[:, 2] < min_confidence)
    hand[bad] = 0.0
    return hand


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    both = (a[:, 2] > 0) & (b[:, 2] > 0)
    if not both.any():
        return np.inf
    return float(np.linalg.norm(a[both, :2] - b[both, :2], axis=1).mean())


def track_hands(
    candidates: Sequence[Sequence[np.ndarray]], config: DetectKeypointsConfig
) -> np.ndarray:
    """Pick one hand per frame from each frame's candidates (one per detected person).

    The first detection is the most confident candidate; after that, the candidate
    nearest the last picked hand. Returns ``(n_frames, 21, 3)``.
    """
    out = np.zeros((len(candidates), N_KEYPOINTS, 3))
    previous = None
    for i, frame in enumerate(candidates):
        hands = [_clean(h, config.min_confidence) for h in frame]
        hands = [h for h in hands if (h[:, 2] > 0).any()]
        if not hands:
            continue
        if previous is None or len(hands) == 1:
            pick = max(hands, key=lambda h: h[:, 2].sum()) if previous is None else hands[0]
        else:
            pick = min(hands, key=lambda h: _distance(h, previous))
        out[i] = pick
        previous = pick
    return out


def read_openpose_frame(path: Path, hand: str) -> tuple[list[np.ndarray], list[str]]:
    """One ``(21, 3)`` (x_px, y_px, conf) array per person for ``hand``, and notes.

    Never raises for a bad file: a file that does not parse, or a hand array without 63
    numbers, gives no hand (with a note); non-finite values or confidences outside [0, 1]
    make those keypoints missing (with a note). A person without the hand gets zeros.
    """
    document = load_json(path)
    if isinstance(document, JsonSyntaxError):
        return [], [document.message + "; no detection"]
    people = document.get("people") if isinstance(document, dict) else None
    if not isinstance(people, list):
        return [], ["no 'people' list; no detection"]
    key, hands, notes = HAND_KEYS[hand], [], []
    for p, person in enumerate(people):
        values = person.get(key) if isinstance(person, dict) else None
        if not values:
            hands.append(np.zeros((N_KEYPOINTS, 3)))
            continue
        if not isinstance(values, list) or len(values) != 3 * N_KEYPOINTS:
            n = len(values) if isinstance(values, list) else type(values).__name__
            notes.append(f"people[{p}].{key} must hold 63 numbers (21 x, y, c), got {n}; "
                         "no detection")
            continue
        ok = [isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
              for v in values]
        arr = np.array([v if good else np.nan for v, good in zip(values, ok, strict=True)],
                       dtype=float).reshape(N_KEYPOINTS, 3)
        bad = ~np.isfinite(arr).all(axis=1) | ~((arr[:, 2] >= 0) & (arr[:, 2] <= 1))
        if bad.any():
            notes.append(f"people[{p}].{key}: keypoint(s) {np.flatnonzero(bad).tolist()} not "
                         "finite or confidence outside [0, 1]; treated as missing")
            arr[bad] = 0.0
        hands.append(arr)
    return hands, notes


def _rel(session: Session, path: Path) -> str:
    return os.path.relpath(path, session.root)


def _openpose(session: Session, config: DetectKeypointsConfig) -> Keypoints2D:
    candidates, notes = [], []
    for i in range(session.manifest.grasp.count):
        path = session.grasp_path("keypoints", i)
        hands, messages = read_openpose_frame(path, str(session.manifest.hand))
        candidates.append(hands)
        notes += [FrameNote(i, _rel(session, path), m) for m in messages]
    return Keypoints2D(track_hands(candidates, config), Backend.OPENPOSE_JSON, tuple(notes))


def _mediapipe(session: Session, config: DetectKeypointsConfig) -> Keypoints2D:
    try:
        from graspcap.tasks.keypoints.mediapipe_detector import detect_frames, hands_module

        hands_module()
    except ImportError as exc:
        raise StageError(
            "detect_keypoints",
            f"backend mediapipe needs the mediapipe package ({exc}); install it as "
            "docs/detectors.md says (make setup does)",
            session=session.session_id,
        ) from exc
    camera = session.manifest.color_camera
    paths = [session.grasp_path("color", i) for i in range(session.manifest.grasp.count)]
    found = detect_frames(paths, (camera.width, camera.height), str(session.manifest.hand),
                          config.mediapipe)
    keypoints = np.array([_clean(k, config.min_confidence) for k in found.keypoints])
    keypoints = keypoints.reshape(len(paths), N_KEYPOINTS, 3)
    notes = tuple(FrameNote(i, _rel(session, paths[i]), m) for i, m in found.notes)
    return Keypoints2D(keypoints, Backend.MEDIAPIPE, notes, found.label_mismatch)


def choose_backend(session: Session, config: DetectKeypointsConfig) -> Backend:
    """The configured backend, or keypoint files when the manifest names them, else
    MediaPipe; raises :class:`StageError` when the session lacks what that backend reads."""
    grasp = session.manifest.grasp
    backend = config.backend or (
        Backend.OPENPOSE_JSON if grasp.keypoints is not None else Backend.MEDIAPIPE
    )
    needs = {Backend.OPENPOSE_JSON: "keypoints", Backend.MEDIAPIPE: "color"}[backend]
    if getattr(grasp, needs) is None:
        raise StageError(
            "detect_keypoints", f"backend {backend} needs grasp.{needs} in session.json",
            session=session.session_id,
        )
    return backend


def detect_keypoints(session: Session, config: DetectKeypointsConfig) -> Keypoints2D:
    """Run the configured (or automatically chosen) backend on a session."""
    if choose_backend(session, config) is Backend.OPENPOSE_JSON:
        return _openpose(session, config)
    return _mediapipe(session, config)
