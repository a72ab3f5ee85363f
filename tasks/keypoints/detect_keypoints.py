"""The ``detect_keypoints`` stage: 21 hand keypoints + confidence per grasp-video frame.

Backends are a :class:`Backend`. ``openpose_json`` reads the session's per-frame
OpenPose JSON (the manifest's hand; with several people, the hand nearest the
previous frame's; empty ``people`` means no detection). ``mediapipe`` runs MediaPipe
Hands in-process on the colour frames (``graspcap.tasks.keypoints.mediapipe_detector``,
imported only when it runs). Without a backend in the config the stage takes the keypoint
files when the manifest names them, else MediaPipe; the result records which ran.

A bad frame (keypoint JSON that does not parse or holds 60 numbers instead of 63, NaN
coordinates, a corrupt or truncated JPEG, a frame of the wrong size) is a missing detection
with a :class:`FrameNote`, never a failure of the session. So are keypoints far outside the
image (``off_image_share``) and a frame whose joints do not form the hand its neighbours show
(all at one point, or scattered: :func:`corrupt_frames`), which would otherwise move the steady
onset without a word. ``Keypoints2D.qa_notes`` counts them, names their files, and counts the
frames with more than one candidate hand; ``missing_summary`` says why frames lack the hand
for the stages that fail on too few. Keypoint files that hold only the other hand fail the
stage with that reason (the manifest's ``hand`` is likely wrong).
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

STAGE_VERSION = "detect_keypoints/3"
STAGE = "detect_keypoints"
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
    off_image_share: float = Field(1.0, ge=0.0)
    """A keypoint more than this share of the image's width (x) or height (y) outside the
    image is no detection: no detector run on the image puts one there."""
    collapse_share: float = Field(0.2, ge=0.0, le=1.0)
    """A frame whose joints spread (RMS distance from their centroid) less than this share of
    the session's median spread is corrupt (all joints at one point)."""
    corrupt_hand_sizes: float = Field(0.75, gt=0.0)
    """A frame whose joints lie, at their median, farther than this many median spreads from
    the midpoint of its two neighbouring frames (which agree with each other better than that)
    is corrupt (joints shuffled or scattered). Per-joint outliers and finger swaps leave the
    median alone."""
    corrupt_shape: float = Field(0.5, gt=0.0)
    """A frame whose shape differs from both neighbouring frames' by more than this (median
    joint distance after the best 2D similarity, over the neighbour's spread), while they
    differ from each other by less than 0.7 of that, is corrupt; 1.3 times this against a
    neighbour on one side only. On 12 synthetic sessions of 120 frames it found 91 % of
    shuffled frames and none of the 1416 good ones (realistic detector noise); 3 of 1416 under
    the hard preset's finger swaps and outliers."""


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
    hand : str
        The manifest's hand (``right`` / ``left``).
    other_hand_frames : tuple of int
        Frames with no detection of ``hand`` whose keypoint file holds the other hand.
    off_image_frames, corrupt_frames : tuple of int
        Frames with keypoints far outside the image (treated as missing), and frames dropped
        as corrupt (:func:`corrupt_frames`).
    multi_candidate_frames : int
        Frames with more than one candidate hand (people); the tracked one was kept.
    """

    keypoints: np.ndarray
    backend: Backend
    notes: tuple[FrameNote, ...] = ()
    label_mismatch: np.ndarray | None = field(default=None)
    hand: str = ""
    other_hand_frames: tuple[int, ...] = ()
    off_image_frames: tuple[int, ...] = ()
    corrupt_frames: tuple[int, ...] = ()
    multi_candidate_frames: int = 0

    @property
    def frames_with_hand(self) -> int:
        return int((self.keypoints[:, :, 2] > 0).any(axis=1).sum())

    @property
    def mean_confidence(self) -> float:
        conf = self.keypoints[:, :, 2]
        detected = conf[conf > 0]
        return float(detected.mean()) if detected.size else 0.0

    def _files(self, frames: Sequence[int], at_most: int = 5) -> str:
        """The files of ``frames`` (from the notes), at most ``at_most`` named, then a count."""
        file_of = {n.frame: n.file for n in self.notes}
        shown = [file_of.get(f, f"frame {f}") for f in frames[:at_most]]
        more = f" and {len(frames) - at_most} more" if len(frames) > at_most else ""
        return ", ".join(shown) + more

    def qa_notes(self) -> list[str]:
        """What a person may want to know about the detections, for the QA report's notes."""
        n, notes = len(self.keypoints), []
        if self.multi_candidate_frames:
            notes.append(f"detect_keypoints: {self.multi_candidate_frames} of {n} frames had more "
                         f"than one {self.hand} hand (several people); the one nearest the "
                         "previous frame's hand was used (the most confident at the first)")
        if self.other_hand_frames:
            notes.append(f"detect_keypoints: {len(self.other_hand_frames)} of {n} frames have "
                         f"only the other hand, no {self.hand} hand "
                         f"({self._files(self.other_hand_frames)})")
        if self.off_image_frames:
            notes.append(f"detect_keypoints: {len(self.off_image_frames)} frame(s) had keypoints "
                         f"far outside the image, treated as not detected "
                         f"({self._files(self.off_image_frames)})")
        if self.corrupt_frames:
            notes.append(f"detect_keypoints: {len(self.corrupt_frames)} frame(s) whose joints do "
                         f"not form the hand of their neighbours were dropped "
                         f"({self._files(self.corrupt_frames)})")
        return notes

    def missing_summary(self) -> str:
        """Why frames lack the hand, for a stage that fails on too few; empty when nothing
        but plain missed detections explains it."""
        causes = []
        if self.other_hand_frames:
            causes.append(f"{len(self.other_hand_frames)} hold only the other hand (check "
                          "`hand` in session.json)")
        if self.off_image_frames:
            causes.append(f"{len(self.off_image_frames)} had keypoints far outside the image "
                          f"({self._files(self.off_image_frames)})")
        if self.corrupt_frames:
            causes.append(f"{len(self.corrupt_frames)} were dropped as corrupt "
                          f"({self._files(self.corrupt_frames)})")
        unreadable = sorted({note.frame for note in self.notes} - set(self.off_image_frames)
                            - set(self.corrupt_frames) - set(self.other_hand_frames))
        if unreadable:
            causes.append(f"{len(unreadable)} have a note ({self._files(unreadable)})")
        if not causes:
            return ""
        return (f"of {len(self.keypoints)} frames, {self.frames_with_hand} have a {self.hand} "
                f"hand detected; {'; '.join(causes)}")

    def summary(self) -> dict[str, object]:
        """Per-session numbers: frames, frames with a hand, mean confidence, backend, notes."""
        return {
            "backend": str(self.backend), "frames": len(self.keypoints),
            "frames_with_hand": self.frames_with_hand,
            "mean_confidence": round(self.mean_confidence, 4), "frame_notes": len(self.notes),
        }


