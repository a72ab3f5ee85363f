"""joint_solve's whole-frame tests (``hand_sfm.joint_frames``): a depth test that condemns
nearly every frame must not switch off the camera-path test that finds a mirrored detection."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from graspcap.tasks.core.geometry import make_T
from graspcap.tasks.hand_sfm.joint_frames import frames_to_drop, off_smooth_path
from graspcap.tasks.hand_sfm.joint_solve import JointSolveConfig


def test_a_mirrored_frame_is_dropped_though_the_depth_test_condemns_nearly_all():
    cfg = JointSolveConfig()
    m = 20
    T_c_p = np.stack([make_T(Rotation.from_rotvec([0.0, 0.03 * i, 0.0]).as_matrix(),
                             [0.0, 0.0, 0.5]) for i in range(m)])
    flipped = 3  # a mirrored detection: the camera on the other side of the hand
    T_c_p[flipped, :3, :3] = T_c_p[flipped, :3, :3] @ Rotation.from_rotvec(
        [0.0, np.pi, 0.0]).as_matrix()
    judged = np.ones(m, bool)
    path_bad = off_smooth_path(T_c_p, judged, cfg)
    assert np.flatnonzero(path_bad).tolist() == [flipped]
    least = max(cfg.min_frames, int(np.ceil(cfg.start_min_share * m)))
    depth_bad = np.ones(m, bool)
    depth_bad[[0, 7, 12]] = False  # fewer than `least` frames pass the depth test
    drop = frames_to_drop(judged, depth_bad, path_bad, least)
    assert drop is not None and np.flatnonzero(drop).tolist() == [flipped]
    depth_bad[:] = False
    depth_bad[[9, 15]] = True  # a depth test that keeps enough frames still counts
    assert np.flatnonzero(frames_to_drop(judged, depth_bad, path_bad, least)).tolist() == [
        flipped, 9, 15]
    assert frames_to_drop(judged, depth_bad, np.ones(m, bool), least) is None
