"""``frames.camera_solved`` (format 4): a real build writes True where stage 2 solved the frame's
camera from its own keypoints and False where it interpolated it (a frame whose detection was
removed); ``estimate_from_catalog`` carries the column. The same build's per-frame validity
(format 6): the frame without a detection has its hand unused and its camera interpolated, with
the reasons, every other frame of these easy sessions is valid and its object pose supported by
its depth, and ``GraspDataset`` leaves out exactly the frame denied."""

from __future__ import annotations

import json
import pickle
import shutil

import numpy as np
import pandas as pd

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.synth.evaluate import estimate_from_catalog
from graspcap.synth.sensors import openpose_json
from tests.flow_fixtures import PRESET, copy_catalog, require_pipeline_passes

DROP_AFTER = 6
"""The dropped detection is this many frames after the first steady frame (not the first
one, whose camera is the world frame and which QA flags on its own)."""


def _pose_valid(catalog) -> list[dict[int, bool]]:
    """Every cached ``reconstruct_hand`` result's {frame: pose_valid} (a list: the warm build's
    result and the new one cover the same frames)."""
    out = []
    for p in (catalog / "work" / "results" / "reconstruct_hand").glob("*.pkl"):
        rec = pickle.loads(p.read_bytes())
        out.append({int(f): bool(v) for f, v in zip(rec.frames, rec.pose_valid, strict=True)})
    return out


def _session_frames(frames: pd.DataFrame, sid: str) -> pd.DataFrame:
    return frames[frames.session_id == sid].sort_values("frame")


def test_a_frame_without_detections_is_written_as_interpolated(warm, synth_root, tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    src = sorted(p for p in synth_root.iterdir() if (p / "session.json").exists())[0]
    root = tmp_path / "sessions"
    session = shutil.copytree(src, root / src.name)
    manifest = json.loads((session / "session.json").read_text())
    sid, steady = manifest["session_id"], int(manifest["grasp"]["steady_from"])
    dropped = steady + DROP_AFTER
    pattern = manifest["grasp"]["keypoints"]
    (session / pattern.format(index=dropped)).write_text(json.dumps(openpose_json(None)))

    warm_frames = gc.open(catalog).table("frames").to_pandas()
    assert warm_frames.camera_solved.notna().all()
    before = _session_frames(warm_frames, sid)
    assert before.camera_solved.astype(bool).all()  # an easy session: every camera solved

    report = build_dataset([root], catalog, PRESET, build_id="drop")
    require_pipeline_passes(report)
    assert sid in report.changed
    frames = _session_frames(gc.open(catalog).table("frames").to_pandas(), sid)
    assert frames.camera_solved.notna().all() and frames.camera_solved.dtype == bool
    solved = dict(zip(frames.frame.tolist(), frames.camera_solved.tolist(), strict=True))
    assert solved[dropped] is False
    detected = {int(f): int((np.asarray(c) > 0).sum()) for f, c in
                zip(frames.frame, frames.keypoint_conf, strict=True)}
    assert detected[dropped] == 0
    assert all(solved[f] for f, n in detected.items() if n >= 6), (solved, detected)
    # the column is reconstruct_hand's pose_valid, frame by frame
    valid = next(v for v in _pose_valid(catalog) if dropped in v and not v[dropped])
    assert solved == {f: valid[f] for f in solved}

    est = estimate_from_catalog({"steady_from": steady}, frames)
    assert est["camera_solved"].dtype == bool
    np.testing.assert_array_equal(est["frame"][~est["camera_solved"]], [dropped])

    # per-frame validity (format 6), in every frame of the catalog, consistent
    everything = gc.open(catalog).table("frames").to_pandas()
    for flag, reason in (("hand_used", "hand_reason"), ("camera_solved", "camera_reason"),
                         ("object_supported", "object_reason")):
        assert everything[flag].notna().all(), flag  # every frame is in the steady window
        assert (everything[reason].isna() == everything[flag].astype(bool)).all(), flag
    assert everything.object_depth_agreement.notna().all()
    dropped_row = frames[frames.frame == dropped].iloc[0]
    assert (dropped_row.hand_used, dropped_row.hand_reason) == (False, "no detection")
    assert dropped_row.camera_reason == "interpolated from its neighbours: no detection"
    others = everything[(everything.session_id != sid) | (everything.frame != dropped)]
    assert others.hand_used.astype(bool).all() and others.camera_solved.astype(bool).all()
    # the easy sessions' object poses agree with their depth (measured: 0.95-1.0 per frame)
    assert everything.object_supported.astype(bool).all()
    assert everything.object_depth_agreement.min() > 0.9
    assert np.isclose(dropped_row.object_depth_agreement,
                      float(frames[frames.frame == dropped - 1].object_depth_agreement.iloc[0]),
                      atol=0.05)  # the interpolated camera is no worse here
    ds = gc.GraspDataset(catalog, status=("ok", "flagged"))
    keys = {(ds[i]["session_id"], int(ds[i]["frame"])) for i in range(len(ds))}
    assert len(ds) == len(everything) - 1 and (sid, dropped) not in keys
    assert len(gc.GraspDataset(catalog, status=("ok", "flagged"), valid_only=False)) == len(
        everything)


def test_estimate_from_catalog_leaves_out_a_null_camera_solved():
    T = np.eye(4).reshape(-1).tolist()
    frames = pd.DataFrame({"frame": [5, 3, 4], "T_w_c": [T] * 3, "T_c_o": [T] * 3,
                           "camera_solved": [True, False, True]})
    est = estimate_from_catalog({"steady_from": 3}, frames)
    np.testing.assert_array_equal(est["frame"], [3, 4, 5])
    np.testing.assert_array_equal(est["camera_solved"], [False, True, True])  # sorted by frame
    old = frames.assign(camera_solved=[None, None, None])  # a row written before format 4
    assert "camera_solved" not in estimate_from_catalog({"steady_from": 3}, old)
    assert "camera_solved" not in estimate_from_catalog({"steady_from": 3},
                                                        frames.drop(columns="camera_solved"))
