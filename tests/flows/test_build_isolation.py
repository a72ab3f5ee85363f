"""Nothing that happens to one session loses the others: rows, the commit's checks, pictures,
duplicated and path-like session ids; a build-level failure keeps the work for the next build;
``graspcap build``'s exit codes."""

from __future__ import annotations

import errno
import json
import shutil
import uuid
from pathlib import Path

import pytest

import graspcap.catalog as gc
from graspcap.catalog.layout import PLAIN_NAME, CatalogLayout, path_name
from graspcap.flows import assemble as assemble_module
from graspcap.flows import build as build_module
from graspcap.flows.build import build_dataset
from graspcap.flows.report import BuildFailed, BuildReport, Outcome, SessionReport
from graspcap.flows.workarea import WorkArea
from tests.flow_fixtures import PRESET, executions
from tests.report_html import check_page
from tests.session_factory import write_session

ODD_IDS = ("../../../../tmp/escaped-session-{u}", "a/b", "x" * 300, "new\nline", "nul\x00id",
           "..", ".hidden", "caf\u00e9", "")


def _sessions(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if (p / "session.json").exists())


def _ids(root: Path) -> list[str]:
    return [json.loads((p / "session.json").read_text())["session_id"] for p in _sessions(root)]


def _fresh_catalog_on_warm_work(warm, dest: Path) -> tuple[Path, Path]:
    """A new (empty) catalog whose work area is a copy of the warm build's: every stage of
    the synthetic sessions is a cache hit, every session is new to the catalog."""
    catalog = dest / "catalog"
    shutil.copytree(warm[0] / "work", catalog / "work")
    return catalog, catalog / "work"


# --- session ids are data, never paths ----------------------------------------------------

def test_path_name_keeps_plain_ids_and_encodes_every_other_inside_its_parent(tmp_path):
    for plain in ("p01-box-use-01", "A.b_c-9", "-x", "x" * 128):
        assert path_name(plain) == plain
    layout = CatalogLayout(tmp_path)
    odd = [s.format(u="z") for s in ODD_IDS] + ["x" * 129, "a" * 128 + "/", "\udcff"]
    names = [path_name(s) for s in odd]
    assert len(set(names)) == len(odd)  # collision-free
    for sid, name in zip(odd, names, strict=True):
        assert not PLAIN_NAME.fullmatch(name) and "~" in name, sid  # never a plain id's name
        assert len(name) <= 65 and "/" not in name and "\x00" not in name and "\n" not in name
        assert not name.startswith(".")
        folder = layout.report_dir(sid)  # a build id is data too
        assert folder.parent == tmp_path / "reports" and folder.name == name
        assert path_name(sid) == name  # deterministic
        folder.mkdir(parents=True)  # a real directory, inside the catalog
    assert sorted(p.name for p in (tmp_path / "reports").iterdir()) == sorted(names)


# --- one build, every per-session mishap ---------------------------------------------------

