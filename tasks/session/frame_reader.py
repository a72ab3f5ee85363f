"""Colour frames for the image detector: decode straight to RGB, optionally on a reader thread.

:func:`read_rgb` decodes one file (JPEG markers checked first, the camera's size enforced) to
a read-only ``(h, w, 3) uint8`` RGB array; read-only so that MediaPipe takes it by reference
instead of copying it into its graph. :func:`iter_frames` yields the frames of a video in
order, decoded up to ``prefetch`` frames ahead by one reader thread while the caller works on
the current one (``cv2.imdecode`` and file reads release the GIL, as does MediaPipe's graph
while it runs). Both paths give identical pixels.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from graspcap.schemas.session import DEFAULT_LIMITS
from graspcap.tasks.session.files import (
    Unreadable,
    _jpeg_problem,
    decode,
    read_regular,
    size_problem,
)

# cv2: imported where used, so that importing the stage table stays cheap

Frame = tuple[np.ndarray | None, str]
"""An ``(h, w, 3) uint8`` read-only RGB image and "", or None and why it could not be read."""


def read_rgb(path: Path | str, size: tuple[int, int] | None) -> Frame:
    """``(h, w, 3) uint8`` RGB of the image at ``path`` (read-only), or None and why not.

    ``size`` (width, height) is the colour camera's; another size is refused, since the
    keypoints would not be in that camera's pixels. JPEG and PNG decode straight to RGB
    (``cv2.IMREAD_COLOR_RGB``: the same pixels as BGR then ``cvtColor``, without the pass).
    """
    import cv2

    data = read_regular(path)  # never opens a FIFO or device, never reads a directory
    if isinstance(data, Unreadable):
        return None, data.message
    if not data:
        return None, "empty file (0 bytes)"
    if Path(path).suffix.lower() in (".jpg", ".jpeg") or data.startswith(b"\xff\xd8"):
        problem = _jpeg_problem(data)
        if problem:
            return None, problem
    if (problem := size_problem(data, size, DEFAULT_LIMITS.max_image_pixels)) is not None:
        return None, problem  # from the header: a wrong or huge size is never decoded
    rgb = decode(data, cv2.IMREAD_COLOR_RGB)
    if rgb is None:
        return None, "does not decode as an image (corrupt or unsupported)"
    h, w = rgb.shape[:2]
    if size is not None and (w, h) != tuple(size):
        return None, f"size {w}x{h}, expected {size[0]}x{size[1]} (width x height)"
    rgb.flags.writeable = False
    return rgb, ""


def iter_frames(
    paths: Sequence[Path | str], size: tuple[int, int] | None, prefetch: int
) -> Iterator[Frame]:
    """:func:`read_rgb` of each path in order; with ``prefetch`` > 0 one reader thread
    decodes up to ``prefetch`` frames ahead of the one the caller holds (a bounded window,
    so memory stays at ``prefetch + 1`` frames). Closing the iterator early stops the
    reader after the reads already started."""
    if prefetch <= 0:
        for path in paths:
            yield read_rgb(path, size)
        return
    pool = ThreadPoolExecutor(1, thread_name_prefix="frame-reader")
    ahead: deque[Future[Frame]] = deque()
    try:
        for path in paths:
            ahead.append(pool.submit(read_rgb, path, size))
            if len(ahead) > prefetch:
                yield ahead.popleft().result()
        while ahead:
            yield ahead.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
