"""The reliability corpus through the validator: every kind gets its exact outcome, and neither
``validate_session``, the cache's file functions nor ``graspcap validate`` crash or hang.

Kinds that once hung (a FIFO, a count of 10^12, a pattern formatting to a gigabyte) run in a
subprocess with a generous timeout, so that a regression fails instead of hanging the tests.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from graspcap.flows.cached import NotARegularFile, reads_digest, session_files, session_id_of
from graspcap.flows.workarea import WorkArea
from graspcap.schemas.session import SESSION_ID_RE, SessionLimits
from graspcap.tasks.session.discover import NOT_A_SESSION, discover, discover_sessions
from graspcap.tasks.session.load_session import (
    LoadSessionConfig,
    Problem,
    SessionInvalid,
    Severity,
    load_session,
    validate_session,
)
from tests.reliability_corpus import (
    DUPLICATE_ID,
    ISSUE_ROWS,
    KINDS,
    Builds,
    Fails,
    Invalid,
    Kind,
    prepare,
)
from tests.session_factory import write_session

TIMEOUT_S = 60
"""Generous: the whole corpus validates in a few seconds; a hang is what this catches."""
LINE = re.compile(r"^  - session (?P<session>.*?): file (?P<file>.*?): field (?P<field>\S+): "
                  r"(?P<message>.*)$")

IN_PROCESS = [k for k in KINDS if not k.hangs]
INVALID = [k for k in IN_PROCESS if isinstance(k.outcome, Invalid)]
VALID = [k for k in IN_PROCESS if not isinstance(k.outcome, Invalid)]
HANGS = [k for k in KINDS if k.hangs]


def _ids(kinds: list[Kind]) -> list[str]:
    return [k.slug for k in kinds]


def _sane(problem: Problem) -> None:
    """A problem is one short line that names a printable session."""
    text = str(problem)
    assert "\n" not in text and len(text) < 600, text[:600]
    assert problem.session.isprintable() and len(problem.session) <= 130
    assert "Traceback" not in text and "RecursionError" not in text


def _cache_functions_never_raise(d: Path, work: WorkArea) -> dict | None:
    """``session_id_of`` gives a valid id or the folder name; ``session_files`` a file list or
    None; ``reads_digest`` of that list a digest or an ``OSError`` (never blocks)."""
    sid = session_id_of(d)
    assert sid == d.name or re.search(SESSION_ID_RE, sid)
    files = session_files(d)
    if files is not None:
        try:
            assert len(reads_digest(work, files, tuple(files))) == 64
        except OSError:
            return None
    return files


def test_corpus_has_every_issue_row_and_at_least_70_kinds():
    assert len(KINDS) >= 70
    assert len(ISSUE_ROWS) >= 29 and all(k.issue_row for k in ISSUE_ROWS)
    assert len(INVALID) + len([k for k in HANGS if isinstance(k.outcome, Invalid)]) >= 60
    assert {type(k.outcome) for k in ISSUE_ROWS} == {Invalid, Fails, Builds}


@pytest.mark.parametrize("kind", INVALID, ids=_ids(INVALID))
def test_invalid_kind_names_file_and_field(tmp_path, kind):
    d = prepare(tmp_path / kind.slug, kind)
    outcome = kind.outcome
    problems = validate_session(d)
    hits = [p for p in problems if p.file == outcome.file and p.field.startswith(outcome.field)
            and re.search(outcome.message, p.message) and p.severity is Severity.ERROR]
    assert hits, "\n".join(map(str, problems))
    for problem in problems:
        _sane(problem)
    with pytest.raises(SessionInvalid) as raised:
        load_session(d)
    assert outcome.file in str(raised.value)
    _cache_functions_never_raise(d, WorkArea(tmp_path / "work"))


@pytest.mark.parametrize("kind", VALID, ids=_ids(VALID))
def test_valid_kind_loads(tmp_path, kind):
    d = prepare(tmp_path / kind.slug, kind)
    outcome = kind.outcome
    problems = validate_session(d)
    errors = [p for p in problems if p.severity is Severity.ERROR]
    assert errors == [], "\n".join(map(str, problems))
    for problem in problems:
        _sane(problem)
    if isinstance(outcome, Builds) and outcome.frame_file is not None:
        assert [(p.file, p.field.startswith(outcome.frame_field)) for p in problems] == [
            (outcome.frame_file, True)], "\n".join(map(str, problems))
    else:
        assert problems == []
    assert load_session(d).session_id == json.loads((d / "session.json").read_text())[
        "session_id"]
    assert _cache_functions_never_raise(d, WorkArea(tmp_path / "work")) is not None


HANG_SCRIPT = textwrap.dedent("""
    import json, sys
    from pathlib import Path
    from graspcap.flows.workarea import WorkArea
    from graspcap.flows.cached import reads_digest, session_files, session_id_of
    from graspcap.tasks.session.load_session import SessionInvalid, load_session, validate_session

    out = {}
    for d in map(Path, sys.argv[2:]):
        problems = validate_session(d)
        try:
            load_session(d)
            loaded = "loaded"
        except SessionInvalid as exc:
            loaded = str(exc)
        files = session_files(d)
        digest = None
        if files is not None:
            try:
                digest = reads_digest(WorkArea(sys.argv[1]), files, tuple(files))
            except OSError as exc:
                digest = type(exc).__name__
        out[d.name] = {"problems": [[p.file, p.field, p.message, str(p.severity)]
                                    for p in problems],
                       "loaded": loaded, "sid": session_id_of(d), "digest": digest}
    print(json.dumps(out))
