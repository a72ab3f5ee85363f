"""Scoring of the pose stages against synthetic truth (``graspcap.synth.evaluate``)."""

from __future__ import annotations

import numpy as np

from graspcap.synth.evaluate import _anchor, _camera_errors, _mpjpe_mm, _T_adj_at
from graspcap.tasks.core.geometry import from_rotvec, inv_T, pose_error


def test_T_adj_truth_follows_the_detected_steady_frame():
    """The pipeline registers the object in the frame it was given as the first steady one;
    after the true onset the object moves with the hand, so the truth it is scored against
    must be the object's pose in that frame (not the onset's), before the onset the onset's."""
    rng = np.random.default_rng(0)
    T_w_c = np.stack([np.eye(4)] + [from_rotvec(rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3))
                                    for _ in range(5)])  # fmt: skip
    truth = {"steady_from": 10, "T_w_c": T_w_c,
             "T_adj": from_rotvec(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.1, -0.2])),
             "T_w_o_stage1": from_rotvec(np.array([0.3, 0.0, 0.0]), np.array([0.0, 0.0, 0.7]))}
    for s in (8, 10):
        np.testing.assert_allclose(_T_adj_at(truth, s), truth["T_adj"])
    T_obj_12 = inv_T(T_w_c[2]) @ truth["T_adj"] @ truth["T_w_o_stage1"]  # object in camera 12
    np.testing.assert_allclose(_T_adj_at(truth, 12) @ truth["T_w_o_stage1"], T_obj_12,
                               atol=1e-12)  # fmt: skip
    assert pose_error(_T_adj_at(truth, 12), truth["T_adj"])[0] > 1.0


def test_cameras_are_compared_from_a_camera_the_estimate_solved():
    """A first steady frame without detections gets an interpolated camera (a fill, several
    degrees off when the camera moves between frames); scored against it every camera would
    carry its error. The comparison starts at the next camera the estimate solved."""
    rng = np.random.default_rng(1)
    T_w_c = np.stack([np.eye(4)] + [from_rotvec(rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3))
                                    for _ in range(7)])  # fmt: skip
    truth = {"steady_from": 20, "T_w_c": T_w_c, "joints_w": rng.normal(0, 0.05, (21, 3))
             + [0.0, 0.0, 0.5]}  # fmt: skip
    # the estimate found the onset one frame early (19, its own world); frame 20 has no pose
    T_19 = from_rotvec(np.array([0.0, 0.05, 0.0]), np.array([0.01, 0.0, 0.0]))  # truth's cam 19
    est = np.concatenate([[np.eye(4)], np.einsum("ij,njk->nik", inv_T(T_19), T_w_c)])
    est[1] = est[1] @ from_rotvec(np.array([0.07, 0.0, 0.0]), np.zeros(3))  # 4 deg fill
    joints = (inv_T(T_19) @ np.c_[truth["joints_w"], np.ones(21)].T).T[:, :3]
    solved = np.ones(len(est), dtype=bool)
    solved[1] = False
    at = _anchor(19, 20, len(est), solved)
    assert at == 21
    cams = _camera_errors(est, 19, truth, at)
    assert len(cams) == 7 and cams.max() < 1e-9
    assert _mpjpe_mm(joints, est, 19, truth, at) < 1e-9
    at_fill = _anchor(19, 20, len(est), None)  # without the flags: frame 20, the fill
    assert at_fill == 20
    assert np.median(_camera_errors(est, 19, truth, at_fill)[:, 0]) > 3.5


def test_per_frame_hand_is_scored_in_each_frames_camera():
    """``frames.joints_c`` (the static hand carried by each frame's camera) is scored against
    the true joints in that frame's true camera; frames before the true onset are left out."""
    from graspcap.synth.evaluate import _per_frame_joint_errors

    rng = np.random.default_rng(2)
    T_w_c = np.stack([from_rotvec(rng.normal(0, 0.2, 3), rng.normal(0, 0.05, 3))
                      for _ in range(6)])  # fmt: skip
    joints_w = rng.normal(0, 0.05, (21, 3))
    truth = {"steady_from": 10, "T_w_c": T_w_c, "joints_w": joints_w}
    frames = np.arange(9, 16)  # one frame before the true onset
    true_c = np.stack([(inv_T(T_w_c[max(f - 10, 0)]) @ np.c_[joints_w, np.ones(21)].T).T[:, :3]
                       for f in frames])  # fmt: skip
    assert _per_frame_joint_errors(frames, true_c, truth)["frame_joints_mm"] < 1e-9
    shifted = true_c + np.array([0.0, 0.0, 0.004])
    shifted[-1] += 0.1  # one frame 10 cm off moves the p90, not the median
    out = _per_frame_joint_errors(frames, shifted, truth)
    assert abs(out["frame_joints_mm"] - 4.0) < 1e-6 and out["frame_joints_p90_mm"] > 4.0


