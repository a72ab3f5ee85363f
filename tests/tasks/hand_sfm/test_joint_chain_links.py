"""The depth chain kept past the start (``joint_solve/11``): its registrations as links
between the solved frames (``chain_links``), the frames the solve did not pose placed by it
(``chain_fill``), and joints from the depth readings where triangulation fails
(``depth_joints``)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from graspcap.tasks.core.geometry import inv_T, make_T, rotation_error_deg
from graspcap.tasks.hand.model import SURFACE_OFFSET_M
from graspcap.tasks.hand_sfm.depth_links import DepthLink
from graspcap.tasks.hand_sfm.joint_starts import Start, chain_fill, chain_links, depth_joints

M = 12


def _cameras(m: int = M) -> np.ndarray:
    """T_c_p (m, 4, 4): a camera turning 4 deg a frame about a hand 0.7 m in front of it,
    with a wobble the interpolation of its ends cannot know."""
    out = []
    for i in range(m):
        R = Rotation.from_rotvec([0.02 * np.sin(i), np.radians(4 * i), 0]).as_matrix()
        out.append(make_T(R, [0.01 * np.cos(2 * i), 0, 0.7]))
    return np.stack(out)


def _chain(T: np.ndarray, start: int = 5, skip: tuple[int, ...] = (8,)) -> tuple[DepthLink, ...]:
    """Registrations grown both ways from ``start``; the frames of ``skip`` are jumped over
    (the next frame registered onto the one before them), as ``odometry_init`` does."""
    info = np.diag([1e4] * 3 + [1e6] * 3)
    links = []
    for order in (range(start + 1, len(T)), range(start - 1, -1, -1)):
        last = start
        for b in order:
            if b in skip:
                continue
            links.append(DepthLink(last, b, T[last] @ inv_T(T[b]), info, 0.001, 0.9))
            last = b
    return tuple(links)


def test_links_join_consecutive_solved_frames_through_the_chains_path():
    T = _cameras()
    start = Start(T, np.zeros(20), 1.0, "chain", _chain(T))
    active = np.ones(M, bool)
    active[[3, 4, 9]] = False  # frames the solve dropped: the links jump over them
    links = chain_links(start, active)
    pairs = [(k.a, k.b) for k in links]
    # 8 is not chained (skipped), so 7 joins 10 and 2 joins 5 across the start
    assert pairs == [(0, 1), (1, 2), (2, 5), (5, 6), (6, 7), (7, 10), (10, 11)]
    for k in links:
        assert np.allclose(k.T_a_b, T[k.a] @ inv_T(T[k.b]))
    hops = {(2, 5): 3, (7, 10): 2, (0, 1): 1}  # registrations on each pair's path
    for k in links:
        if (k.a, k.b) in hops:
            assert np.allclose(k.information, np.diag([1e4] * 3 + [1e6] * 3) / hops[(k.a, k.b)])
    assert chain_links(Start(T, np.zeros(20), 1.0, "staged"), active) == []


def test_fill_places_unsolved_frames_by_the_chain_not_by_interpolation():
    T = _cameras()
    start = Start(T, np.zeros(20), 1.0, "chain", _chain(T))
    # the solve found the same cameras up to one palm-side transform (the hand placed anew)
    D = make_T(Rotation.from_rotvec([0.05, -0.1, 0.02]).as_matrix(), [0.01, 0.0, -0.02])
    solved = T @ D
    active = np.ones(M, bool)
    active[[1, 2, 3, 8]] = False
    T_c_p = np.where(active[:, None, None], solved, np.nan)
    out = chain_fill(start, T_c_p, active)
    for i in (1, 2, 3):  # chained: the wobble inside the gap is kept
        assert rotation_error_deg(out[i][:3, :3], solved[i][:3, :3]) < 1e-6
        assert np.allclose(out[i][:3, 3], solved[i][:3, 3], atol=1e-9)
    assert np.all(np.isnan(out[8]))  # not chained: left for the interpolation
    assert np.array_equal(out[active], T_c_p[active])
    unchained = Start(T, np.zeros(20), 1.0, "depth")
    assert np.array_equal(chain_fill(unchained, T_c_p, active), T_c_p, equal_nan=True)


def test_depth_joints_are_the_readings_back_projected_and_robust_to_a_stray_one():
    rng = np.random.default_rng(0)
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    X = rng.normal(0, 0.04, (21, 3))  # joints in the world of the chain's first camera
    T = _cameras(6)
    T[:, :3, 3] = [0, 0, 0.8]
    Xc = np.einsum("mab,jb->mja", T[:, :3, :3], X) + T[:, None, :3, 3]
    uv = Xc[..., :2] / Xc[..., 2:] * 600 + [320, 240]
    readings = Xc[..., 2] - np.asarray(SURFACE_OFFSET_M)
    readings[0, 3] -= 0.05  # the object in front of a joint in one frame
    readings[:, 7] = np.nan  # a joint nothing reads
    readings[1:, 9] = np.nan  # ... or one frame only
    T[5] = np.nan  # an unposed frame
    got = depth_joints(T, uv, readings, K)
    known = np.ones(21, bool)
    known[[7, 9]] = False
    assert np.all(np.isnan(got[~known]))
    assert np.abs(got[known] - X[known]).max() < 1e-9

