"""A catalog version as a LeRobot v3.0-style dataset (Parquet data, ``meta/info.json``,
episodes, tasks and stats); docs/catalog.md "LeRobot layout".

One episode per session with frames (failed sessions have none and are left out), in
``session_id`` order, with the session's labels, status and hand (``hand_scale``,
``hand_shape``: the subject's 20 bone lengths in metres); one row per frame, in frame order.
All frames go to ``data/chunk-000/file-000.parquet`` and all episodes to
``meta/episodes/chunk-000/file-000.parquet`` (one file each: LeRobot splits files at 100 MB,
a reader follows ``data/chunk_index``/``data/file_index`` of each episode either way).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from graspcap.catalog.stats import Accumulator

CODEBASE_VERSION = "v3.0"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
CHUNKS_SIZE = 1000
DEFAULT_FPS = 30.0
"""Frame rate the timestamps assume unless told (the catalog does not record the grasp videos'
``grasp.fps``; 30 is the session format's example and the synthetic rig's)."""

_POSES = ("T_w_c", "T_c_o", "T_c_p")
_ANGLES = 20
_BONES = 20
"""Bone lengths of ``sessions.hand_shape`` (``tasks.hand.shape.BONE_NAMES``' order)."""
_POSE_NAMES = [f"r{r}c{c}" for r in range(4) for c in range(4)]
_JOINT_NAMES = [f"j{j:02d}.{a}" for j in range(21) for a in "xyz"]


FEATURE_DOCS: dict[str, tuple[str, str]] = {
    "observation.state": ("rad, m", "The session's 20 joint angles of the hand model (rad), then "
                          "T_c_p, the palm in the frame's camera (16, row-major 4x4, m)."),
    "T_w_c": ("m", "Virtual camera of the frame in the world frame (row-major 4x4)."),
    "T_c_o": ("m", "Object in the frame's camera (row-major 4x4)."),
    "T_c_p": ("m", "Palm in the frame's camera (row-major 4x4)."),
    "observation.hand_joints_c": ("m", "21 x 3 joints in the frame's camera (catalog joints_c)."),
    "observation.keypoints_2d_px": ("px", "21 x 2 observed 2D keypoints (catalog joints_2d_px)."),
    "observation.keypoint_conf": ("1", "Detection confidence per keypoint, 0 = not detected."),
    "frame": ("frames", "Video frame index of the recorded session (catalog frame)."),
    "timestamp": ("s", "frame_index / fps."),
    "frame_index": ("frames", "0 at the episode's first (steady) frame."),
    "episode_index": ("", "The episode (a session; meta/episodes/ says which)."),
    "index": ("", "Row over the whole dataset, 0 .. total_frames - 1."),
    "task_index": ("", "Row of meta/tasks.parquet (an object and an intent)."),
}
"""Unit and description of each feature, for the dataset card."""


def task_text(object_id: str, intent: str) -> str:
    """The task string of an object and intent."""
    return f"grasp the {object_id} for {intent}"


def _fixed(values: np.ndarray, width: int, dtype: pa.DataType) -> pa.FixedSizeListArray:
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1), dtype), width)


def feature_specs() -> dict[str, dict]:
    """``info.json``'s ``features``: dtype, shape and names of every data column."""
    state_names = [f"joint_angle_{i:02d}" for i in range(_ANGLES)] + \
                  [f"T_c_p.{n}" for n in _POSE_NAMES]
    feats = {
        "observation.state": {"dtype": "float32", "shape": [len(state_names)],
                              "names": state_names},
        **{p: {"dtype": "float64", "shape": [16], "names": _POSE_NAMES} for p in _POSES},
        "observation.hand_joints_c": {"dtype": "float64", "shape": [63],
                                      "names": _JOINT_NAMES},
        "observation.keypoints_2d_px": {"dtype": "float64", "shape": [42],
                                        "names": [f"j{j:02d}.{a}" for j in range(21)
                                                  for a in "uv"]},
        "observation.keypoint_conf": {"dtype": "float64", "shape": [21],
                                      "names": [f"j{j:02d}" for j in range(21)]},
        "frame": {"dtype": "int64", "shape": [1], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1], "names": None},
        "frame_index": {"dtype": "int64", "shape": [1], "names": None},
        "episode_index": {"dtype": "int64", "shape": [1], "names": None},
        "index": {"dtype": "int64", "shape": [1], "names": None},
        "task_index": {"dtype": "int64", "shape": [1], "names": None},
    }
    return feats


def _pose_matrix(col: pa.ChunkedArray | pa.Array) -> np.ndarray:
    return np.asarray(col.combine_chunks().flatten() if isinstance(col, pa.ChunkedArray)
                      else col.flatten(), np.float64).reshape(-1, 16)


def _feature_stats(data: pa.Table, feats: dict[str, dict]) -> dict[str, dict]:
    """LeRobot's ``meta/stats.json``: per feature and dimension min, max, mean, std, count,
    q01, q99."""
    out = {}
    for name, spec in feats.items():
        width = spec["shape"][0]
        acc = Accumulator(width)
        for chunk in data.column(name).chunks:
            values = chunk.flatten() if pa.types.is_fixed_size_list(chunk.type) else chunk
            acc.update(values.to_numpy(zero_copy_only=False).reshape(-1, width))
        r = acc.result()
        out[name] = {"min": r["min"], "max": r["max"], "mean": r["mean"], "std": r["std"],
                     "count": [max(r["count"])], "q01": r["p01"], "q99": r["p99"]}
    return out