def test_cameras_scored_are_the_catalogs_and_stage_2s_beside_them():
    """With ``propagate_poses`` in the results, the cameras scored are its ``T_w_c`` (the
    catalog's ``frames.T_w_c``: tracked where the object was tracked in the depth), as
    ``estimate_from_catalog`` scores a built catalog; stage 2's own are kept as ``sfm_``."""
    from types import SimpleNamespace

    from graspcap.synth.evaluate import estimate_from_results

    sfm = np.stack([np.eye(4)] * 3)
    tracked = sfm.copy()
    tracked[:, 0, 3] = 0.01
    results = {
        "reconstruct_hand": SimpleNamespace(joints_w=np.zeros((21, 3)), T_w_c=sfm,
                                            pose_valid=np.ones(3, bool), reproj_rmse_px=1.0),
        "propagate_poses": SimpleNamespace(frame_indices=np.arange(3), T_c_o=sfm,
                                           joints_c=np.zeros((3, 21, 3)), T_w_c=tracked),
    }
    est = estimate_from_results(results)
    assert est["T_w_c"] is tracked and est["T_w_c_sfm"] is sfm
    results["propagate_poses"].T_w_c = None  # an older result: stage 2's cameras only
    est = estimate_from_results(results)
    assert est["T_w_c"] is sfm and "T_w_c_sfm" not in est


def test_aligned_cameras_and_joints_are_unmoved_by_a_bad_anchor_camera():
    """The anchored errors carry the anchor camera's error into every frame; one robust rigid
    alignment of the whole trajectory (``camera_*_aligned_*``, ``joints_aligned_mm``) does
    not: a trajectory exact but for its first camera (30 deg, 5 cm off) scores ~0 aligned."""
    from graspcap.synth.evaluate import _aligned_metrics

    rng = np.random.default_rng(5)
    T_w_c = np.stack([from_rotvec(rng.normal(0, 0.3, 3), rng.normal(0, 0.1, 3))
                      for _ in range(20)])  # fmt: skip
    joints_w = rng.normal(0, 0.05, (21, 3)) + [0.0, 0.0, 0.5]
    truth = {"steady_from": 30, "T_w_c": T_w_c, "joints_w": joints_w}
    T_est_true = from_rotvec(np.array([0.5, -1.0, 2.0]), np.array([0.3, 0.1, -0.2]))  # worlds
    est = np.einsum("ij,njk->nik", T_est_true, T_w_c)
    joints = (T_est_true @ np.c_[joints_w, np.ones(21)].T).T[:, :3]
    est[0] = est[0] @ from_rotvec(np.array([0.0, np.radians(30.0), 0.0]), [0.05, 0.0, 0.0])
    at = _anchor(30, 30, len(est), np.ones(len(est), bool))
    assert at == 30  # the bad camera is the anchor
    assert np.median(_camera_errors(est, 30, truth, at)[:, 0]) > 25
    assert _mpjpe_mm(joints, est, 30, truth, at) > 20
    out = _aligned_metrics("", est, 30, truth, {"joints": joints})
    assert out["camera_rot_aligned_deg"] < 1e-6 and out["camera_trans_aligned_mm"] < 1e-6
    assert out["joints_aligned_mm"] < 1e-6
    # noise on every camera: the aligned median reads it
    noisy = est @ np.stack([from_rotvec(rng.normal(0, np.radians(1.0), 3), np.zeros(3))
                            for _ in range(20)])  # fmt: skip
    noisy_out = _aligned_metrics("", noisy, 30, truth, {})
    assert 0.5 < noisy_out["camera_rot_aligned_deg"] < 3.0