def why_missing(keypoints: Keypoints2D) -> str:
    """``keypoints.missing_summary()`` for the stages that fail on too few detections; empty
    for a result cached before :class:`Keypoints2D` had one."""
    summary = getattr(keypoints, "missing_summary", None)
    return summary() if summary is not None else ""


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


def off_image(hand: np.ndarray, size: tuple[int, int], share: float) -> np.ndarray:
    """``(21,) bool``: detected keypoints of ``hand (21, 3)`` more than ``share`` of the image
    ``size (width, height)`` outside it."""
    w, h = size
    x, y = hand[:, 0], hand[:, 1]
    far = (x < -share * w) | (x > (1 + share) * w) | (y < -share * h) | (y > (1 + share) * h)
    return far & (hand[:, 2] > 0)


def _spread(hand: np.ndarray) -> float:
    xy = hand[hand[:, 2] > 0, :2]
    return float(np.sqrt(((xy - xy.mean(0)) ** 2).sum(1).mean()))


def _median_gap(a: np.ndarray, b: np.ndarray, min_joints: int) -> float:
    both = (a[:, 2] > 0) & (b[:, 2] > 0)
    if both.sum() < min_joints:
        return np.nan
    return float(np.median(np.linalg.norm(a[both, :2] - b[both, :2], axis=1)))


