"""MediaPipe Hands, in-process, on colour frames: the image detector of ``detect_keypoints``.

This module imports without MediaPipe; :func:`hands_module` imports it on first use
(``mediapipe.solutions.hands``, the legacy API whose palm and landmark models ship inside
the 0.10.21 wheel, so nothing is downloaded at run time) with its glog/absl chatter on
stderr swallowed; ``graspcap.tasks.keypoints.mediapipe_graph`` holds that and the tuned graph
(inference threads, a lean ``process``), ``graspcap.tasks.session.frame_reader`` the decoding
(straight to RGB, a reader thread ahead of the detector). See ``docs/detectors.md`` for
the install and the measurements.

Handedness: MediaPipe labels hands as if the image were a mirrored selfie; on an
unmirrored camera image its "Left" is the person's right hand (checked on the shared
photos, see the docs). :data:`TRUE_HAND` undoes that unless ``mirrored`` is set.

Confidence: the legacy API leaves per-landmark visibility and presence at 0, so each of
the 21 keypoints of a hand gets the hand's handedness score (the classifier's certainty of
its label), the only per-hand score it returns.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.keypoints.mediapipe_graph import (
    HandsOutput,
    hands_module,
    quiet_stderr,
    tuned_hands,
)
from graspcap.tasks.session.frame_reader import iter_frames, read_rgb

__all__ = ["hands_module", "read_rgb"]  # re-exported: the CLI, the stage and the bench use them

log = logging.getLogger(__name__)
N_KEYPOINTS = 21
HandName = Literal["right", "left"]
TRUE_HAND: dict[str, HandName] = {"Left": "right", "Right": "left"}
"""MediaPipe's label on an unmirrored image -> the person's hand."""


class FrameMode(StrEnum):
    VIDEO = "video"
    """MediaPipe's tracker: the landmarks of one frame seed the hand region of the next; palm
    detection runs again only when the hand is lost (``static_image_mode=False``)."""
    IMAGES = "images"
    """Every frame on its own: palm detection + landmarks each time."""


class HandednessPolicy(StrEnum):
    PREFER = "prefer"
    """The hand labelled as the manifest's hand when there is one, else the best other
    (a single visible hand is kept even when MediaPipe calls it the other hand)."""
    STRICT = "strict"
    """Only a hand labelled as the manifest's hand; otherwise no detection."""


class MediaPipeConfig(StageConfig):
    model_complexity: int = Field(1, ge=0, le=1)
    """0: lite landmark model, 1: full landmark model."""
    min_detection_confidence: float = Field(0.5, ge=0.0, le=1.0)
    """Palm detection threshold (MediaPipe's own)."""
    min_tracking_confidence: float = Field(0.5, ge=0.0, le=1.0)
    """Below this hand presence the tracker falls back to palm detection (video mode)."""
    mode: FrameMode = FrameMode.VIDEO
    """Track between consecutive frames or detect every frame on its own."""
    handedness: HandednessPolicy = HandednessPolicy.PREFER
    """How to use MediaPipe's left/right label to pick the manifest's hand."""
    mirrored: bool = False
    """Frames are mirrored (selfie) images: take MediaPipe's labels as they are."""
    workers: int | None = Field(1, ge=1)
    """Processes per session, each tracking its own chunk of consecutive frames; None: the
    CPU count capped at 2. 1 by default: a worker costs ~3 s of CPU to start (about 90
    frames of tracking), and a build already runs sessions side by side
    (``bench/detect_speed.py``, ``docs/detectors.md``)."""
    min_frames_per_worker: int = Field(200, ge=1)
    """Chunks are at least this long, so a worker's start-up is paid back."""
    threads: int = Field(1, ge=1, le=8)
    """Threads of each TFLite inference (XNNPACK's ``num_threads``, palm and landmark
    models). 1 by default (MediaPipe's own desktop default): a build runs two stages side by
    side on the 2 cores, and XNNPACK's spinning worker threads then burn several times the
    CPU they save. 2 when the detector has both cores to itself (``docs/detectors.md``)."""
    prefetch: int = Field(2, ge=0, le=16)
    """Frames a reader thread decodes ahead while MediaPipe runs the current one (0: decode
    on the calling thread). The detections do not depend on it."""


@dataclass(frozen=True)
class Candidate:
    """One hand MediaPipe found in an image.

    Attributes
    ----------
    xy_px : (21, 2) float
        Landmarks in image pixels.
    hand : str
        The person's hand ("right"/"left"), MediaPipe's label un-mirrored.
    score : float
        MediaPipe's handedness score of its label.
    inside : (21,) bool
        Landmark inside the image (MediaPipe extrapolates the others).
    """

    xy_px: np.ndarray
    hand: HandName
    score: float
    inside: np.ndarray

    def keypoints(self) -> np.ndarray:
        """``(21, 3)`` x_px, y_px, confidence: the hand's score on every keypoint inside the
        image, 0 outside."""
        return np.column_stack([self.xy_px, np.where(self.inside, self.score, 0.0)])


