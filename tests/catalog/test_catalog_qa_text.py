"""``sessions.qa_flags`` / ``qa_notes`` (format 4, list<string>) on the read side: validation,
GraspDataset.session_qa, diff, and export (Parquet lists, CSV JSON text)."""

from __future__ import annotations

import json
import pickle

import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest

import graspcap.catalog as gc
from graspcap.catalog.export import export_version
from tests.catalog_factory import make_build

IDS = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-handoff-00"]
FLAG = "RGB-D result vs pixels-only optimum 15.62 mm > 12.50 mm"
NOTE = "estimate_adjustment: ambiguous (the pose nearest stage 1 kept)"


def _build(seed: int, build_id: str, notes: list[str]) -> gc.BuildCommit:
    """p01 flagged with FLAG and ``notes``, p02 ok with no reasons, p03 failed."""
    build = make_build(IDS, seed=seed, build_id=build_id, failed=(IDS[2],))
    rows = build.sessions
    rows[0].update(status="flagged", qa_flags=[FLAG], qa_notes=list(notes))
    assert rows[1]["qa_flags"] == [] == rows[1]["qa_notes"]
    assert rows[2]["qa_flags"] is None and rows[2]["qa_notes"] is None
    return build


@pytest.fixture(scope="module")
def cat(tmp_path_factory):
    cat = gc.open(tmp_path_factory.mktemp("qa") / "cat", create=True)
    assert cat.commit(_build(1, "b1", [NOTE])) == 1
    assert cat.commit(_build(1, "b2", [NOTE, "refine_grasp: refinement rejected"])) == 2
    return cat


def test_a_string_is_not_a_list_of_reasons(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    build = _build(1, "b1", [NOTE])
    build.sessions[0]["qa_flags"] = FLAG  # would be stored as one reason per character
    with pytest.raises(gc.CatalogSchemaError, match=r"qa_flags.*expected a list of string"):
        cat.commit(build)
    assert cat.latest_version() is None


def test_dataset_gives_each_sessions_flags_and_notes(cat):
    ds = gc.GraspDataset(cat, 1, unit="sessions", status=("ok", "flagged"))
    assert ds.session_ids == IDS[:2]
    assert ds.session_qa(IDS[0]) == {"status": "flagged", "qa_flags": [FLAG],
                                     "qa_notes": [NOTE]}
    assert ds.session_qa(IDS[1]) == {"status": "ok", "qa_flags": [], "qa_notes": []}
    assert "qa_flags" not in ds[0] and "qa_notes" not in ds[0]  # items stay collatable
    again = pickle.loads(pickle.dumps(ds))  # as a DataLoader worker gets it
    assert again.session_qa(IDS[0])["qa_flags"] == [FLAG]
    rest, held = ds.split_by("object_id", ["mug"])
    assert held.session_qa(IDS[0])["qa_notes"] == [NOTE] and rest.session_ids == [IDS[1]]
    assert gc.GraspDataset(cat, 2, unit="sessions").session_ids == [IDS[1]]  # "ok" only
    failed = gc.GraspDataset(cat, 2, unit="sessions", status=("failed",))
    assert failed.session_qa(IDS[2]) == {"status": "failed", "qa_flags": None,
                                         "qa_notes": None}


def test_diff_names_a_changed_note(cat):
    # same seed, same rows: only p01's second note and every row's build_id differ
    assert cat.diff(1, 2)["changed"] == {IDS[0]: ["qa_notes", "build_id"],
                                         IDS[1]: ["build_id"], IDS[2]: ["build_id"]}


def test_export_keeps_the_lists(cat, tmp_path):
    export_version(cat, 2, tmp_path / "p")
    got = {r["session_id"]: r for r in pq.read_table(tmp_path / "p" / "sessions.parquet")
           .to_pylist()}
    assert got[IDS[0]]["qa_notes"] == [NOTE, "refine_grasp: refinement rejected"]
    assert got[IDS[0]]["qa_flags"] == [FLAG] and got[IDS[1]]["qa_flags"] == []
    assert got[IDS[2]]["qa_flags"] is None
    assert pq.read_schema(tmp_path / "p" / "sessions.parquet").field(
        "qa_flags").type == pa.list_(pa.string())
    export_version(cat, 2, tmp_path / "c", "csv")
    rows = {r["session_id"]: r for r in pacsv.read_csv(tmp_path / "c" / "sessions.csv")
            .to_pylist()}
    assert json.loads(rows[IDS[0]]["qa_flags"]) == [FLAG]
    assert json.loads(rows[IDS[1]]["qa_notes"]) == []
    assert rows[IDS[2]]["qa_flags"] in ("", None)  # null: an empty cell, not "[]"