def test_per_session_mishaps_after_the_stages_never_lose_the_build(warm, synth_root, tmp_path,
                                                                  monkeypatch):
    """In one build: a bug in one session's rows, disk full writing another's pictures, a
    folder reusing a session id, and path-like, huge, newline and NUL ids (refused by the
    validator, each under its folder's name): one version commits the good session and a reason
    for every bad one."""
    catalog, work = _fresh_catalog_on_warm_work(warm, tmp_path / "a")
    good, buggy = _ids(synth_root)
    extra = tmp_path / "zz-extra"  # sorts after synth_root: the copy is the duplicate
    dup = extra / "copy-of-good"
    shutil.copytree(_sessions(synth_root)[0], dup)
    assert str(_sessions(synth_root)[0]) < str(dup)
    escaped = Path(f"/tmp/escaped-session-{uuid.uuid4().hex}")
    odd = [s.format(u=escaped.name.removeprefix("escaped-session-")) for s in ODD_IDS
           if s]  # "" falls back to the folder name, covered below
    for j, sid in enumerate(odd):
        write_session(extra / f"odd-{j}", session_id=sid)
    # a real session whose id is a path (refused by the validator: the build never uses it)
    climber = f"../../../../tmp/escaped-real-{uuid.uuid4().hex}"
    shutil.copytree(_sessions(synth_root)[1], extra / "climber")
    manifest = json.loads((extra / "climber" / "session.json").read_text())
    (extra / "climber" / "session.json").write_text(json.dumps({**manifest,
                                                                "session_id": climber}))

    real_rows = assemble_module.session_rows
    pictures_seen = []

    def rows_with_a_bug(results, **kw):
        if results["load_session"].session_id == buggy:
            raise RuntimeError("injected bug in the rows of one session")
        return real_rows(results, **kw)

    def disk_full(layout, session_id, pictures):
        pictures_seen.append(session_id)
        if session_id == good:
            raise OSError(errno.ENOSPC, "No space left on device",
                          str(layout.pictures_root / "ab" / "ab.png"))
        return real_write(layout, session_id, pictures)

    real_write = assemble_module._write_pictures
    monkeypatch.setattr(assemble_module, "session_rows", rows_with_a_bug)
    monkeypatch.setattr(assemble_module, "_write_pictures", disk_full)
    report = build_dataset([synth_root, extra], catalog, PRESET, build_id="mishaps")

    assert report.catalog_version == 1
    # the validator refuses every odd id (issue 15: ids are data, 1-128 of A-Za-z0-9._-):
    # those sessions fail at load_session naming the field, under their folder's name
    names = [f"odd-{j}" for j in range(len(odd))] + ["climber"]
    assert executions(catalog, "mishaps") == []  # nothing else ran: the rest is cached
    by_dir = {s.session_dir: s for s in report.sessions}
    first = by_dir[str(_sessions(synth_root)[0])]
    assert first.outcome == Outcome.ADDED and first.status in ("ok", "flagged")
    (note,) = first.notes
    assert "No space left on device" in note and str(catalog / "pictures" / "ab") in note
    assert note.startswith(f"pictures of {good} not written to ") and first.pictures == {}
    bug = by_dir[str(_sessions(synth_root)[1])]
    assert bug.outcome == Outcome.FAILED and bug.error == (
        "assembling the catalog rows: RuntimeError: injected bug in the rows of one session")
    copy = by_dir[str(dup)]
    assert copy.outcome == Outcome.FAILED and copy.session_id == good
    assert str(dup) in copy.error and str(_sessions(synth_root)[0]) in copy.error
    assert "comes first" in copy.error and not copy.kept_previous
    cat = gc.open(catalog)
    rows = {r["session_id"]: r for r in cat.table("sessions").to_pylist()}
    assert sorted(rows) == sorted([good, buggy, *names])  # one row per id
    assert rows[good]["status"] in ("ok", "flagged") and rows[good]["error"] is None
    assert rows[buggy]["status"] == "failed" and "injected bug" in rows[buggy]["error"]
    for name in names:
        report_of = by_dir[str(extra / name)]
        assert report_of.outcome == Outcome.FAILED and report_of.failed_stage == "load_session"
        assert rows[name]["status"] == "failed", name
        assert "field session_id" in rows[name]["error"], rows[name]["error"]
        assert "is not a session id" in rows[name]["error"]
    assert set(cat.table("frames")["session_id"].to_pylist()) == {good}
    assert len(cat.contactmap(good)[0]) > 0
    build = cat.table("builds").to_pylist()[0]
    assert sorted(f["session_id"] for f in build["sessions_failed"]) == sorted([buggy, *names])
    record = json.loads(build["parameters_json"])["report"]
    assert str(dup) in record["summary"]["failed"][good]  # the duplicate: in the record only
    assert not escaped.exists() and not Path("/tmp/escaped-session").exists()
    assert not Path("/tmp", climber.rsplit("/", 1)[1]).exists()
    # the sessions with pictures (written before their rows), by content inside the catalog
    assert sorted(pictures_seen) == sorted([good, buggy])
    assert sorted(bug.pictures) == ["contact.ply", "contact.png", "keypoints.png",
                                    "reprojection.png", "strip.png"]
    for rel in bug.pictures.values():
        assert (catalog / rel).is_file() and rel.startswith("pictures/")
    # the report page names every failure, the buggy session's among them
    page = check_page(Path(report.report_page))  # failed first, links resolve
    shown = [(r.session_id, r.status) for r in page.rows]
    assert sorted(shown) == sorted([(good, first.status), (good, "failed"), (buggy, "failed"),
                                    *[(n, "failed") for n in names]])  # the duplicate too
    assert "injected bug in the rows of one session" in page.row_text(buggy)
    assert "No space left on device" in page.row_text(good, first.status)
    assert "comes first" in page.row_text(good, "failed")
    # nothing under the catalog but its own folders
    assert {p.name for p in catalog.iterdir()} <= {"catalog.json", "published.json", "tables",
                                                   "arrays", "vacuum.jsonl", "reports",
                                                   "pictures", ".lock", "work"}