def shape_gap(a: np.ndarray, b: np.ndarray, min_joints: int = 6) -> float:
    """Median distance between the joints detected in both ``a`` and ``b`` (21, 3) after the
    2D similarity that best maps ``a`` onto ``b``, over ``b``'s spread; NaN with fewer than
    ``min_joints`` such joints."""
    both = (a[:, 2] > 0) & (b[:, 2] > 0)
    if both.sum() < min_joints:
        return np.nan
    za = a[both, 0] + 1j * a[both, 1]
    zb = b[both, 0] + 1j * b[both, 1]
    za, zb = za - za.mean(), zb - zb.mean()
    size = float(np.sqrt((np.abs(zb) ** 2).mean()))
    norm = float((np.abs(za) ** 2).sum())
    if size <= 0 or norm <= 0:
        return np.nan
    c = (np.conj(za) @ zb) / norm
    return float(np.median(np.abs(c * za - zb)) / size)


def corrupt_frames(keypoints: np.ndarray, config: DetectKeypointsConfig,
                   min_joints: int = 6) -> dict[int, str]:
    """Frames of ``keypoints (n, 21, 3)`` whose joints do not form the hand the video shows,
    with why: spread below ``collapse_share`` of the median spread (all at one point); or,
    against the nearest judged frame on each side (at most 2 frames away), at the median
    farther than ``corrupt_hand_sizes`` median spreads from their midpoint, or a shape
    (:func:`shape_gap`) further than ``corrupt_shape`` from both, while the two agree with each
    other better; against the one neighbour at a video's end or a gap, a shape further than
    1.3 times ``corrupt_shape``.
    Frames with fewer than ``min_joints`` detected joints are not judged; fewer than 3 judged
    frames, none."""
    kp = np.asarray(keypoints, dtype=float)
    judged = np.flatnonzero((kp[:, :, 2] > 0).sum(1) >= min_joints)
    if len(judged) < 3:
        return {}
    spread = np.array([_spread(kp[i]) for i in judged])
    size = float(np.median(spread))
    if size <= 0:
        return {}
    bad = {int(i): f"the detected joints spread {s:.1f} px, the session's median {size:.1f} px "
                   "(all at one point)"
           for i, s in zip(judged, spread, strict=True) if s < config.collapse_share * size}
    good = [int(i) for i in judged if int(i) not in bad]
    limit = config.corrupt_hand_sizes * size
    for j, i in enumerate(good):
        prev = good[j - 1] if j > 0 and i - good[j - 1] <= 2 else None
        nxt = good[j + 1] if j + 1 < len(good) and good[j + 1] - i <= 2 else None
        if prev is not None and nxt is not None:
            t = (i - prev) / (nxt - prev)
            mid = kp[prev].copy()
            mid[:, :2] = (1 - t) * kp[prev, :, :2] + t * kp[nxt, :, :2]
            mid[:, 2] = np.minimum(kp[prev, :, 2], kp[nxt, :, 2])
            gap, apart = _median_gap(kp[i], mid, min_joints), _median_gap(
                kp[prev], kp[nxt], min_joints)
            shape = min(shape_gap(kp[i], kp[prev]), shape_gap(kp[i], kp[nxt]))
            if gap > limit and apart < gap:
                bad[i] = (f"the joints lie {gap:.0f} px (median) from where frames {prev} and "
                          f"{nxt} put them, {gap / size:.1f} hand spreads (shuffled or garbage)")
            elif shape > config.corrupt_shape and shape_gap(kp[nxt], kp[prev]) < 0.7 * shape:
                bad[i] = (f"the joints do not form the hand of frames {prev} and {nxt} (shape "
                          f"difference {shape:.2f} of its size; shuffled or garbage)")
        elif (prev is None) != (nxt is None):  # by shape alone: a hand may move fast here
            other = prev if prev is not None else nxt
            shape = shape_gap(kp[i], kp[other])
            if shape > 1.3 * config.corrupt_shape:
                bad[i] = (f"the joints do not form the hand of frame {other} (shape difference "
                          f"{shape:.2f} of its size; shuffled or garbage)")
    return dict(sorted(bad.items()))