@dataclass(frozen=True)
class FrameDetections:
    """MediaPipe on a run of frames.

    Attributes
    ----------
    keypoints : (n, 21, 3) float
        x_px, y_px, confidence; all 0 where no hand was picked.
    label_mismatch : (n,) bool
        The picked hand carries the other hand's label (kept under ``prefer``).
    notes : tuple of (int, str)
        ``(frame, message)`` for frames that could not be read.
    workers : int
        Processes that ran.
    """

    keypoints: np.ndarray
    label_mismatch: np.ndarray
    notes: tuple[tuple[int, str], ...]
    workers: int


class Detector:
    """One MediaPipe ``Hands`` graph (it keeps tracking state between calls in video mode)."""

    def __init__(self, config: MediaPipeConfig, *, video: bool, max_hands: int):
        self.config = config
        with quiet_stderr():
            self._hands = tuned_hands()(
                inference_threads=config.threads,
                static_image_mode=not video,
                max_num_hands=max_hands,
                model_complexity=config.model_complexity,
                min_detection_confidence=config.min_detection_confidence,
                min_tracking_confidence=config.min_tracking_confidence,
            )
            # the graph opens its models (and logs) in its own threads after Hands() returns;
            # a first frame waits for that
            self._hands.process(np.zeros((64, 64, 3), np.uint8))
        self._quiet_calls = 2
        """The first frames with a hand log once more (landmark projection): stderr stays
        hidden until two calls after the first hand."""
        self._done: HandsOutput | None = None

    def __call__(self, rgb: np.ndarray) -> list[Candidate]:
        """Hands in an ``(h, w, 3) uint8`` RGB image (a read-only array, as :func:`read_rgb`
        returns, is passed by reference; a writable one is copied by MediaPipe)."""
        return self.candidates(self.process(rgb), rgb.shape[:2])

    def process(self, rgb: np.ndarray) -> HandsOutput:
        """MediaPipe's own output for ``rgb`` (``multi_hand_landmarks``, ...)."""
        if self._quiet_calls <= 0:
            return self._hands.process(rgb)
        with quiet_stderr():
            result = self._hands.process(rgb)
        if result.multi_hand_landmarks or self._quiet_calls < 2:
            self._quiet_calls -= 1
        return result

    def send(self, rgb: np.ndarray) -> None:
        """Start on ``rgb``; :meth:`wait` gives the raw output for :meth:`candidates`, which
        may run while the graph works on the next frame (the first frames, while MediaPipe
        still logs, run at once)."""
        self._done = self.process(rgb) if self._quiet_calls > 0 else None
        if self._done is None:
            self._hands.send(rgb)

    def wait(self) -> Any:
        return self._done if self._done is not None else self._hands.wait()

    def candidates(self, result: Any, shape: tuple[int, int]) -> list[Candidate]:
        """:meth:`process`'s (or :meth:`wait`'s) output for an image of ``shape`` (h, w)."""
        if not isinstance(result, HandsOutput):
            result = self._hands.outputs(result)
        h, w = shape
        out = []
        for lms, cls in zip(
            result.multi_hand_landmarks or [], result.multi_handedness or [], strict=True
        ):
            xy = np.array([[p.x * w, p.y * h] for p in lms.landmark], dtype=float)
            label = cls.classification[0]
            hand = label.label.lower() if self.config.mirrored else TRUE_HAND[label.label]
            inside = (xy >= 0).all(axis=1) & (xy[:, 0] < w) & (xy[:, 1] < h)
            out.append(Candidate(xy, hand, float(label.score), inside))
        return out

    def close(self) -> None:
        self._hands.close()


def _mean_distance_px(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=1).mean())


def pick(
    candidates: Sequence[Candidate],
    hand: HandName,
    previous: np.ndarray | None,
    policy: HandednessPolicy,
) -> Candidate | None:
    """The manifest's hand among ``candidates``: labelled ``hand`` first (any under
    ``prefer`` when none is), then nearest ``previous`` ((21, 3), conf > 0 used) or the
    highest score."""
    matching = [c for c in candidates if c.hand == hand]
    pool = matching or (list(candidates) if policy is HandednessPolicy.PREFER else [])
    if not pool:
        return None
    if previous is not None and (previous[:, 2] > 0).any():
        seen = previous[:, 2] > 0
        return min(pool, key=lambda c: _mean_distance_px(c.xy_px[seen], previous[seen, :2]))
    return max(pool, key=lambda c: c.score)


# --- frames -> keypoints ------------------------------------------------------------------


@dataclass(frozen=True)
class FrameResult:
    """MediaPipe on one frame of a video.

    Attributes
    ----------
    index : int
        The frame's position in the run.
    keypoints : (21, 3) float
        x_px, y_px, confidence; all 0 when no hand was picked.
    label_mismatch : bool
        The picked hand carries the other hand's label.
    note : str
        Why the frame could not be read ("" when it was).
    """

    index: int
    keypoints: np.ndarray
    label_mismatch: bool
    note: str