def write_lerobot(sessions: pa.Table, frames: pa.Table, fps: float, out: Path
                  ) -> dict[str, int]:
    """Write the layout under ``out``; return row counts (frames, episodes, tasks)."""
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    frames = frames.sort_by([("session_id", "ascending"), ("frame", "ascending")])
    with_frames = set(frames["session_id"].unique().to_pylist())
    srows = sorted((r for r in sessions.to_pylist() if r["session_id"] in with_frames),
                   key=lambda r: r["session_id"])
    tasks = sorted({task_text(r["object_id"], r["intent"]) for r in srows})
    task_index = {t: i for i, t in enumerate(tasks)}
    episode_task = np.array([task_index[task_text(r["object_id"], r["intent"])] for r in srows],
                            np.int64)
    ids = pa.array([r["session_id"] for r in srows], pa.string())
    ep = pc.index_in(frames["session_id"], value_set=ids).to_numpy().astype(np.int64)
    n = len(ep)
    starts = np.flatnonzero(np.r_[True, ep[1:] != ep[:-1]]) if n else np.zeros(0, np.int64)
    lengths = np.diff(np.r_[starts, n]).astype(np.int64)
    frame_index = np.arange(n, dtype=np.int64) - np.repeat(starts, lengths)
    episode_angles = np.array([r["joint_angles_rad"] for r in srows], np.float64
                              ).reshape(len(srows), _ANGLES)
    angles = episode_angles[ep]
    t_c_p = _pose_matrix(frames["T_c_p"])
    state = np.concatenate([angles, t_c_p], axis=1).astype(np.float32)
    columns = {
        "observation.state": _fixed(state, state.shape[1], pa.float32()),
        **{p: _fixed(_pose_matrix(frames[p]), 16, pa.float64()) for p in _POSES},
        "observation.hand_joints_c": frames["joints_c"].combine_chunks(),
        "observation.keypoints_2d_px": frames["joints_2d_px"].combine_chunks(),
        "observation.keypoint_conf": frames["keypoint_conf"].combine_chunks(),
        "frame": frames["frame"].combine_chunks(),
        "timestamp": pa.array((frame_index / fps).astype(np.float32), pa.float32()),
        "frame_index": pa.array(frame_index, pa.int64()),
        "episode_index": pa.array(ep, pa.int64()),
        "index": pa.array(np.arange(n, dtype=np.int64), pa.int64()),
        "task_index": pa.array(episode_task[ep] if n else np.zeros(0, np.int64), pa.int64()),
    }
    data = pa.table(columns)
    feats = feature_specs()
    data_file = out / DATA_PATH.format(chunk_index=0, file_index=0)
    data_file.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(data, data_file, compression="zstd")

    offsets = np.r_[0, np.cumsum(lengths)].astype(np.int64)
    episodes = pa.table({
        "episode_index": pa.array(np.arange(len(srows)), pa.int64()),
        "tasks": pa.array([[task_text(r["object_id"], r["intent"])] for r in srows],
                          pa.list_(pa.string())),
        "length": pa.array(lengths, pa.int64()),
        "data/chunk_index": pa.array(np.zeros(len(srows), np.int64)),
        "data/file_index": pa.array(np.zeros(len(srows), np.int64)),
        "dataset_from_index": pa.array(offsets[:-1]),
        "dataset_to_index": pa.array(offsets[1:]),
        "meta/episodes/chunk_index": pa.array(np.zeros(len(srows), np.int64)),
        "meta/episodes/file_index": pa.array(np.zeros(len(srows), np.int64)),
        "session_id": pa.array([r["session_id"] for r in srows], pa.string()),
        "object_id": pa.array([r["object_id"] for r in srows], pa.string()),
        "participant": pa.array([r["participant"] for r in srows], pa.string()),
        "intent": pa.array([r["intent"] for r in srows], pa.string()),
        "status": pa.array([r["status"] for r in srows], pa.string()),
        # the subject's hand: the model's scale and its 20 bone lengths (m; null on a row
        # written before catalog format 7, which has no hand_shape)
        "hand_scale": pa.array([r["hand_scale"] for r in srows], pa.float64()),
        "hand_shape": pa.array([r.get("hand_shape") for r in srows],
                               pa.list_(pa.float64(), _BONES)),
    })
    ep_file = out / EPISODES_PATH.format(chunk_index=0, file_index=0)
    ep_file.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(episodes, ep_file)
    import pandas as pd  # only here: the catalog's readers do not need it

    # LeRobot keeps tasks as a pandas frame indexed by the task string
    pd.DataFrame({"task_index": np.arange(len(tasks), dtype=np.int64)},
                 index=pd.Index(tasks, name="task")).to_parquet(out / "meta" / "tasks.parquet")
    fps_out: float | int = int(fps) if float(fps).is_integer() else float(fps)
    info = {
        "codebase_version": CODEBASE_VERSION, "robot_type": "human_hand",
        "total_episodes": len(srows), "total_frames": n, "total_tasks": len(tasks),
        "chunks_size": CHUNKS_SIZE, "data_files_size_in_mb": 100, "video_files_size_in_mb": 200,
        "fps": fps_out, "splits": {"train": f"0:{len(srows)}"},
        "data_path": DATA_PATH, "video_path": None, "features": feats,
    }
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=2) + "\n")
    (out / "meta" / "stats.json").write_text(
        json.dumps(_feature_stats(data, feats), indent=2) + "\n")
    return {"frames": n, "episodes": len(srows), "tasks": len(tasks)}


__all__ = ["CODEBASE_VERSION", "DATA_PATH", "EPISODES_PATH", "FEATURE_DOCS", "feature_specs",
           "task_text", "write_lerobot"]