def test_pictures_are_stored_by_content_and_a_failed_write_is_a_note(tmp_path):
    """The write itself (``_store_pictures``): files named by their sha256 (never by the
    session id, which may be path-like), stored once; an OSError is a note naming the path."""
    import hashlib
    from types import SimpleNamespace

    layout = CatalogLayout(tmp_path / "cat")
    files = {"keypoints.png": b"k", "contact.ply": b"c"}
    pictures = SimpleNamespace(files=lambda: files)
    escaped = f"../../../../tmp/escaped-session-{uuid.uuid4().hex}"
    orig_load = assemble_module.WorkArea.load
    try:
        assemble_module.WorkArea.load = staticmethod(lambda ref: pictures)
        stored, notes = assemble_module._store_pictures(layout, escaped, None)
        assert notes == ()
        for name, data in files.items():
            digest = hashlib.sha256(data).hexdigest()
            suffix = Path(name).suffix
            assert stored[name] == f"pictures/{digest[:2]}/{digest}{suffix}"
            assert (layout.root / stored[name]).read_bytes() == data
        assert assemble_module._store_pictures(layout, "other", None) == (stored, ())  # once
        assert not Path("/tmp", escaped.rsplit("/", 1)[1]).exists()
        shutil.rmtree(tmp_path / "cat" / "pictures")
        (tmp_path / "cat" / "pictures").write_text("a file where the folder should be")
        stored, (text,) = assemble_module._store_pictures(layout, "p02", None)  # a note
        assert stored == {}
        assert text.startswith(f"pictures of p02 not written to {layout.pictures_root}")
        assert "NotADirectoryError" in text or "FileExistsError" in text
    finally:
        assemble_module.WorkArea.load = orig_load


def test_rows_the_catalog_would_refuse_fail_that_session_alone(warm, synth_root, tmp_path,
                                                               monkeypatch):
    """A session whose arrays or frames would make the commit raise gets a failed row with
    the catalog's reason; the other session is committed in the same version."""
    catalog, work = _fresh_catalog_on_warm_work(warm, tmp_path / "b")
    good, bad = _ids(synth_root)
    real_rows = assemble_module.session_rows

    def short_contact(results, **kw):
        sr = real_rows(results, **kw)
        if sr.session["session_id"] != bad:
            return sr
        arrays = type(sr.arrays)(**{**sr.arrays.__dict__, "contact": sr.arrays.contact[:-1]})
        return type(sr)(sr.session, sr.frames, arrays, sr.object_id, sr.object_mesh)

    monkeypatch.setattr(assemble_module, "session_rows", short_contact)
    report = build_dataset([synth_root], catalog, PRESET, build_id="refused")
    assert report.catalog_version == 1 and report.added == [good]
    assert report.failed[bad].startswith("the catalog refused its rows: table 'arrays/contact'")
    assert f"session '{bad}'" in report.failed[bad]
    rows = {r["session_id"]: r for r in gc.open(catalog).table("sessions").to_pylist()}
    assert rows[good]["status"] in ("ok", "flagged")
    assert rows[bad]["status"] == "failed" and rows[bad]["error"] == report.failed[bad]
    assert "does not match" in rows[bad]["error"]

    # the same refusal on an unchanged rebuild is replayed: no new version
    again = build_dataset([synth_root], catalog, PRESET, build_id="refused-again")
    assert again.catalog_version is None and again.failed == report.failed
    # fixed: the session is committed from its cached results
    monkeypatch.setattr(assemble_module, "session_rows", real_rows)
    fixed = build_dataset([synth_root], catalog, PRESET, build_id="fixed")
    assert fixed.failed == {} and fixed.changed == [bad] and fixed.catalog_version == 2


