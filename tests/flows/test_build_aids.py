"""A failing aid stage (pictures) leaves the session committed with a note, never failed."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.tasks.core.errors import StageError
from tests.flow_fixtures import PRESET, copy_catalog
from tests.report_html import check_page


def test_failing_pictures_leave_the_session_committed_with_a_note(warm, synth_root, tmp_path,
                                                                   monkeypatch):
    from graspcap.flows.commands import status_text
    from graspcap.tasks import pipeline

    assert pipeline.AID_STAGES == {"pictures"}
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    shutil.rmtree(catalog / "work" / "results" / "pictures")
    shutil.rmtree(catalog / "work" / "results" / "qa_metrics")  # the row is rebuilt
    before = {r["session_id"]: r for r in gc.open(catalog).table("sessions").to_pylist()}

    def broken(session, config, **_):
        raise StageError("pictures", "offscreen renderer unavailable", session=session.session_id)

    monkeypatch.setitem(pipeline.STAGES, "pictures",
                        dataclasses.replace(pipeline.STAGES["pictures"], run=broken))
    report = build_dataset([synth_root], catalog, PRESET, build_id="nopics")
    assert report.failed == {}
    ids = sorted(before)
    assert sorted(s.session_id for s in report.sessions) == ids
    for s in report.sessions:
        assert s.error is None and s.failed_stage is None
        assert s.status == before[s.session_id]["status"] != "failed"
        assert len(s.notes) == 1 and "offscreen renderer unavailable" in s.notes[0]
        assert "pictures" not in s.ran and "qa_metrics" in s.ran
    assert "note " in report.summary() and "offscreen renderer unavailable" in report.summary()
    after = {r["session_id"]: r for r in gc.open(catalog).table("sessions").to_pylist()}
    assert all(after[i]["build_id"] == "nopics" and after[i]["status"] != "failed"
               for i in ids)
    record = json.loads(gc.open(catalog).table("builds").sort_by("catalog_version")
                        .to_pylist()[-1]["parameters_json"])["report"]
    assert record["summary"]["failed"] == {}
    assert all("offscreen" in x["notes"][0] for x in record["sessions"])
    assert "offscreen renderer unavailable (a QA aid" in status_text(catalog)
    # the page shows each session without pictures, with the note
    page = check_page(Path(report.report_page))
    for sid in ids:
        assert "offscreen renderer unavailable" in page.row_text(sid)
        assert "no pictures" in page.row_text(sid)

    # a page that cannot be written is a warning: the build stands (here: nothing changed)
    import graspcap.catalog.report_page as report_page

    def disk_full(*_, **__):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report_page, "write_report", disk_full)
    again = build_dataset([synth_root], catalog, PRESET, build_id="nopage")
    assert again.report_page is None and again.failed == {} and again.catalog_version is None
    assert "report:" not in again.summary()
    assert not (catalog / "reports" / "nopage").exists()
