"""The bare pipeline (``run_session``) treats a failing aid stage as the build does: a note
in its results, the session's results standing; any other stage's failure still raises."""

from __future__ import annotations

import dataclasses

import pytest

from graspcap.tasks import pipeline
from graspcap.tasks.core.errors import StageError
from tests.flow_fixtures import PRESET


def _first(root):
    return sorted(p for p in root.iterdir() if (p / "session.json").exists())[0]


def test_failing_pictures_is_a_note_in_run_sessions_results(synth_root, monkeypatch):
    calls = []

    def broken(session, config, **up):
        calls.append(str(up["qa_metrics"].verdict))
        raise StageError("pictures", "offscreen renderer unavailable", session=session.session_id)

    monkeypatch.setitem(pipeline.STAGES, "pictures",
                        dataclasses.replace(pipeline.STAGES["pictures"], run=broken))
    timings: dict[str, float] = {}
    results = pipeline.run_session(_first(synth_root), pipeline.configs_for(PRESET), timings)
    assert calls == [str(results["qa_metrics"].verdict)]  # ran once, after the QA verdict
    assert "pictures" not in results
    assert set(results) == (set(pipeline.STAGES) - {"pictures"}) | {pipeline.NOTES}
    assert all(results[name] is not None for name in pipeline.STAGES if name != "pictures")
    # clean detections (the default mode, auto): the staged result, passed on
    assert results["joint_solve"].path == "staged"
    assert results["reconstruct_hand"] is results["joint_solve"].reconstruction
    (note,) = results[pipeline.NOTES]
    assert "pictures: offscreen renderer unavailable" in note and "a QA aid" in note
    assert set(timings) == set(pipeline.STAGES)


def test_a_bug_in_an_aid_stage_is_a_note_too_and_other_stages_still_raise(synth_root,
                                                                          monkeypatch):
    def boom(*_, **__):
        raise ValueError("bad shape")

    monkeypatch.setitem(pipeline.STAGES, "register_object",
                        dataclasses.replace(pipeline.STAGES["register_object"], run=boom))
    with pytest.raises(ValueError, match="bad shape"):
        pipeline.run_session(_first(synth_root), pipeline.configs_for(PRESET))

    fake = {"load_session": pipeline.STAGES["load_session"],
            "pictures": dataclasses.replace(pipeline.STAGES["pictures"], upstream=(), run=boom),
            "after": dataclasses.replace(pipeline.STAGES["pictures"], name="after", upstream=(),
                                         run=lambda session, config: "ran")}
    monkeypatch.setattr(pipeline, "STAGES", fake)  # the stage after an aid still runs
    results = pipeline.run_session(_first(synth_root), pipeline.configs_for(PRESET))
    assert results["after"] == "ran" and "pictures" not in results
    assert results[pipeline.NOTES] == (
        "pictures: ValueError: bad shape (a QA aid: the session's results stand without it)",)
