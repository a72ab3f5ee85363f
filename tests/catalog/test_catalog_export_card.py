"""`graspcap catalog export`: the dataset card, stats.json and the LeRobot layout.

The Hugging Face `datasets` package is not installed here (and there is no network): the
LeRobot layout is checked with pyarrow against the layout docs/catalog.md documents.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import graspcap.catalog as gc
from graspcap.catalog.card import DEFAULT_LICENCE
from graspcap.catalog.lerobot import task_text
from graspcap.catalog.stats import table_stats
from graspcap.cli import main
from graspcap.schemas.tables import FRAMES_SCHEMA, SESSIONS_SCHEMA
from tests.catalog_factory import make_build

IDS = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-handoff-00", "p04-mug-handoff-00",
       "p05-drill-use-01"]
FAILED = "p03-bowl-handoff-00"
FLAGS = {"p02-drill-use-00": ["inlier ratio 0.900 < 0.915",
                              "RGB-D result vs pixels-only optimum 15.62 mm > 12.50 mm"],
         "p04-mug-handoff-00": ["inlier ratio 0.870 < 0.915"]}
FRAMES = 4
PAPER = Path(__file__).resolve().parents[2] / ".." / "shared" / "seeds" / \
    "towards-markerless-grasp-capture.tex"


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    cat = gc.open(tmp_path_factory.mktemp("card") / "cat", create=True)
    build = make_build(IDS, seed=7, frames=FRAMES, failed=(FAILED,))
    for row in build.sessions:
        if row["session_id"] in FLAGS:
            row["status"], row["qa_flags"] = "flagged", FLAGS[row["session_id"]]
    build.frames["reproj_err_px"][1, 4] = np.nan  # an unseen keypoint: left out of the stats
    assert cat.commit(build) == 1
    return cat


def export(capsys, catalog, out: Path, *extra: str) -> tuple[int, str, str]:
    code = main(["catalog", "export", "1", "--out", str(out), "--catalog",
                 str(catalog.layout.root), *extra])
    got = capsys.readouterr()
    return code, got.out, got.err


@pytest.fixture(scope="module")
def plain(catalog, tmp_path_factory):
    out = tmp_path_factory.mktemp("plain") / "x"
    code = main(["catalog", "export", "1", "--out", str(out), "--catalog",
                 str(catalog.layout.root), "--licence", "CC-BY-4.0"])
    assert code == 0
    return out


def _row(card: str, first: str) -> list[str]:
    """The cells of the table row whose first cell is ``first`` (in the first table that has
    one after the heading found by the caller)."""
    for line in card.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("|") and cells[0] == first:
            return cells
    raise AssertionError(f"no row {first!r}")


def _section(card: str, heading: str) -> str:
    return card.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0].strip()


def test_card_lists_every_object_participant_intent_with_counts(catalog, plain):
    card = (plain / "README.md").read_text(encoding="utf-8")
    sessions = catalog.table("sessions", 1).to_pylist()
    frames = Counter(catalog.table("frames", 1)["session_id"].to_pylist())
    for key, heading in (("object_id", "Objects"), ("participant", "Participants"),
                         ("intent", "Intents")):
        section = _section(card, heading)
        values = sorted({r[key] for r in sessions})
        assert len(values) > 1
        for value in values:
            mine = [r for r in sessions if r[key] == value]
            status = Counter(r["status"] for r in mine)
            assert _row(section, value) == [
                value, str(len(mine)), str(status["ok"]), str(status["flagged"]),
                str(status["failed"]), str(sum(frames[r["session_id"]] for r in mine))]


def test_card_qa_summary_licence_conventions_units_citation(catalog, plain, capsys, tmp_path):
    card = (plain / "README.md").read_text(encoding="utf-8")
    status = Counter(catalog.table("sessions", 1)["status"].to_pylist())
    assert status == {"ok": 2, "flagged": 2, "failed": 1}
    assert "- **Sessions**: 5 (2 ok, 2 flagged, 1 failed), **frames**: 16" in card
    qa = _section(card, "Quality (QA)")
    assert qa.startswith("2 session(s) ok, 2 flagged, 1 failed.")
    # reasons that differ only in their numbers count as one, the most common first
    assert qa.index("- 2 x inlier ratio # < #") < qa.index(
        "- 1 x RGB-D result vs pixels-only optimum # mm > # mm")
    assert "- 1 x register_object: no platter plane in stage1/depth.png" in qa
    assert "- **Licence**: CC-BY-4.0" in card
    assert "p_a = T_a_b @ p_b" in card and "OpenCV convention" in card
    assert "Metres and radians" in card and "catalog format `graspcap-catalog` 7" in card
    # every column of both tables with its unit and shape
    for schema in (SESSIONS_SCHEMA, FRAMES_SCHEMA):
        for f in schema:
            meta = f.metadata or {}
            cells = _row(_section(card, "Columns and units"), f"`{f.name}`")
            assert cells[2] == (meta.get(b"unit", b"").decode() or "-"), f.name
            assert cells[3] == (meta.get(b"shape", b"").decode() or "-"), f.name
    assert _row(card, "`object_mesh.vertices`")[1:4] == ["float32", "nx3", "m"]
    # the method's paper, title and authors as its LaTeX source gives them
    if PAPER.exists():
        tex = PAPER.read_text(encoding="utf-8")
        title = re.search(r"\\title\{(.+?)\}", tex).group(1)
        authors = re.search(r"\\author\{\s*(.+?)\\\\", tex, re.S).group(1)
        authors = re.sub(r"\$\^\{?[\d,]+\}?\$", "", authors)  # affiliation marks
        names = [a.strip() for a in re.split(r",\s*(?:and\s+)?|\s+and\s+", authors)]
        assert len(names) == 3
        assert f"*{title}*" in card and f"title  = {{{title}}}" in card
        assert f"author = {{{' and '.join(names)}}}" in card
    else:
        assert "*Towards Markerless Grasp Capture*" in card
    # the default licence says to set one
    code, _, _ = export(capsys, catalog, tmp_path / "d")
    assert code == 0
    assert f"- **Licence**: {DEFAULT_LICENCE}" in (tmp_path / "d" / "README.md").read_text(
        encoding="utf-8")


def _np_stats(values: np.ndarray) -> dict:
    values = values[~np.isnan(values)]
    return {"count": len(values), "mean": values.mean(), "std": values.std(),
            "min": values.min(), "max": values.max(), "p01": np.percentile(values, 1),
            "p99": np.percentile(values, 99)}


def _check(entry: dict, values: np.ndarray, dim: int | None = None) -> None:
    want = _np_stats(values)
    for key, value in want.items():
        got = entry[key] if dim is None else entry[key][dim]
        assert got == pytest.approx(value, rel=1e-12, abs=1e-15), key


def test_stats_equal_numpy(plain):
    stats = json.loads((plain / "stats.json").read_text())
    frames = pq.read_table(plain / "frames.parquet")
    sessions = pq.read_table(plain / "sessions.parquet")
    assert stats["version"] == 1 and stats["frames"]["frame"]["count"] == 16
    t_c_o = np.array(frames["T_c_o"].to_pylist()).reshape(-1, 4, 4)
    entry = stats["frames"]["T_c_o.translation"]
    assert entry["names"] == ["x", "y", "z"] and entry["unit"] == "m"
    for axis in range(3):
        _check(entry, t_c_o[:, axis, 3], axis)
    joints = np.array(frames["joints_c"].to_pylist()).reshape(-1, 21, 3)
    for axis in range(3):
        _check(stats["frames"]["joints_c"], joints[:, :, axis].ravel(), axis)
    err = np.array(frames["reproj_err_px"].to_pylist(), np.float64)
    assert np.isnan(err).sum() == 1 and stats["frames"]["reproj_err_px"]["count"][4] == 15
    for k in range(21):
        _check(stats["frames"]["reproj_err_px"], err[:, k], k)
    solved = np.array(frames["camera_solved"].to_pylist(), np.float64)
    _check(stats["frames"]["camera_solved"], solved)
    # sessions: nulls of the failed session left out
    scale = np.array([v for v in sessions["hand_scale"].to_pylist() if v is not None])
    assert len(scale) == 4
    _check(stats["sessions"]["hand_scale"], scale)
    angles = np.array([v for v in sessions["joint_angles_rad"].to_pylist() if v is not None])
    for k in range(20):
        _check(stats["sessions"]["joint_angles_rad"], angles[:, k], k)
    assert "session_id" not in stats["sessions"] and "qa_flags" not in stats["sessions"]
    # arrays: over the exported groups
    meshes = pq.read_table(plain / "object_mesh.parquet")
    verts = np.concatenate([np.array(v, np.float32) for v in meshes["vertices"].to_pylist()])
    for axis in range(3):
        _check(stats["arrays"]["object_mesh.vertices"], verts[:, axis].astype(np.float64), axis)
    contact = pq.read_table(plain / "contact.parquet")
    values = np.concatenate([np.array(v, np.float32) for v in contact["values"].to_pylist()])
    _check(stats["arrays"]["contact.values"], values.astype(np.float64))
    assert "object_mesh.faces" not in stats["arrays"]


def test_lerobot_layout(catalog, capsys, tmp_path):
    out = tmp_path / "lr"
    code, stdout, _ = export(capsys, catalog, out, "--format", "lerobot", "--fps", "15",
                             "--licence", "CC0-1.0")
    assert code == 0 and "exported version 1" in stdout
    info = json.loads((out / "meta" / "info.json").read_text())
    sessions = catalog.table("sessions", 1).to_pylist()
    frames = catalog.table("frames", 1).sort_by([("session_id", "ascending"),
                                                 ("frame", "ascending")])
    with_frames = sorted(r["session_id"] for r in sessions if r["status"] != "failed")
    assert info["codebase_version"] == "v3.0" and info["fps"] == 15
    assert info["total_episodes"] == len(with_frames) == 4
    assert info["total_frames"] == frames.num_rows == 16
    assert info["splits"] == {"train": "0:4"}
    path = info["data_path"].format(chunk_index=0, file_index=0)
    assert path == "data/chunk-000/file-000.parquet"
    data = pq.read_table(out / path)
    assert data.num_rows == 16
    # every feature is a column whose width matches its shape, and nothing else is
    assert set(data.column_names) == set(info["features"])
    for name, spec in info["features"].items():
        col = data[name]
        width = col.type.list_size if hasattr(col.type, "list_size") else 1
        assert [width] == spec["shape"], name
        assert spec["names"] is None or len(spec["names"]) == width, name
        item = col.type.value_type if width > 1 else col.type
        assert np.dtype(item.to_pandas_dtype()) == np.dtype(spec["dtype"]), name
    assert info["features"]["T_c_o"]["shape"] == [16]
    np.testing.assert_array_equal(data["index"].to_numpy(), np.arange(16))
    np.testing.assert_array_equal(data["T_c_o"].to_pylist(), frames["T_c_o"].to_pylist())
    np.testing.assert_array_equal(data["observation.hand_joints_c"].to_pylist(),
                                  frames["joints_c"].to_pylist())
    # episodes: lengths sum to the frames, contiguous ranges, one per session with frames
    episodes = pq.read_table(out / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    ep = episodes.to_pylist()
    assert episodes.schema.field("hand_shape").type == pa.list_(pa.float64(), 20)
    assert episodes.schema.field("hand_scale").type == pa.float64()
    assert [e["session_id"] for e in ep] == with_frames
    assert [e["episode_index"] for e in ep] == [0, 1, 2, 3]
    assert sum(e["length"] for e in ep) == info["total_frames"]
    by_id = {r["session_id"]: r for r in sessions}
    tasks = pq.read_table(out / "meta" / "tasks.parquet").to_pylist()
    task_of = {t["task_index"]: t["task"] for t in tasks}
    assert info["total_tasks"] == len(tasks) == 3  # mug/use, drill/use, mug/handoff
    episode_col, frame_index = data["episode_index"].to_numpy(), data["frame_index"].to_numpy()
    for e in ep:
        row = by_id[e["session_id"]]
        assert (e["object_id"], e["participant"], e["status"]) == (
            row["object_id"], row["participant"], row["status"])
        # the subject's hand round-trips exactly: scale and 20 bone lengths (m)
        assert row["hand_shape"] is not None and len(row["hand_shape"]) == 20
        assert e["hand_scale"] == row["hand_scale"] and e["hand_shape"] == row["hand_shape"]
        lo, hi = e["dataset_from_index"], e["dataset_to_index"]
        assert hi - lo == e["length"] == FRAMES
        assert (episode_col[lo:hi] == e["episode_index"]).all()
        np.testing.assert_array_equal(frame_index[lo:hi], np.arange(FRAMES))
        np.testing.assert_allclose(data["timestamp"].to_numpy()[lo:hi], np.arange(FRAMES) / 15,
                                   rtol=1e-6)
        task = task_text(row["object_id"], row["intent"])
        assert e["tasks"] == [task]
        assert {task_of[t] for t in data["task_index"].to_numpy()[lo:hi]} == {task}
        state = np.array(data["observation.state"].to_pylist()[lo], np.float32)
        want = np.r_[row["joint_angles_rad"],
                     frames["T_c_p"].to_pylist()[lo]].astype(np.float32)
        np.testing.assert_array_equal(state, want)
    # meta/stats.json: LeRobot's keys per feature, equal to numpy over the data column
    stats = json.loads((out / "meta" / "stats.json").read_text())
    assert set(stats) == set(info["features"])
    t = np.array(data["T_c_o"].to_pylist())
    for key, fn in (("mean", np.mean), ("std", np.std), ("min", np.min), ("max", np.max)):
        np.testing.assert_allclose(stats["T_c_o"][key], fn(t, axis=0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(stats["T_c_o"]["q01"], np.percentile(t, 1, axis=0), rtol=1e-12,
                               atol=1e-15)
    assert stats["T_c_o"]["count"] == [16]
    card = (out / "README.md").read_text(encoding="utf-8")
    assert "- **Licence**: CC0-1.0" in card and "- `meta/info.json`" in card
    assert "Towards Markerless Grasp Capture" in card


def test_export_refuses_bad_format_and_fps(catalog, capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["catalog", "export", "1", "--out", str(tmp_path / "b"), "--format", "lerobo",
              "--catalog", str(catalog.layout.root)])
    assert exc.value.code == 2 and "invalid choice: 'lerobo'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["catalog", "export", "1", "--out", str(tmp_path / "b"), "--fps", "0",
              "--catalog", str(catalog.layout.root)])
    assert exc.value.code == 2 and "must be a number > 0" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_stats_merge_chunks_like_numpy_over_the_whole_column():
    """Mean and variance are merged chunk by chunk: several chunks with nulls and NaN give
    numpy's statistics of the whole column."""
    rng = np.random.default_rng(3)
    rows = [list(rng.normal(size=16) * 10 + 5) for _ in range(50)]
    rows[7] = None
    rows[11][3] = np.nan
    pose = SESSIONS_SCHEMA.field("T_adj")
    scalar = [float(v) for v in rng.uniform(-3, 9, 50)]
    scalar[4] = None
    table = pa.table({
        "T_adj": pa.chunked_array([pa.array(rows[i:i + 13], pose.type)
                                   for i in range(0, 50, 13)]),
        "hand_scale": pa.chunked_array([pa.array(scalar[:1]), pa.array(scalar[1:30]),
                                        pa.array([], pa.float64()), pa.array(scalar[30:])]),
    }, schema=pa.schema([pose, SESSIONS_SCHEMA.field("hand_scale")]))
    assert table["T_adj"].num_chunks == 4
    stats = table_stats(table)
    t = np.array([r for r in rows if r is not None], np.float64)
    for axis, k in enumerate((3, 7, 11)):
        _check(stats["T_adj.translation"], t[:, k], axis)
    assert stats["T_adj.translation"]["count"] == [48, 49, 49]
    _check(stats["hand_scale"], np.array([v for v in scalar if v is not None]))


