"""The depth work of ``reconstruct_hand``, each frame done once per stage call.

Every solve of the stage (the pair scoring of the two-view start, the depth sweep of the
scale and the range factors, the dense depth links, the depth initialisation of a restart)
reads the aligned depth at the same keypoints, and the links the same surfaces. Both are
functions of the frame alone: the readings at every usable keypoint (a reading depends only
on its own pixel's neighbourhood) and the surface around the hand's centre, placed by the
readings of the confident keypoints. :class:`DepthSweep` computes them once per frame, on
first use or ahead on a second thread (``background``): decoding a 16-bit depth PNG is most
of the work and OpenCV does it without the GIL, so it overlaps the solves when a core is
free. Which thread computes a frame changes nothing in its values.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.hand_sfm.metric_scale import DepthLookup
from graspcap.tasks.hand_sfm.surface_clouds import SurfaceCloud


@dataclass(frozen=True)
class FrameDepth:
    """Depth of one solve frame.

    readings : (21,) metres at the usable keypoints (0 where the sensor has none), NaN at the
        others; surface : the frame's surface for the depth links, None without.
    """

    readings: np.ndarray
    surface: SurfaceCloud | None


def frame_depth(
    i: int,
    uv: np.ndarray,
    usable: np.ndarray,
    depth_at: DepthLookup,
    first_frame: int,
    surface_at: Callable[[int, np.ndarray, np.ndarray], SurfaceCloud | None] | None = None,
    confident: np.ndarray | None = None,
) -> FrameDepth:
    """The :class:`FrameDepth` of solve frame ``i`` (video frame ``first_frame + i``).

    uv : (m, 21, 2) pixels; usable : (m, 21) bool, keypoints that get a reading.
    surface_at : ``(i, uv (k, 2), depth (k,)) -> surface`` from the readings of the
        ``confident`` (m, 21) keypoints of the frame, when given and the frame has any.
    """
    j = np.flatnonzero(usable[i])
    readings = np.full(usable.shape[1], np.nan)
    if len(j):
        readings[j] = np.asarray(depth_at(first_frame + int(i), uv[i, j]), dtype=float)
    surface = None
    if surface_at is not None and confident is not None:
        c = np.flatnonzero(confident[i] & usable[i])
        if len(c):
            surface = surface_at(int(i), uv[i, c], readings[c])
    return FrameDepth(readings, surface)


class DepthSweep:
    """:class:`FrameDepth` per solve frame, computed once: by :meth:`get` on first use, or
    ahead in ``order`` on a second thread (``background``), whichever comes first.

    Use as a context manager: leaving it stops the second thread after its current frame.
    A frame whose computation raised re-raises from :meth:`get`.
    """

    def __init__(
        self, compute: Callable[[int], FrameDepth], order: Iterable[int], *, background: bool
    ) -> None:
        self._compute = compute
        self._order = [int(i) for i in order]
        self._lock = threading.Lock()
        self._done: dict[int, FrameDepth | BaseException] = {}
        self._running: dict[int, threading.Event] = {}
        self._stop = threading.Event()
        self._thread = (
            threading.Thread(target=self._ahead, name="depth-sweep", daemon=True)
            if background
            else None
        )

    def __enter__(self) -> DepthSweep:
        if self._thread is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _ahead(self) -> None:
        for i in self._order:
            if self._stop.is_set():
                return
            self._claim_and_compute(i)

    def _claim_and_compute(self, i: int) -> FrameDepth | BaseException:
        """Computes frame ``i`` unless done or under way on the other thread (then waits)."""
        with self._lock:
            if i in self._done:
                return self._done[i]
            event = self._running.get(i)
            mine = event is None
            if mine:
                event = self._running[i] = threading.Event()
        if not mine:
            event.wait()
            return self._done[i]
        try:
            result: FrameDepth | BaseException = self._compute(i)
        except Exception as e:  # handed to the caller of get
            result = e
        with self._lock:
            self._done[i] = result
        event.set()
        return result

    def get(self, i: int) -> FrameDepth:
        """The :class:`FrameDepth` of solve frame ``i``."""
        result = self._claim_and_compute(int(i))
        if isinstance(result, BaseException):
            raise result
        return result

    def readings(self, frames: Iterable[int], n_joints: int = 21) -> np.ndarray:
        """Readings (len(frames), n_joints) of the given solve frames, in order."""
        rows = [self.get(i).readings for i in frames]
        return np.stack(rows) if rows else np.zeros((0, n_joints))