""")


def test_hang_prone_kinds_fail_in_bounded_time(tmp_path):
    dirs = [prepare(tmp_path / k.slug, k) for k in HANGS]
    assert len(dirs) >= 5
    command = [sys.executable, "-c", HANG_SCRIPT, str(tmp_path / "work"), *map(str, dirs)]
    run = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "Traceback" not in run.stderr
    results = json.loads(run.stdout)
    for kind in HANGS:
        got, outcome = results[kind.slug], kind.outcome
        assert any(f == outcome.file and field.startswith(outcome.field)
                   and re.search(outcome.message, m) and sev == "error"
                   for f, field, m, sev in got["problems"]), (kind.name, got["problems"])
        assert all(len(m) < 600 for _, _, m, _ in got["problems"])
        assert got["loaded"] != "loaded" and outcome.file in got["loaded"]
        assert got["sid"] in (kind.slug, f"kind-{kind.slug}")
        assert got["digest"] in (None, "NotARegularFile"), kind.name


def _blocks(output: str) -> dict[str, tuple[str, list[dict]]]:
    """``graspcap validate`` output by folder name: (OK/FAIL/SKIP, problem lines parsed)."""
    blocks: dict[str, tuple[str, list[dict]]] = {}
    current = None
    for line in output.splitlines():
        head = re.match(r"^(OK  |FAIL|SKIP) (\S+?)(:| |$)", line)
        if head:
            current = Path(head[2]).name
            blocks[current] = (head[1].strip(), [])
            continue
        if line.startswith("  - "):
            match = LINE.match(line)
            assert match, line
            blocks[current][1].append(match.groupdict())
    return blocks


def _validate_cli(*dirs: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "graspcap.cli", "validate", *map(str, dirs)],
                          capture_output=True, text=True, timeout=TIMEOUT_S)


def test_graspcap_validate_on_the_whole_corpus(tmp_path):
    root = tmp_path / "corpus"
    write_session(root / "good-0", session_id=DUPLICATE_ID)
    write_session(root / "good-1", session_id="good-session-1")
    for kind in KINDS:
        prepare(root / kind.slug, kind)
    run = _validate_cli(root)
    output = run.stdout + run.stderr
    assert "Traceback" not in output and "Error:" not in output
    assert run.returncode == 1, output[-3000:]
    blocks = _blocks(run.stdout)
    assert blocks["good-0"] == ("OK", []) and blocks["good-1"] == ("OK", [])
    skipped = failed = 0
    for kind in KINDS:
        status, lines = blocks[kind.slug]
        manifest = root / kind.slug / "session.json"
        if not manifest.exists() or manifest.is_dir():  # os.walk sees no session.json file
            assert status == "SKIP", kind.name
            assert f"SKIP {root / kind.slug}: {NOT_A_SESSION}" in run.stdout
            skipped += 1
        elif isinstance(kind.outcome, Invalid):
            outcome = kind.outcome
            assert status == "FAIL", (kind.name, status)
            assert any(p["file"] == outcome.file and p["field"].startswith(outcome.field)
                       and re.search(outcome.message, p["message"]) for p in lines), (
                kind.name, lines)
            failed += 1
        else:
            assert status == "OK", (kind.name, lines)
    # a folder a kind moved beside the sessions ("symlinked folder leading out"): not a session
    slugs = {k.slug for k in KINDS} | {"good-0", "good-1"}
    assert [(name, status) for name, (status, _) in blocks.items() if name not in slugs] == [
        ("elsewhere", "SKIP")]
    skipped += 1
    ok = len(KINDS) + 2 - skipped - failed + 1
    assert run.stdout.splitlines()[-1] == f"{ok} ok, {failed} failed, {skipped} not a session"
    assert len(run.stdout) < 200_000  # no gigabyte file name, no repeated frame lists


def test_graspcap_validate_exits_zero_when_every_session_is_valid(tmp_path):
    root = tmp_path / "valid"
    for kind in VALID:
        prepare(root / kind.slug, kind)
    write_session(root / "group" / "inner", session_id="inner-1")  # a parent of sessions
    (root / "forgotten" / "grasp").mkdir(parents=True)  # no session.json among sessions
    (root / ".cache").mkdir()
    run = _validate_cli(root)
    assert run.returncode == 0, run.stdout[-3000:]
    assert "Traceback" not in run.stdout + run.stderr
    skips = [line for line in run.stdout.splitlines() if line.startswith("SKIP")]
    assert skips == [f"SKIP {root / 'forgotten'}: {NOT_A_SESSION}"]
    assert run.stdout.splitlines()[-1] == f"{len(VALID) + 1} ok, 0 failed, 1 not a session"


def test_discover_reports_folders_that_are_not_sessions(tmp_path):
    root = tmp_path / "root"
    for name in ("b", "a", "group/c", "group/d"):
        write_session(root / name, frames=1, views=1)
    (root / "forgot" / "deeper").mkdir(parents=True)  # reported once, not its inside
    (root / "group" / "e" / "frames").mkdir(parents=True)
    (root / ".git" / "objects").mkdir(parents=True)
    (root / "notes.txt").write_text("not a folder")
    (tmp_path / "lonely").mkdir()
    found = discover([root, root / "a", tmp_path / "lonely", tmp_path / "absent"])
    assert found.sessions == [root / "a", root / "b", root / "group/c", root / "group/d"]
    assert found.not_sessions == [root / "forgot", root / "group/e"]
    assert discover_sessions([root]) == found.sessions  # the old signature, unchanged
    assert discover([tmp_path / "lonely"]).not_sessions == []  # no sessions beside it


def test_limits_are_config_values(tmp_path):
    d = write_session(tmp_path / "s")
    assert validate_session(d) == []
    tight = SessionLimits(max_frames=3, max_mesh_faces=10, max_image_pixels=4000)
    problems = {(p.file, p.field): p.message for p in validate_session(d, limits=tight)}
    assert "SessionLimits.max_frames" in problems[("session.json", "grasp.count")]
    assert "max_mesh_faces" in problems[("object.ply", "object_mesh")]
    assert "max_image_pixels" in problems[("session.json", "color_camera.height")]
    assert LoadSessionConfig().limits == SessionLimits()
    assert LoadSessionConfig(limits=tight).digest() != LoadSessionConfig().digest()
    for name, field in SessionLimits.model_fields.items():
        assert field.description, f"SessionLimits.{name} has no docstring"
    with pytest.raises(ValueError):
        SessionLimits(max_frames=0)


def test_reads_digest_refuses_a_directory_without_opening_it(tmp_path):
    d = write_session(tmp_path / "s")
    files = session_files(d)
    (d / "object.ply").unlink()
    (d / "object.ply").mkdir()
    with pytest.raises(NotARegularFile):
        reads_digest(WorkArea(tmp_path / "work"), files, ("object_mesh",))


def test_many_unreadable_frames_are_capped(tmp_path):
    d = write_session(tmp_path / "s", frames=30)
    for i in range(25):  # directories where 25 depth frames should be
        (d / f"grasp/depth/{i:06d}.png").unlink()
        (d / f"grasp/depth/{i:06d}.png").mkdir()
    problems = [p for p in validate_session(d) if p.field == "grasp.depth"]
    assert [p.file for p in problems[:20]] == [f"grasp/depth/{i:06d}.png" for i in range(20)]
    assert {p.message for p in problems[:20]} == {"is a directory, not a file"}
    assert [(p.file, p.message) for p in problems[20:]] == [
        ("grasp/depth/{index:06d}.png",
         "5 more frames are not readable files (the first: is a directory, not a file)")]
