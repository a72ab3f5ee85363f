"""Write-audit-publish: a version whose audit fails is staged, readers stay on the published one;
``publish`` moves them, ``reject`` drops a version from the next build's base."""

from __future__ import annotations

import dataclasses
import json

import pyarrow.compute as pc
import pytest

import graspcap.catalog as gc
from graspcap.catalog.audit import AuditGates, audit_version, parse_gates
from graspcap.catalog.cli import summary
from graspcap.catalog.delta import table_versions_of
from graspcap.catalog.report_page import write_report
from graspcap.cli import main
from tests.catalog_factory import make_build

IDS = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-use-00", "p04-mug-use-00"]
STRICT = AuditGates(tolerated_sessions=0)
"""The default gates without the small-catalog allowance, so four sessions can fail them."""


def _ids(table) -> list[str]:
    return sorted(table["session_id"].to_pylist())


def _status(cat, version=None) -> dict[str, str]:
    t = cat.table("sessions", version)
    return dict(zip(t["session_id"].to_pylist(), t["status"].to_pylist(), strict=True))


@pytest.fixture
def staged(tmp_path):
    """Version 1 published (four ok sessions), version 2 staged (three of them failed)."""
    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    assert cat.commit(make_build(IDS, seed=1, build_id="b1"), STRICT) == 1
    assert cat.commit(make_build(IDS[:3], seed=2, build_id="b2", failed=tuple(IDS[:3])),
                      STRICT) == 2
    return root


def test_a_failed_audit_leaves_readers_on_the_published_version(staged):
    cat = gc.open(staged)
    assert cat.states() == {1: "published", 2: "staged"}
    assert cat.latest_version() == 2 and cat.published_version() == 1
    # open(), the file lists of the one-liners and GraspDataset read version 1 by default
    assert cat.table("sessions").equals(cat.table("sessions", 1))
    assert cat.files("frames") == cat.files("frames", 1)
    assert gc.GraspDataset(staged).version == 1
    assert set(_status(cat).values()) == {"ok"}
    # the staged version reads by number (time travel is untouched)
    assert _status(cat, 2) == {**dict.fromkeys(IDS[:3], "failed"), IDS[3]: "ok"}
    # its audit is in its builds row, with the reasons
    row = cat.table("builds", 2).filter(pc.equal(pc.field("catalog_version"), 2)).to_pylist()[0]
    assert row["audit_passed"] is False
    assert row["audit_reasons"] == [
        "failed share: 75.0% of sessions failed, 0.0% in published version 1 (rise 75.0% > "
        "max_failed_share_rise 10.0%)",
        "row count: frames has 3 rows, published version 1 had 12 (a drop of 75.0% > "
        "max_frames_drop_share 50.0%)"]
    audit = cat.audit(2)
    assert audit["compared_to"] == 1 and audit["measured"]["failed_sessions"] == 3
    assert cat.audit(1) == {**cat.audit(1), "passed": True, "compared_to": None, "reasons": []}
    assert [r["state"] for r in cat.versions().to_pylist()] == ["published", "staged"]
    assert summary(cat, 2)["state"] == "staged" and summary(cat)["version"] == 1