@pytest.mark.parametrize("fault", ["lock", "disk"])
def test_a_build_level_failure_keeps_the_work_and_the_next_build_commits_it(
        fault, warm, synth_root, tmp_path, monkeypatch):
    """The catalog's writer lock times out at the commit (``lock``), or the disk fills up
    writing its arrays (``disk``): nothing is committed, the build says so (BuildFailed, its
    record in builds.jsonl, ``graspcap status``), and the next build commits every session
    without running a stage again."""
    import contextlib

    from graspcap.catalog import commit as commit_module
    from graspcap.catalog.store import Catalog
    from graspcap.flows.build import last_build_failures
    from graspcap.flows.commands import status_text

    catalog, work = _fresh_catalog_on_warm_work(warm, tmp_path / "c")
    for stage in ("qa_metrics", "pictures"):  # these run in the failing build
        shutil.rmtree(work / "results" / stage)
    layout = gc.open(catalog, create=True).layout
    if fault == "lock":
        monkeypatch.setattr(Catalog, "commit", lambda self, b, gates=None: (
            commit_module.commit_build(self.layout, b, lock_timeout_s=0.3, gates=gates)))
        held = commit_module.writer_lock(layout, 5)
        expected = "CatalogLockTimeout: another writer"
    else:
        def disk_full(layout, kind, arrays, digest):
            raise OSError(errno.ENOSPC, "No space left on device",
                          str(layout.arrays_tmp / digest))

        monkeypatch.setattr(commit_module, "write_group", disk_full)
        held = contextlib.nullcontext()
        expected = "CatalogDiskFull: disk full writing " + str(layout.arrays_dir)
    with held, pytest.raises(BuildFailed) as failed:
        build_dataset([synth_root], catalog, PRESET, build_id="broken")
    text = str(failed.value)
    assert text.startswith(f"build broken committed nothing: {expected}")
    assert text.endswith(f"stay in the work area {work}; the next build commits them "
                         "without running those stages again")
    assert gc.open(catalog).latest_version() is None
    recs = [json.loads(x) for x in (work / "builds.jsonl").read_text().splitlines()]
    (broken,) = [r for r in recs if r["build_id"] == "broken"]
    assert broken["catalog_version"] is None and broken["error"] == text
    ids = _ids(synth_root)
    assert executions(catalog, "broken") == sorted(
        (s, st) for s in ids for st in ("pictures", "qa_metrics"))
    # --retry-failed after a build that committed nothing retries every session of it
    assert last_build_failures(gc.open(catalog), WorkArea(work)) == set(ids)
    status = status_text(catalog)
    assert "build broken (FAILED, nothing committed)" in status
    assert f"ERROR: build broken committed nothing: {expected}" in status

    monkeypatch.undo()
    report = build_dataset([synth_root], catalog, PRESET, build_id="after")
    assert executions(catalog, "after") == []
    assert report.catalog_version == 1 and sorted(report.added) == sorted(ids)
    assert sorted(gc.open(catalog).table("sessions")["session_id"].to_pylist()) == sorted(ids)
    assert len(gc.open(catalog).contactmap(ids[0])[0]) > 0


# --- graspcap build's exit codes -----------------------------------------------------------

def _report(*outcomes: Outcome) -> BuildReport:
    sessions = tuple(SessionReport(f"s{i}", f"/d/s{i}", o, "failed" if o == Outcome.FAILED
                                   else "ok", error="why" if o == Outcome.FAILED else None)
                     for i, o in enumerate(outcomes))
    return BuildReport("b", 1, None, sessions, {"total": 1.0}, {})


@pytest.mark.parametrize(("result", "code"), [
    (_report(Outcome.ADDED, Outcome.UNCHANGED), 0),
    (_report(Outcome.ADDED, Outcome.FAILED), 1),
    (BuildFailed("build b committed nothing: CatalogLockTimeout: another writer"), 3),
    (OSError(errno.ENOSPC, "No space left on device"), 3),
    (ZeroDivisionError("a bug"), 3),
])
def test_build_exit_codes(result, code, tmp_path, monkeypatch, capsys):
    import graspcap.flows.commands as commands
    from graspcap.cli import main

    write_session(tmp_path / "s" / "one")

    def fake_build(*args, **kwargs):
        if isinstance(result, BaseException):
            raise result
        return result

    monkeypatch.setattr(commands, "configure", lambda work: None)
    monkeypatch.setattr(build_module, "build_dataset", fake_build)
    assert main(["build", str(tmp_path / "s"), "--catalog", str(tmp_path / "cat")]) == code
    out, err = capsys.readouterr()
    if code == 3:
        assert f"the build failed, nothing committed: {result}" in err
        assert ("Traceback" in err) == isinstance(result, ZeroDivisionError)
    else:
        assert "build b: catalog version 1" in out


def test_build_usage_errors_exit_2(tmp_path, capsys):
    from graspcap.cli import main

    (tmp_path / "empty").mkdir()
    assert main(["build", str(tmp_path / "empty"), "--catalog", str(tmp_path / "cat")]) == 2
    assert "no session.json found under" in capsys.readouterr().err
    assert not (tmp_path / "cat").exists()
    with pytest.raises(SystemExit) as bad:
        main(["build", "--no-such-option", str(tmp_path)])
    assert bad.value.code == 2


def test_build_help_documents_the_exit_codes(capsys):
    from graspcap.cli import main

    with pytest.raises(SystemExit):
        main(["build", "--help"])
    out = capsys.readouterr().out
    for line in ("0  every session built", "1  some sessions failed", "2  usage error",
                 "3  the build failed as a whole"):
        assert line in out


