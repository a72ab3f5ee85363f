"""``sessions.qa_flags`` and ``qa_notes`` (format 4): a real build writes each session's
``QaReport.flags`` and ``notes`` (a flag forced by a zero reprojection limit; a note from a
refinement that finds no contact and keeps the stage-3 fit), and a row without them (written
before format 4) is rewritten from the cached results by the next build, no stage running."""

from __future__ import annotations

import pickle

import pyarrow as pa

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from tests.flow_fixtures import PRESET, copy_catalog, executions

OVERRIDES = {
    # every session crosses this flag limit, none the fail limit
    "qa_metrics": {"reproj_rmse_px": {"flag": 0.0, "fail": 100.0}},
    # no vertex reaches contact 1.01: the refinement is rejected, the fit kept (a QA note)
    "refine_grasp": {"contact_threshold": 1.01},
}
REJECTED = "refine_grasp: refinement rejected, the stage-3 fit kept"


def _reports(catalog) -> list:
    return [pickle.loads(p.read_bytes())
            for p in (catalog / "work" / "results" / "qa_metrics").glob("*.pkl")]


def _report_of(row: dict, reports: list, *, rejected: bool):
    """The one cached QaReport of ``row``'s session and build: same reprojection RMSE (a
    per-session value no override changes), with or without the rejected refinement's note."""
    mine = [q for q in reports if q.metrics.get("reproj_rmse_px") == row["qa_reproj_rmse_px"]
            and any(REJECTED in n for n in q.notes) == rejected]
    assert len(mine) == 1, (row["session_id"], len(mine))
    return mine[0]


def test_rows_carry_the_qa_reports_flags_and_notes(warm, synth_root, tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    warm_rows = gc.open(catalog).table("sessions").to_pylist()
    for r in warm_rows:  # the warm build: lists, equal to its reports' (empty or not)
        q = _report_of(r, _reports(catalog), rejected=False)
        assert r["qa_flags"] == list(q.flags) and r["qa_notes"] == list(q.notes), r["session_id"]

    report = build_dataset([synth_root], catalog, PRESET, overrides=OVERRIDES, build_id="noted")
    assert not report.failed
    cat = gc.open(catalog)
    rows = cat.table("sessions").to_pylist()
    assert len(rows) == len(warm_rows) == 2
    reports = _reports(catalog)
    for r in rows:
        q = _report_of(r, reports, rejected=True)
        assert r["status"] == str(q.verdict) == "flagged", r["session_id"]
        assert r["qa_flags"] == list(q.flags) and r["qa_notes"] == list(q.notes)
        assert any(f.startswith("reprojection RMSE ") and "> 0.00 px" in f
                   for f in r["qa_flags"]), r["qa_flags"]
        assert any(n.startswith(REJECTED) for n in r["qa_notes"]), r["qa_notes"]
        assert r["error"] is None

    # rows as a format-3 catalog had them (no qa_flags, qa_notes, camera_solved): the next
    # build rewrites them from the cached results (predates_columns), running no stage
    sessions, frames = cat.table("sessions"), cat.table("frames")
    old, old_frames = sessions, frames
    for col in ("qa_flags", "qa_notes"):
        i = old.schema.get_field_index(col)
        old = old.set_column(i, old.schema.field(i), pa.nulls(old.num_rows, old.schema[i].type))
    i = frames.schema.get_field_index("camera_solved")
    old_frames = frames.set_column(i, frames.schema.field(i), pa.nulls(frames.num_rows, pa.bool_()))
    v = cat.commit(gc.BuildCommit(gc.BuildInfo("pre-format-4", "old", "x" * 64), sessions=old,
                                  frames=old_frames))
    assert cat.table("sessions", v)["qa_flags"].null_count == old.num_rows
    again = build_dataset([synth_root], catalog, PRESET, overrides=OVERRIDES, build_id="fill4")
    assert executions(catalog, "fill4") == []
    assert again.catalog_version == v + 1 and len(again.changed) == old.num_rows
    new = cat.table("sessions", v + 1).sort_by("session_id")
    for col in ("qa_flags", "qa_notes"):
        assert new[col].to_pylist() == sessions.sort_by("session_id")[col].to_pylist(), col
    by_key = [("session_id", "ascending"), ("frame", "ascending")]
    refilled = cat.table("frames", v + 1).sort_by(by_key)["camera_solved"]
    assert refilled.null_count == 0
    assert refilled.to_pylist() == frames.sort_by(by_key)["camera_solved"].to_pylist()
