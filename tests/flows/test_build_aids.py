# ruff: noqa: F811  (fixtures imported from tests.flow_fixtures)
"""A failing aid stage (pictures) leaves the session committed with a note, never failed."""

from __future__ import annotations

import dataclasses
import json
import shutil

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.tasks.core.errors import StageError
from tests.flow_fixtures import (  # noqa: F401
    PRESET,
    copy_catalog,
    executions,
    prefect_harness,
    require_pipeline_passes,
    synth_root,
    warm,
)


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
