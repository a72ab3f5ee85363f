"""The depth work of reconstruct_hand done once per frame (``hand_sfm.depth_sweep``): ahead on a
second thread or on first use, the same readings and surfaces; the stage's result the same
with the second thread on and off; a failed read re-raised to the solve."""

from __future__ import annotations

import threading
from functools import lru_cache

import numpy as np
import pytest

from graspcap.synth.hand_video import make_hand_video
from graspcap.tasks.core.geometry import project
from graspcap.tasks.hand_sfm.depth_sweep import DepthSweep, frame_depth
from graspcap.tasks.hand_sfm.metric_scale import depth_lookup_from_frames
from graspcap.tasks.hand_sfm.reconstruct_hand import ReconstructConfig, reconstruct_hand
from graspcap.tasks.hand_sfm.surface_clouds import hand_centre, surface_cloud

K = np.array([[615.0, 0.0, 320.0], [0.0, 615.0, 240.0], [0.0, 0.0, 1.0]])
H, W = 480, 640


def _frames_and_keypoints(m=8, seed=3):
    rng = np.random.default_rng(seed)
    frames = 0.5 + 0.02 * rng.random((m, H, W))
    frames[rng.random(frames.shape) < 0.2] = 0.0  # dropouts
    uv = np.stack([rng.uniform(200, 440, (m, 21)), rng.uniform(150, 330, (m, 21))], axis=2)
    conf = rng.uniform(0.1, 1.0, (m, 21))
    usable = conf >= 0.2
    usable[3] = False  # a frame without a usable keypoint reads nothing
    return frames, uv, usable, conf >= 0.5


def _sweep(frames, uv, usable, confident, *, background, reads):
    read = lru_cache(maxsize=4)(lambda i: (reads.append(i), frames[i])[1])
    depth_at = depth_lookup_from_frames(frames)

    def surface_at(i, uv_i, depth_i):
        centre = hand_centre(K, uv_i, depth_i, 0.01)
        return surface_cloud(read(i), K, centre, radius_m=0.1, stride_px=3)

    def compute(i):
        return frame_depth(i, uv, usable, depth_at, 0, surface_at, confident)

    return DepthSweep(compute, [5, 0, 1, 2, 4, 6, 7], background=background)


def test_second_thread_and_first_use_give_the_same_frames():
    """Frames asked for out of the thread's order, while it runs: identical readings (NaN
    exactly at the unusable keypoints) and surfaces; each frame's depth read once."""
    frames, uv, usable, confident = _frames_and_keypoints()
    results = {}
    for background in (False, True):
        reads: list[int] = []
        with _sweep(frames, uv, usable, confident, background=background, reads=reads) as s:
            got = [s.get(i) for i in (7, 3, 0, 6, 1, 2, 4, 5)]
        results[background] = dict(zip((7, 3, 0, 6, 1, 2, 4, 5), got, strict=True))
        assert sorted(reads) == [0, 1, 2, 4, 5, 6, 7]  # each frame once, frame 3 never
    for i in range(8):
        a, b = results[False][i], results[True][i]
        assert np.array_equal(a.readings, b.readings, equal_nan=True)
        assert np.array_equal(np.isnan(a.readings), ~usable[i])
        assert (a.surface is None) == (b.surface is None) == (i == 3)
        if a.surface is not None:
            assert np.array_equal(a.surface.points, b.surface.points)
            assert np.array_equal(a.surface.normals, b.surface.normals)
    # the readings are the per-pixel lookups of the usable keypoints
    lookup = depth_lookup_from_frames(frames)
    j = np.flatnonzero(usable[6])
    np.testing.assert_array_equal(results[True][6].readings[j], lookup(6, uv[6, j]))


def test_a_failed_read_is_raised_to_the_caller_and_the_thread_stops():
    frames, uv, usable, confident = _frames_and_keypoints()

    def compute(i):
        if i == 4:
            raise OSError("depth frame 4 unreadable")
        return frame_depth(i, uv, usable, depth_lookup_from_frames(frames), 0)

    sweep = DepthSweep(compute, range(8), background=True)
    with sweep:
        assert np.isfinite(sweep.get(0).readings[usable[0]]).all()
        with pytest.raises(OSError, match="frame 4 unreadable"):
            sweep.get(4)
    assert not any(t.name == "depth-sweep" for t in threading.enumerate())


def test_reconstruct_hand_is_the_same_with_the_second_thread_on_and_off():
    """A 40-frame synthetic session with depth frames made from its joints' readings (a disk
    of the median reading behind 5x5 patches of each joint's reading at its true pixel), so
    the stage reads whole frames and registers their surfaces: bit-identical results."""
    video = make_hand_video(n_frames=40, steady_from=5, seed=0)
    n = len(video.keypoints)
    frames = np.zeros((n, H, W), np.float32)
    rows, cols = np.mgrid[0:H, 0:W]
    for f in range(n):
        true_uv = project(video.K, video.joints_c[f])
        cu, cv = np.median(true_uv, axis=0)
        disk = (cols - cu) ** 2 + (rows - cv) ** 2 < 70.0**2
        frames[f][disk] = np.median(video.skin_depth_m[f]) + 0.02
        for j, (u, v) in enumerate(np.rint(true_uv).astype(int)):
            if 2 <= u < W - 2 and 2 <= v < H - 2:
                frames[f, v - 2 : v + 3, u - 2 : u + 3] = video.skin_depth_m[f, j]
    T_color_turntable = np.diag([1.0, -1.0, -1.0, 1.0])
    T_color_turntable[2, 3] = 5.0  # the platter 5 m away, up towards the camera: nothing cut
    out = []
    for prefetch in (False, True):
        cfg = ReconstructConfig(prefetch_depth=prefetch)
        out.append(reconstruct_hand(video.keypoints, video.K, video.steady_from, frames,
                                    video.surface_offset_m, cfg,
                                    T_color_turntable=T_color_turntable))
    a, b = out
    assert np.array_equal(a.joints_w, b.joints_w)
    assert np.array_equal(a.T_w_c, b.T_w_c, equal_nan=True)
    assert len(a.diagnostics.depth_links) > 0  # the surfaces were built and registered
    assert np.linalg.norm(a.joints_w - video.joints_w, axis=1).mean() < 0.01