class _Chooser:
    """The manifest's hand from each frame's candidates, frames in order.

    Video: one hand is tracked; when it carries the other hand's label, a second, two-hand
    detector looks at that frame once (its hands replace the tracked one if one has the
    manifest's label; otherwise the tracked hand is kept without looking again while it is
    tracked). Then :func:`pick`, seeded by the previous frame's keypoints.
    """

    def __init__(self, config: MediaPipeConfig, hand: HandName, video: bool):
        self.config, self.hand, self.video = config, hand, video
        self.both: Detector | None = None
        self.previous: np.ndarray | None = None
        self.settled = False  # the tracked hand is the best there is

    def __call__(self, i: int, rgb: np.ndarray, candidates: list[Candidate]) -> FrameResult:
        hand = self.hand
        self.settled = self.settled and bool(candidates)
        if self.video and candidates and not self.settled and all(
            c.hand != hand for c in candidates
        ):
            self.both = self.both or Detector(self.config, video=False, max_hands=2)
            again = self.both(rgb)
            if any(c.hand == hand for c in again):
                candidates = again
            else:
                self.settled = True
        chosen = pick(candidates, hand, self.previous, self.config.handedness)
        if chosen is None:
            return FrameResult(i, np.zeros((N_KEYPOINTS, 3)), False, "")
        self.previous = chosen.keypoints()
        return FrameResult(i, self.previous, chosen.hand != hand, "")

    def close(self) -> None:
        if self.both is not None:
            self.both.close()


def iter_detections(
    paths: Sequence[Path | str], size: tuple[int, int] | None, hand: HandName,
    config: MediaPipeConfig,
) -> Iterator[FrameResult]:
    """One tracker over consecutive frames, a :class:`FrameResult` per frame in order.

    Frames are decoded ``config.prefetch`` ahead by a reader thread, and the graph runs one
    frame ahead of the Python side: while it works on frame i, frame i-1's output becomes
    arrays, is chosen from and yielded. The graph's input is the frames alone, so the
    results are those of running frame by frame.
    """
    video = config.mode is FrameMode.VIDEO
    main = Detector(config, video=video, max_hands=1 if video else 2)
    choose = _Chooser(config, hand, video)
    frames = iter_frames(paths, size, config.prefetch)
    running: tuple[int, np.ndarray] | None = None  # (index, image) the graph works on
    try:
        for i, (rgb, why) in enumerate(frames):
            raw = main.wait() if running else None
            if rgb is not None:
                main.send(rgb)
            if running:
                yield choose(*running, main.candidates(raw, running[1].shape[:2]))
            running = None if rgb is None else (i, rgb)
            if rgb is None:
                yield FrameResult(i, np.zeros((N_KEYPOINTS, 3)), False, why)
        if running:
            yield choose(*running, main.candidates(main.wait(), running[1].shape[:2]))
    finally:
        frames.close()
        main.close()
        choose.close()


def _detect_chunk(
    paths: Sequence[str], size: tuple[int, int] | None, hand: HandName, config: MediaPipeConfig
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, str]]]:
    """:func:`iter_detections` collected (runs in a worker process or in-process)."""
    n = len(paths)
    keypoints, mismatch, notes = np.zeros((n, N_KEYPOINTS, 3)), np.zeros(n, bool), []
    for r in iter_detections(paths, size, hand, config):
        keypoints[r.index], mismatch[r.index] = r.keypoints, r.label_mismatch
        if r.note:
            notes.append((r.index, r.note))
    return keypoints, mismatch, notes


def worker_count(config: MediaPipeConfig, n_frames: int) -> int:
    """Processes to use: ``workers`` (or the CPU count capped at 2), no more than chunks of
    ``min_frames_per_worker``, and 1 inside a daemon process (which may not have children)."""
    wanted = config.workers or min(os.cpu_count() or 1, 2)
    by_length = max(1, n_frames // config.min_frames_per_worker)
    if multiprocessing.current_process().daemon:
        return 1
    return max(1, min(wanted, by_length, n_frames))


def detect_frames(
    paths: Sequence[Path | str],
    size: tuple[int, int] | None,
    hand: HandName,
    config: MediaPipeConfig,
) -> FrameDetections:
    """MediaPipe on the frames at ``paths`` (in video order) of a ``size`` (width, height)
    camera; one hand per frame, the manifest's ``hand``. Frames that cannot be read are
    missing detections with a note, never an exception."""
    paths = [str(p) for p in paths]
    workers = worker_count(config, len(paths))
    if workers == 1:
        kp, mismatch, notes = _detect_chunk(paths, size, hand, config)
        return FrameDetections(kp, mismatch, tuple(notes), 1)
    bounds = np.linspace(0, len(paths), workers + 1).round().astype(int)
    chunks = [paths[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    ctx = multiprocessing.get_context("spawn")  # fork is unsafe under Prefect/Open3D threads
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
        parts = list(pool.map(_detect_chunk, chunks, [size] * workers, [hand] * workers,
                              [config] * workers))
    notes = tuple((int(a) + i, m) for a, (_, _, ns) in zip(bounds, parts, strict=False)
                  for i, m in ns)
    return FrameDetections(
        np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), notes,
        workers,
    )

