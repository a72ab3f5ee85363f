"""reconstruct_hand's second threads change no result: the initialisation's PnP split over
two threads gives the same start as on one."""

from __future__ import annotations

import numpy as np

from graspcap.synth.hand_video import make_hand_video
from graspcap.tasks.hand_sfm.two_view_init import initialise


def test_initialisation_is_the_same_on_one_or_two_threads():
    video = make_hand_video(n_frames=40, steady_from=5, seed=2)
    kp = video.keypoints[video.steady_from :]
    ok = kp[..., 2] >= 0.2
    out = [
        initialise(kp[..., :2], ok, video.K, n_candidates=12, ransac_px=8.0, min_points=6,
                   min_parallax_deg=2.0, threads=t)
        for t in (1, 2)
    ]  # fmt: skip
    (a, _), (b, _) = out
    assert a is not None and b is not None
    assert (a.pair.a, a.pair.b) == (b.pair.a, b.pair.b)
    posed = np.all(np.isfinite(a.T_c_w.reshape(len(kp), -1)), axis=1)
    assert posed.sum() >= 30  # most frames posed, so both threads had work
    assert np.array_equal(a.T_c_w, b.T_c_w, equal_nan=True)
    assert np.array_equal(a.points_w, b.points_w, equal_nan=True)


def test_worker_thread_cap(monkeypatch):
    """``GRASPCAP_WORKER_THREADS`` caps a stage's threads (a Dask worker per core must not
    fan out over the other workers' cores); unset or 0, the config's count stands."""
    from graspcap.tasks.core.threads import THREADS_ENV, thread_budget

    monkeypatch.delenv(THREADS_ENV, raising=False)
    assert thread_budget(2) == 2 and thread_budget(0) == 1
    monkeypatch.setenv(THREADS_ENV, "0")
    assert thread_budget(2) == 2
    monkeypatch.setenv(THREADS_ENV, "1")
    assert thread_budget(2) == 1
    monkeypatch.setenv(THREADS_ENV, "4")
    assert thread_budget(2) == 2