def test_export_without_a_version_takes_the_latest(catalog, capsys, tmp_path):
    code = main(["catalog", "export", "--out", str(tmp_path / "l"), "--catalog",
                 str(catalog.layout.root)])
    assert code == 0 and "exported version 1" in capsys.readouterr().out
    assert json.loads((tmp_path / "l" / "manifest.json").read_text())["version"] == 1


def test_lerobot_of_a_version_where_every_session_failed_is_empty_but_valid(tmp_path, capsys):
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(make_build([FAILED], seed=2, failed=(FAILED,)))
    code, _, err = export(capsys, cat, tmp_path / "lr", "--format", "lerobot")
    assert code == 0, err
    info = json.loads((tmp_path / "lr" / "meta" / "info.json").read_text())
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (0, 0, 0)
    data = pq.read_table(tmp_path / "lr" / "data" / "chunk-000" / "file-000.parquet")
    assert data.num_rows == 0 and set(data.column_names) == set(info["features"])
    stats = json.loads((tmp_path / "lr" / "meta" / "stats.json").read_text())
    assert stats["T_c_o"]["count"] == [0] and stats["T_c_o"]["mean"] == [None] * 16
    card = (tmp_path / "lr" / "README.md").read_text(encoding="utf-8")
    assert "0 ok, 0 flagged, 1 failed" in card


def test_lerobot_data_reads_with_the_hugging_face_parquet_loader(catalog, capsys, tmp_path):
    """Where `datasets` is installed: its Parquet loader reads the data and episodes files,
    and each feature of info.json comes back with its length."""
    datasets = pytest.importorskip("datasets", reason="the Hugging Face `datasets` package is "
                                   "not installed (not a dependency of graspcap)")
    out = tmp_path / "lr"
    assert export(capsys, catalog, out, "--format", "lerobot")[0] == 0
    info = json.loads((out / "meta" / "info.json").read_text())
    data = datasets.load_dataset("parquet", data_files=str(out / info["data_path"].format(
        chunk_index=0, file_index=0)), split="train", cache_dir=str(tmp_path / "hf"))
    assert data.num_rows == info["total_frames"]
    assert set(data.column_names) == set(info["features"])
    row = data[5]
    for name, spec in info["features"].items():
        value = row[name]
        assert (len(value) if isinstance(value, list) else 1) == spec["shape"][0], name
    episodes = datasets.load_dataset("parquet", data_files=str(
        out / "meta" / "episodes" / "chunk-000" / "file-000.parquet"), split="train",
        cache_dir=str(tmp_path / "hf"))
    assert sum(episodes["length"]) == info["total_frames"]
