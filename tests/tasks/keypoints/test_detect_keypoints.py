"""detect_keypoints, OpenPose JSON backend: real OpenPose output, tracking, bad values."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from graspcap.tasks.keypoints.detect_keypoints import (
    Backend,
    DetectKeypointsConfig,
    Keypoints2D,
    detect_keypoints,
    track_hands,
    why_missing,
)
from graspcap.tasks.session.load_session import load_session
from tests.session_factory import write_session

CONFIG = DetectKeypointsConfig()


def _hand(offset: float, conf: float = 0.8) -> np.ndarray:
    h = np.zeros((21, 3))
    h[:, 0] = np.arange(21) + offset
    h[:, 1] = 100.0
    h[:, 2] = conf
    return h


def test_tracks_the_hand_nearest_the_previous_frame():
    near, far = _hand(0.0), _hand(300.0, conf=0.95)
    frames = [[_hand(1.0)], [far, near], [near.copy(), far]]
    out = track_hands(frames, CONFIG)
    assert np.allclose(out[1], near) and np.allclose(out[2], near)


def test_first_detection_is_the_most_confident_and_empty_frames_stay_missing():
    out = track_hands([[], [_hand(0.0, 0.3), _hand(50.0, 0.9)]], CONFIG)
    assert (out[0, :, 2] == 0).all()
    assert np.allclose(out[1], _hand(50.0, 0.9))


def test_nan_and_low_confidence_become_missing():
    h = _hand(0.0)
    h[3, 0] = np.nan
    h[4, 2] = 0.01
    out = track_hands([[h]], CONFIG)
    assert out[0, 3, 2] == 0 and out[0, 4, 2] == 0 and (out[0, 5:, 2] > 0).all()


def test_reads_real_openpose_output_with_confidences(shared_data, tmp_path):
    src = shared_data / "openpose_hand_json" / "COCO_val2014_000000000192_keypoints.json"
    size = {"width": 640, "height": 480}  # the COCO image's (the files are 80x60: not read)
    directory = write_session(tmp_path / "s", frames=2, color_camera=size)
    session = load_session(directory, check_images=False)
    for i in range(2):
        shutil.copy(src, session.grasp_path("keypoints", i))
    result = detect_keypoints(load_session(directory, check_images=False), CONFIG)
    raw = np.asarray(json.loads(src.read_text())["people"][0]["hand_right_keypoints_2d"])
    raw = raw.reshape(21, 3)
    kept = raw[:, 2] >= CONFIG.min_confidence
    assert result.backend is Backend.OPENPOSE_JSON
    assert result.keypoints.shape == (2, 21, 3)
    assert np.allclose(result.keypoints[0][kept], raw[kept])
    assert (result.keypoints[0][~kept, 2] == 0).all()
    assert result.frames_with_hand == (2 if kept.any() else 0)


def _with_files(tmp_path, documents):
    directory = write_session(tmp_path / "s", frames=len(documents))
    for i, doc in enumerate(documents):
        text = doc if isinstance(doc, str) else json.dumps(doc)
        (directory / f"grasp/keypoints/{i:06d}_keypoints.json").write_text(text)
    return directory


def test_bad_keypoint_files_are_missing_detections_with_notes_not_a_failed_session(tmp_path):
    good = _hand(10.0, 0.7)
    nan = good.copy()
    nan[2, 0] = np.nan
    flat = good.reshape(-1).tolist()
    directory = _with_files(tmp_path, [
        {"people": [{"hand_right_keypoints_2d": flat}]},
        {"people": [{"hand_right_keypoints_2d": flat[:60]}]},
        '{"people": [{"hand_right_keypoints_2d": ['
        + ", ".join("NaN" if np.isnan(v) else str(float(v)) for v in nan.reshape(-1)) + "]}]}",
        '{"people": [\n  {"hand_right',
        {"people": [{"hand_right_keypoints_2d": (good * [1, 1, 2]).reshape(-1).tolist()}]},
        {"people": []},
    ])
    result = detect_keypoints(load_session(directory), CONFIG)  # images checked too
    kp = result.keypoints
    assert np.allclose(kp[0], good)
    assert (kp[1] == 0).all() and (kp[3] == 0).all() and (kp[4] == 0).all()
    assert (kp[5] == 0).all()  # empty people: no detection, no note
    assert kp[2, 2, 2] == 0 and np.allclose(np.delete(kp[2], 2, axis=0), np.delete(good, 2, 0))
    notes = {n.frame: n.message for n in result.notes}
    assert sorted(notes) == [1, 2, 3, 4]
    assert "got 60" in notes[1] and "[2]" in notes[2] and "line 2 column" in notes[3]
    assert "[0, 1]" in notes[4]
    assert result.summary() == {"backend": "openpose_json", "frames": 6, "frames_with_hand": 2,
                                "mean_confidence": 0.7, "frame_notes": 4}


def test_backend_is_chosen_from_the_manifest(tmp_path):
    from graspcap.tasks.core.errors import StageError
    from graspcap.tasks.keypoints.detect_keypoints import choose_backend

    directory = write_session(tmp_path / "s", frames=2)
    session = load_session(directory, check_images=False)
    assert choose_backend(session, CONFIG) is Backend.OPENPOSE_JSON
    forced = DetectKeypointsConfig(backend=Backend.MEDIAPIPE)
    assert choose_backend(session, forced) is Backend.MEDIAPIPE
    m = session.manifest
    bare = type(session)(root=session.root, manifest=m.model_copy(
        update={"grasp": m.grasp.model_copy(update={"keypoints": None})}))
    assert choose_backend(bare, CONFIG) is Backend.MEDIAPIPE
    with pytest.raises(StageError, match="needs grasp.keypoints"):
        choose_backend(bare, DetectKeypointsConfig(backend=Backend.OPENPOSE_JSON))


def test_why_missing_is_the_summary_and_empty_for_an_older_result():
    kp = np.zeros((6, 21, 3))
    kp[:2, :, 2] = 0.9
    result = Keypoints2D(kp, Backend.OPENPOSE_JSON, hand="right", other_hand_frames=(3, 4))
    assert why_missing(result) == result.missing_summary()
    assert why_missing(result).startswith("of 6 frames, 2 have a right hand detected; 2 hold "
                                          "only the other hand")
    assert why_missing(Keypoints2D(kp, Backend.OPENPOSE_JSON, hand="right")) == ""

    class Cached:  # a result pickled before Keypoints2D had missing_summary
        keypoints = kp

    assert why_missing(Cached()) == ""