def test_a_failed_row_the_catalog_refuses_is_left_out_and_replayed(warm, synth_root, tmp_path,
                                                                   monkeypatch):
    """A failed session whose own failed row would not validate: no row, the reason in the
    build record, the others committed; an unchanged rebuild makes no new version."""
    catalog, _ = _fresh_catalog_on_warm_work(warm, tmp_path / "d")
    tiny = write_session(tmp_path / "more" / "tiny", session_id="tiny-one")
    real_failed_row = assemble_module.failed_row

    def bad_failed_row(*args, **kwargs):
        return {**real_failed_row(*args, **kwargs), "bogus": 1}

    monkeypatch.setattr(assemble_module, "failed_row", bad_failed_row)
    report = build_dataset([synth_root, tiny.parent], catalog, PRESET, build_id="no-row")
    assert report.catalog_version == 1 and sorted(report.added) == sorted(_ids(synth_root))
    assert "no failed row written: table 'sessions', column 'bogus'" in report.failed["tiny-one"]
    cat = gc.open(catalog)
    assert sorted(cat.table("sessions")["session_id"].to_pylist()) == sorted(_ids(synth_root))
    record = json.loads(cat.table("builds").to_pylist()[0]["parameters_json"])["report"]
    assert record["summary"]["failed"] == report.failed
    again = build_dataset([synth_root, tiny.parent], catalog, PRESET, build_id="no-row-again")
    assert again.catalog_version is None and again.failed == report.failed


def test_a_failed_row_never_opens_a_fifo_manifest(tmp_path):
    import os

    from graspcap.flows.rows import failed_row

    (tmp_path / "s").mkdir()
    os.mkfifo(tmp_path / "s" / "session.json")
    row = failed_row(tmp_path / "s", "s", "why", input_digest="a" * 64, code_version="v",
                     build_id="b", config_digest="c" * 64)  # returns: never blocks on it
    assert row["participant"] == row["object_id"] == "unknown" and row["error"] == "why"


def test_a_failing_progress_callback_is_dropped_not_raised():
    from graspcap.flows.progress import Tracker, reporting_to

    calls = []

    def broken(event):
        calls.append(event)
        raise BrokenPipeError(32, "Broken pipe")

    with reporting_to(broken):
        tracker = Tracker({"a": 2})
    first = tracker.finished("a", "s1", "Completed")
    last = tracker.finished("a", "s2", "Completed")
    assert calls == [first] and last.session_done and tracker.sink is None


@pytest.mark.slow
def test_graspcap_build_exit_codes_end_to_end(tmp_path):
    """The real command in a process of its own: 1 when a session failed (its row
    committed), 3 with the reason and no traceback when the catalog cannot be opened, 2
    without sessions."""
    import os
    import subprocess
    import sys

    from tests.conftest import REPO

    write_session(tmp_path / "s" / "tiny", session_id="tiny-one")  # fails at a stage
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}

    def build(*roots: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "graspcap.cli", "build", *map(str, roots),
                               "--catalog", str(tmp_path / "cat"), "--preset", PRESET],
                              capture_output=True, text=True, env=env, cwd=REPO, timeout=600)

    failed = build(tmp_path / "s")
    assert failed.returncode == 1, failed.stderr[-3000:]
    assert "FAILED tiny-one" in failed.stdout and "catalog version 1" in failed.stdout
    # the commit cannot take the writer lock (its file is a folder): 3, the work kept
    (tmp_path / "cat" / ".lock").unlink()
    (tmp_path / "cat" / ".lock").mkdir()
    write_session(tmp_path / "s" / "tiny2", session_id="tiny-two")
    locked = build(tmp_path / "s")
    assert locked.returncode == 3, locked.stderr[-3000:]
    assert ("graspcap build: the build failed, nothing committed: build " in locked.stderr
            and "committed nothing: IsADirectoryError" in locked.stderr)
    assert "Traceback" not in locked.stderr  # Prefect's copy of it is dropped too
    (tmp_path / "cat" / ".lock").rmdir()
    (tmp_path / "cat" / "catalog.json").write_text('{"format": "other"}')
    broken = build(tmp_path / "s")
    assert broken.returncode == 3
    assert broken.stderr.strip() == (
        "graspcap build: the build failed, nothing committed: "
        f"{tmp_path / 'cat' / 'catalog.json'}: format is 'other', expected 'graspcap-catalog'")
    (tmp_path / "none").mkdir()
    assert build(tmp_path / "none").returncode == 2