def track_hands(
    candidates: Sequence[Sequence[np.ndarray]], config: DetectKeypointsConfig
) -> np.ndarray:
    """Pick one hand per frame from each frame's candidates (one per detected person).

    The first detection is the most confident candidate; after that, the candidate
    nearest the last picked hand (ties: the first in the file). Returns ``(n_frames, 21, 3)``.
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
    return _hands_in(document, hand)


def _hands_in(document: object, hand: str) -> tuple[list[np.ndarray], list[str]]:
    """:func:`read_openpose_frame` on a parsed document."""
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


def _detected(hands: Sequence[np.ndarray], config: DetectKeypointsConfig) -> int:
    return sum(bool((_clean(h, config.min_confidence)[:, 2] > 0).any()) for h in hands)


def _drop_off_image(hands: list[np.ndarray], size: tuple[int, int], share: float
                    ) -> tuple[list[np.ndarray], str | None]:
    """``hands`` with their keypoints far outside the image set missing, and a note."""
    out, dropped = [], []
    for p, hand in enumerate(hands):
        far = off_image(hand, size, share)
        if far.any():
            hand = hand.copy()
            worst = hand[far][np.argmax(np.abs(hand[far, :2]).max(1)), :2]
            dropped.append(f"people[{p}] keypoint(s) {np.flatnonzero(far).tolist()} (e.g. at "
                           f"{worst[0]:.3g}, {worst[1]:.3g} px)")
            hand[far] = 0.0
        out.append(hand)
    if not dropped:
        return out, None
    w, h = size
    return out, (f"{'; '.join(dropped)} far outside the {w}x{h} image; treated as not "
                 "detected")


def _finish(session: Session, config: DetectKeypointsConfig, keypoints: np.ndarray,
            notes: list[FrameNote], file_of: Sequence[str], **fields) -> Keypoints2D:
    """Drop corrupt frames (with notes) and assemble the result."""
    keypoints = np.array(keypoints, dtype=float)
    corrupt = corrupt_frames(keypoints, config)
    for i, why in corrupt.items():
        keypoints[i] = 0.0
        notes.append(FrameNote(i, file_of[i], f"{why}; frame dropped (no detection)"))
    notes.sort(key=lambda note: note.frame)
    return Keypoints2D(keypoints, notes=tuple(notes), hand=str(session.manifest.hand),
                       corrupt_frames=tuple(corrupt), **fields)


def _openpose(session: Session, config: DetectKeypointsConfig) -> Keypoints2D:
    hand = str(session.manifest.hand)
    other = "left" if hand == "right" else "right"
    camera = session.manifest.color_camera
    size = (camera.width, camera.height)
    candidates, notes, files, other_only, far_frames = [], [], [], [], []
    for i in range(session.manifest.grasp.count):
        path = session.grasp_path("keypoints", i)
        files.append(_rel(session, path))
        document = load_json(path)
        if isinstance(document, JsonSyntaxError):
            hands, messages = [], [document.message + "; no detection"]
        else:
            hands, messages = _hands_in(document, hand)
            hands, far = _drop_off_image(hands, size, config.off_image_share)
            if far:
                messages.append(far)
                far_frames.append(i)
            others = _drop_off_image(_hands_in(document, other)[0], size, config.off_image_share)
            if not _detected(hands, config) and _detected(others[0], config):
                other_only.append(i)
                messages.append(f"only the {other} hand ({HAND_KEYS[other]}), none "
                                f"{HAND_KEYS[hand]}; no detection")
        candidates.append(hands)
        notes += [FrameNote(i, files[i], m) for m in messages]
    with_hand = sum(_detected(c, config) > 0 for c in candidates)
    if other_only and with_hand == 0:
        raise StageError(
            STAGE,
            f"the keypoint files hold the other hand: {len(other_only)} of {len(files)} frames "
            f"have {HAND_KEYS[other]}, none has {HAND_KEYS[hand]} (session.json says hand: "
            f"{hand}); check `hand` in session.json (e.g. {files[other_only[0]]})",
            session=session.session_id,
        )
    multi = sum(_detected(c, config) > 1 for c in candidates)
    return _finish(session, config, track_hands(candidates, config), notes, files,
                   backend=Backend.OPENPOSE_JSON, other_hand_frames=tuple(other_only),
                   off_image_frames=tuple(far_frames), multi_candidate_frames=multi)


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
    files = [_rel(session, p) for p in paths]
    notes = [FrameNote(i, files[i], m) for i, m in found.notes]
    far_frames = []
    for i in range(len(paths)):
        hands, far = _drop_off_image([keypoints[i]], (camera.width, camera.height),
                                     config.off_image_share)
        if far:
            keypoints[i] = hands[0]
            far_frames.append(i)
            notes.append(FrameNote(i, files[i], far))
    return _finish(session, config, keypoints, notes, files, backend=Backend.MEDIAPIPE,
                   label_mismatch=found.label_mismatch, off_image_frames=tuple(far_frames))


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
