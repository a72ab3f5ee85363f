"""Issue 15's "done when": every kind of the reliability corpus, each one session among four
good ones, in ONE real build: one version, every good session committed, a reason for every
bad one (a failed row naming file and field for the invalid kinds), nothing written outside
the catalog."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.flows.report import Outcome
from graspcap.tasks.session.discover import NOT_A_SESSION
from tests.flow_fixtures import PRESET
from tests.reliability_corpus import DUPLICATE_ID, KINDS, Builds, Fails, Invalid, prepare

GOOD = 4


def _good_sessions(synth_root: Path, root: Path) -> list[str]:
    """Four sessions the stages get through: the fixture's two, each twice, ids
    ``good-session-0..3`` (the corpus's duplicate-id kind takes the first)."""
    sources = sorted(p for p in synth_root.iterdir() if (p / "session.json").exists())
    ids = []
    for i in range(GOOD):
        d = root / f"good-{i}"
        shutil.copytree(sources[i % len(sources)], d)
        manifest = json.loads((d / "session.json").read_text())
        manifest["session_id"] = f"good-session-{i}"
        (d / "session.json").write_text(json.dumps(manifest))
        ids.append(manifest["session_id"])
    assert ids[0] == DUPLICATE_ID
    return ids


def test_the_whole_corpus_and_four_good_sessions_in_one_build(synth_root, prefect_harness,
                                                              tmp_path):
    root = tmp_path / "sessions"
    good = _good_sessions(synth_root, root / "a-good")
    folders = {kind.name: prepare(root / "b-kinds" / kind.slug, kind) for kind in KINDS}
    catalog = tmp_path / "catalog"

    # the fast preset skips decoding images at load; a user's default build decodes them
    report = build_dataset([root], catalog, PRESET, build_id="corpus",
                           overrides={"load_session": {"check_images": True}})

    cat = gc.open(catalog)
    assert [v["version"] for v in cat.versions().to_pylist()] == [1]
    assert report.catalog_version == 1
    rows = {r["session_id"]: r for r in cat.table("sessions").to_pylist()}
    for sid in good:
        assert rows[sid]["status"] in ("ok", "flagged"), (sid, rows[sid]["error"])
    by_dir = {Path(s.session_dir).resolve(): s for s in report.sessions}
    not_sessions = {Path(p).resolve() for p in report.parameters["not_sessions"]}
    summary = report.summary()
    for kind in KINDS:
        folder = folders[kind.name].resolve()
        manifest = folder / "session.json"
        if not manifest.exists() or manifest.is_dir():  # no manifest entry: not a session
            assert folder in not_sessions, kind.name
            assert f"SKIPPED {folders[kind.name]}: {NOT_A_SESSION}" in summary
            continue
        s = by_dir[folder]
        outcome = kind.outcome
        if s.outcome != Outcome.FAILED:  # built: only a valid kind may
            assert isinstance(outcome, Builds), (kind.name, s)
            assert rows[s.session_id]["status"] in ("ok", "flagged")
            continue
        assert s.error, kind.name
        if isinstance(outcome, Invalid):
            assert s.failed_stage == "load_session", (kind.name, s.error)
            assert outcome.file in s.error, (kind.name, s.error)
            if outcome.field != "(file)":
                assert outcome.field in s.error, (kind.name, s.error)
        if isinstance(outcome, Fails) and outcome.stage == "build":  # the duplicate id
            assert outcome.message_contains in s.error and str(folder) in s.error
            assert rows[DUPLICATE_ID]["status"] in ("ok", "flagged")  # the first folder's row
            continue
        # a failed row with the reason, or a previous good row kept (none: a new catalog)
        row = rows.get(s.session_id)
        assert row is not None and row["status"] == "failed" and row["error"], (kind.name, s)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["catalog", "sessions"]
    # every kind reached the catalog or the report: nothing lost, nothing committed twice
    assert len(rows) == len({s.session_id for s in report.sessions})
