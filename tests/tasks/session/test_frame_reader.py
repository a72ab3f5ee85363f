"""frame_reader: RGB decode equal to imread + cvtColor, bad frames named, the prefetching
reader yields exactly what inline decoding yields, in order, and stops when closed."""

from __future__ import annotations

import threading

import cv2
import numpy as np

from graspcap.tasks.session.frame_reader import iter_frames, read_rgb


def _frames(folder, n: int = 7) -> list:
    """JPEG and PNG frames of seeded noise (640x480), one truncated, one the wrong size,
    one missing."""
    rng = np.random.default_rng(5)
    paths = []
    for i in range(n):
        image = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
        paths.append(folder / f"{i:03d}.{'png' if i % 3 == 2 else 'jpg'}")
        cv2.imwrite(str(paths[-1]), image)
    data = paths[1].read_bytes()
    paths[1].write_bytes(data[: len(data) // 2])
    cv2.imwrite(str(paths[3]), np.zeros((240, 320, 3), np.uint8))
    paths[4].unlink()
    return paths


def test_read_rgb_equals_imread_and_cvtcolor_and_is_read_only(tmp_path):
    paths = _frames(tmp_path)
    for i in (0, 2, 5):  # jpg, png, png
        rgb, why = read_rgb(paths[i], (640, 480))
        assert why == "" and not rgb.flags.writeable and rgb.flags.c_contiguous
        expected = cv2.cvtColor(cv2.imread(str(paths[i])), cv2.COLOR_BGR2RGB)
        assert np.array_equal(rgb, expected)
    assert "truncated" in read_rgb(paths[1], (640, 480))[1]
    assert "expected 640x480" in read_rgb(paths[3], (640, 480))[1]
    assert read_rgb(paths[4], (640, 480))[1] == "file does not exist"


def test_prefetching_reader_yields_what_inline_decoding_yields(tmp_path):
    paths = _frames(tmp_path)
    inline = list(iter_frames(paths, (640, 480), prefetch=0))
    assert [why == "" for _, why in inline] == [True, False, True, False, False, True, True]
    for prefetch in (1, 3, 20):
        ahead = list(iter_frames(paths, (640, 480), prefetch=prefetch))
        assert [w for _, w in ahead] == [w for _, w in inline]
        for (a, _), (b, _) in zip(ahead, inline, strict=True):
            assert (a is None and b is None) or np.array_equal(a, b)


def test_closing_the_reader_early_stops_its_thread(tmp_path):
    paths = _frames(tmp_path) * 5
    before = threading.active_count()
    frames = iter_frames(paths, None, prefetch=2)
    next(frames)
    assert threading.active_count() == before + 1
    frames.close()
    assert threading.active_count() == before