def test_publish_moves_readers_and_reject_marks_a_version(staged, capsys):
    assert main(["catalog", "publish", "2", "--catalog", str(staged)]) == 0
    assert "version 2 published; readers' default is version 2" in capsys.readouterr().out
    cat = gc.open(staged)
    assert cat.published_version() == 2 and cat.table("sessions").equals(cat.table("sessions", 2))
    assert gc.GraspDataset(staged, valid_only=False).version == 2
    assert not cat.publish(2)  # already published: nothing written
    # reject it: readers go back to version 1, which is still published
    assert main(["catalog", "reject", "2", "--catalog", str(staged), "--reason", "bad"]) == 0
    out = capsys.readouterr().out
    assert "version 2 rejected; readers' default is version 1" in out
    assert "the next build is written on top of version 1" in out
    cat = gc.open(staged)
    assert cat.states() == {1: "published", 2: "rejected"} and cat.base_version() == 1
    assert main(["catalog", "versions", "--catalog", str(staged)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "published" in lines[1] and lines[1].endswith("<- readers' default")
    assert "rejected" in lines[2]
    assert main(["catalog", "versions", "--json", "--catalog", str(staged)]) == 0
    assert [r["state"] for r in json.loads(capsys.readouterr().out)] == ["published",
                                                                          "rejected"]


def test_the_next_build_is_written_on_top_of_the_newest_version_not_rejected(staged, capsys):
    cat = gc.open(staged)
    v1 = {n: cat.table(n, 1) for n in ("sessions", "frames")}
    v2 = {n: cat.table(n, 2) for n in ("sessions", "frames")}
    cat.reject(2)
    assert cat.commit(make_build(["p05-bowl-use-00"], seed=5, build_id="b3"), STRICT) == 3
    cat = gc.open(staged)
    assert cat.states()[3] == "published" and cat.published_version() == 3
    # version 3 is version 1 plus the new session: nothing of the rejected version 2
    three = cat.table("sessions", 3)
    assert _ids(three) == sorted([*IDS, "p05-bowl-use-00"])
    assert three.filter(pc.is_in(three["session_id"], v1["sessions"]["session_id"])).sort_by(
        "session_id").equals(v1["sessions"].sort_by("session_id"))
    assert cat.audit(3)["compared_to"] == 1 and cat.audit(3)["passed"]
    assert cat.diff(1, 3) == {"added": ["p05-bowl-use-00"], "removed": [], "changed": {}}
    for name, table in v2.items():  # the rejected version still reads what it held
        assert cat.table(name, 2).equals(table)
    # a version with a newer one on top of it cannot be rejected alone
    with pytest.raises(gc.CatalogError, match=r"version\(s\) \[3\] were written on top"):
        cat.reject(1)
    assert main(["catalog", "reject", "1", "--catalog", str(staged)]) == 2
    assert "reject them first" in capsys.readouterr().err
    assert cat.problems() == []


def test_regressions_of_unchanged_inputs_stage_a_version(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    first = make_build(IDS, seed=1, build_id="b1")
    assert cat.commit(first, STRICT) == 1
    # the same inputs (input_digest), two verdicts worse: ok -> flagged
    rows = [dict(r, build_id="b2") for r in first.sessions]
    for r in rows[:2]:
        r.update(status="flagged", qa_flags=["inlier ratio 0.900 < 0.915"])
    again = dataclasses.replace(first, build=dataclasses.replace(first.build, build_id="b2"),
                                sessions=rows)
    assert cat.commit(again, STRICT) == 2
    audit = cat.audit(2)
    assert not audit["passed"] and cat.published_version() == 1
    assert audit["measured"]["regressed"] == {IDS[0]: "ok -> flagged", IDS[1]: "ok -> flagged"}
    assert audit["reasons"] == [
        f"QA regressions: 2 of 4 session(s) whose inputs did not change got a worse verdict "
        f"than in published version 1: {IDS[0]} (ok -> flagged), {IDS[1]} (ok -> flagged) "
        "(50.0% > max_regressed_share 5.0%)"]
    # with two regressions tolerated (the default) or the gate off, it is published
    assert cat.commit(dataclasses.replace(again, build=dataclasses.replace(
        first.build, build_id="b3")), AuditGates()) == 3
    assert cat.states()[3] == "published" and cat.audit(3)["passed"]


def test_lost_sessions_rows_and_the_schema_are_checked(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(make_build(IDS, seed=1, build_id="b1"), STRICT)
    assert cat.remove([IDS[0]], "withdrawn") == 2  # on purpose: published, not audited
    pins = {v: table_versions_of(r) for v, r in
            ((r["version"], r) for r in cat.versions().to_pylist())}
    lost = audit_version(cat.layout, pins[2], (1, pins[1]), STRICT)
    assert lost.reasons == [f"lost sessions: 1 session(s) of published version 1 are missing: "
                            f"{IDS[0]} (max_lost_sessions 0)"]
    assert audit_version(cat.layout, pins[2], (1, pins[1]), STRICT, removed=[IDS[0]]).passed
    # an ok session without frames rows
    empty = make_build(["p09-bowl-use-00"], seed=9, build_id="b3")
    empty = dataclasses.replace(empty, frames=[])
    assert cat.commit(empty, STRICT) == 3
    assert cat.audit(3)["reasons"] == ["rows: 1 ok/flagged session(s) without frames rows: "
                                       "p09-bowl-use-00"]
    assert cat.states()[3] == "staged"
    # a commit without gates on top of a staged version is staged too
    assert cat.commit(make_build(["p10-mug-use-00"], seed=10, build_id="b4")) == 4
    assert cat.states()[4] == "staged" and cat.audit(4) is None
    assert cat.published_version() == 2


def test_vacuum_keeps_the_published_version(staged):
    cat = gc.open(staged)
    cat.commit(make_build(IDS[:1], seed=3, build_id="b3", failed=(IDS[0],)), STRICT)
    before = cat.table("frames", 1)
    report = cat.vacuum(1)
    assert report.kept_versions == [1, 3]
    assert gc.open(staged).table("frames").equals(before)


def test_auto_publish_off_stages_a_passing_version_and_gates_parse(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    assert cat.commit(make_build(IDS, seed=1), parse_gates(["auto_publish=false"])) == 1
    assert cat.audit(1)["passed"] and cat.states() == {1: "staged"}
    with pytest.raises(gc.VersionNotFound, match=r"no published version \(staged: \[1\]"):
        cat.table("sessions")
    assert parse_gates(["max_lost_sessions=off", "max_failed_share=0.3"]) == AuditGates(
        max_lost_sessions=None, max_failed_share=0.3)
    with pytest.raises(ValueError, match="NAME one of max_failed_share"):
        parse_gates(["max_lost=1"])
    with pytest.raises(ValueError, match="max_failed_share"):
        parse_gates(["max_failed_share=2"])


def test_the_report_page_shows_the_audit(staged):
    page = write_report(gc.open(staged), 2).read_text()
    assert '<div class="audit bad" id="audit"><b>staged</b>: audit FAILED against published ' \
           "version 1; readers read version 1 by default" in page
    assert "<li>failed share: 75.0% of sessions failed" in page
    assert "graspcap catalog publish 2" in page
    page = write_report(gc.open(staged), 1).read_text()
    assert '<div class="audit ok" id="audit"><b>published</b>: audit passed;' in page


def test_a_wrong_gate_is_refused_before_anything_is_made(tmp_path, capsys):
    roots = tmp_path / "captures"
    roots.mkdir()
    code = main(["serve", str(roots), "--cron", "0 2 * * *", "--gate", "max_lost=1",
                 "--catalog", str(tmp_path / "cat")])
    assert code == 2 and not (tmp_path / "cat").exists()
    assert "--gate 'max_lost=1': give NAME=VALUE with NAME one of max_failed_share" \
        in capsys.readouterr().err
