"""The ``detect_keypoints`` stage: 21 hand keypoints + confidence per grasp-video frame.

Backends are a :class:`Backend`. ``openpose_json`` reads the session's per-frame
OpenPose JSON (the manifest's hand; with several people, the hand nearest the
previous frame's; empty ``people`` means no detection). A detector on colour
frames (MediaPipe) is not built yet: a session without keypoint files fails with
that reason.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from pydantic import Field

from graspcap.tasks.config import StageConfig
from graspcap.tasks.errors import StageError
from graspcap.tasks.load_session import Session

STAGE_VERSION = "detect_keypoints/1"
N_KEYPOINTS = 21


class Backend(StrEnum):
    OPENPOSE_JSON = "openpose_json"


class DetectKeypointsConfig(StageConfig):
    backend: Backend | None = None
    """None: keypoint files when the manifest names them, else the image detector."""
    min_confidence: float = Field(0.05, ge=0.0, le=1.0)
    """Detections below this confidence are treated as missing (confidence set to 0)."""


PRESETS = {"default": DetectKeypointsConfig()}


@dataclass(frozen=True)
class Keypoints2D:
    """Per-frame hand keypoints of one session.

    Attributes
    ----------
    keypoints : (n_frames, 21, 3) float
        x_px, y_px, confidence in the colour image; confidence 0 where missing.
    backend : Backend
        What produced them.
    """

    keypoints: np.ndarray
    backend: Backend

    @property
    def frames_with_hand(self) -> int:
        return int((self.keypoints[:, :, 2] > 0).any(axis=1).sum())

    @property
    def mean_confidence(self) -> float:
        conf = self.keypoints[:, :, 2]
        detected = conf[conf > 0]
        return float(detected.mean()) if detected.size else 0.0


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


def detect_keypoints(session: Session, config: DetectKeypointsConfig) -> Keypoints2D:
    """Run the configured (or automatically chosen) backend on a session."""
    has_files = session.manifest.grasp.keypoints is not None
    backend = config.backend or (Backend.OPENPOSE_JSON if has_files else None)
    if backend is None:
        raise StageError(
            "detect_keypoints",
            "the manifest names no grasp.keypoints files and no image detector is built yet",
            session=session.session_id,
        )
    if not has_files:
        raise StageError(
            "detect_keypoints", "backend openpose_json needs grasp.keypoints in session.json",
            session=session.session_id,
        )
    frames = [session.read_keypoints(i) for i in range(session.manifest.grasp.count)]
    return Keypoints2D(track_hands(frames, config), backend)
