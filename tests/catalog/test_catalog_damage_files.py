"""A catalog damaged on purpose, continued (``test_catalog_damage.py`` has the logs): a full
disk, deleted or garbage Parquet files, a garbage ``catalog.json``, the command line on a
damaged catalog, and a killed writer's work-area temp files.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import graspcap.catalog as gc
import graspcap.catalog.commit as commit_mod
from graspcap.catalog.errors import CatalogDiskFull
from graspcap.flows.workarea import WorkArea
from tests.catalog_factory import (
    DAMAGE_IDS,
    assert_reads_back,
    commit_three,
    delta_logs,
    log_entry,
    make_build,
    snapshot,
)
from tests.conftest import REPO

# --- 3. disk full ------------------------------------------------------------------------------

def _enospc(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


@pytest.mark.parametrize("target", ["arrays", "sessions", "frames", "builds", "versions"])
def test_disk_full_names_the_path_and_keeps_every_version(tmp_path, monkeypatch, target):
    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    cat.commit(make_build(DAMAGE_IDS[0], seed=1, build_id="b1"))
    before = snapshot(cat, 1)
    if target == "arrays":
        monkeypatch.setattr(commit_mod, "write_group", _enospc)
    else:
        real = commit_mod.write_deltalake
        monkeypatch.setattr(commit_mod, "write_deltalake", lambda uri, *a, **k: _enospc()
                            if uri.endswith(f"/{target}") else real(uri, *a, **k))
    with pytest.raises(CatalogDiskFull) as err:
        cat.commit(make_build(DAMAGE_IDS[1], seed=2, build_id="b2"))
    path = root / target if target == "arrays" else root / "tables" / target
    assert str(err.value).startswith(f"disk full writing {path} (")
    assert err.value.errno == errno.ENOSPC and isinstance(err.value, OSError)
    monkeypatch.undo()
    fresh = gc.open(root)
    assert fresh.latest_version() == 1
    assert_reads_back(root, {1: before})
    assert fresh.commit(make_build(DAMAGE_IDS[1], seed=2, build_id="b2")) == 2  # space again
    assert_reads_back(root, {1: before})


def test_disk_full_after_the_versions_row_landed_is_no_failure(tmp_path, monkeypatch, caplog):
    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    real = commit_mod.write_deltalake

    def full_after_versions(uri, *args, **kwargs):  # e.g. its checkpoint (a post-commit hook)
        real(uri, *args, **kwargs)
        if uri.endswith("/versions"):
            _enospc()

    monkeypatch.setattr(commit_mod, "write_deltalake", full_after_versions)
    assert cat.commit(make_build(DAMAGE_IDS[0], seed=1, build_id="b1")) == 1
    assert f"version 1 is committed; disk full writing {root / 'tables' / 'versions'}" \
        in caplog.text
    monkeypatch.undo()
    assert gc.open(root).commit(make_build(DAMAGE_IDS[1], seed=2, build_id="b2")) == 2


def test_disk_full_from_deltalake_and_for_the_stamp_and_work_area(tmp_path, monkeypatch):
    from deltalake.exceptions import DeltaError

    root = tmp_path / "cat"
    cat = gc.open(root, create=True)
    real = commit_mod.write_deltalake

    def rust_enospc(uri, *args, **kwargs):
        if uri.endswith("/frames"):
            raise DeltaError("Generic error: No space left on device (os error 28)\n 0: <unknown>")
        return real(uri, *args, **kwargs)

    monkeypatch.setattr(commit_mod, "write_deltalake", rust_enospc)
    with pytest.raises(CatalogDiskFull, match=f"^disk full writing {root / 'tables' / 'frames'} "
                       r"\(Generic error: No space left on device \(os error 28\)\)"):
        cat.commit(make_build(DAMAGE_IDS[0], seed=1))
    monkeypatch.undo()

    monkeypatch.setattr(Path, "write_text", _enospc)
    with pytest.raises(CatalogDiskFull, match=f"^disk full writing {tmp_path / 'c2'}/catalog.json"):
        gc.open(tmp_path / "c2", create=True)
    monkeypatch.undo()
    assert not (tmp_path / "c2" / "catalog.json").exists()

    work = WorkArea(tmp_path / "work")
    monkeypatch.setattr(os, "fdopen", _enospc)
    with pytest.raises(CatalogDiskFull, match="^disk full writing "
                       f"{tmp_path / 'work' / 'results' / 'stage' / 'k.pkl'}"):
        work.save("stage", "k", {"a": 1}, "b1")
    monkeypatch.undo()
    assert work.lookup("stage", "k") is None
    assert not [p for p in (tmp_path / "work" / "results" / "stage").iterdir()]


# --- 4. deleted Parquet files, garbage catalog.json, and the command line ----------------------

def test_deleted_parquet_file_is_named_with_its_cause(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    [gone] = [f for f in cat.files("frames", 2) if f not in cat.files("frames", 1)]
    Path(gone).unlink()
    fresh = gc.open(root)
    with pytest.raises(gc.CatalogError) as err:
        fresh.table("frames", 2)
    assert str(err.value) == (
        f"table 'frames': file {gone} of this version is missing; version 2 was never "
        "vacuumed, so the files were deleted outside graspcap: put them back from a backup "
        "(`graspcap catalog verify` lists what every version lacks)")

    root = tmp_path / "vacuumed"
    cat = commit_three(root)
    assert cat.commit(make_build(DAMAGE_IDS[0], seed=4, build_id="b4")) == 4  # replaces v1 files
    v4 = snapshot(cat, 4)
    assert cat.vacuum(keep=1).dropped_versions == [1, 2, 3]
    [vacuumed] = cat.files("sessions", 1)
    assert not Path(vacuumed).exists()
    with pytest.raises(gc.CatalogError) as err:
        gc.open(root).table("sessions", 1)
    assert str(err.value).startswith(f"table 'sessions': file {vacuumed} of this version is "
                                     "missing; version 1 was dropped by `catalog vacuum` at ")
    assert_reads_back(root, {4: v4})


def test_garbage_parquet_and_a_missing_file_under_a_commit_are_named(tmp_path):
    root = tmp_path / "cat"
    cat = commit_three(root)
    v1 = snapshot(cat, 1)
    [bad] = [f for f in cat.files("sessions", 3) if f not in cat.files("sessions", 2)]
    saved = Path(bad).read_bytes()
    Path(bad).write_bytes(b"PAR1 not really")
    with pytest.raises(gc.CatalogError) as err:
        gc.open(root).table("sessions", 3)
    assert str(err.value).startswith(f"table 'sessions': file {bad} (")
    assert str(err.value).endswith(") of this version is not readable Parquet; put it back "
                                   "from a backup")

    Path(bad).write_bytes(saved)
    [gone] = [f for f in cat.files("frames", 3) if f not in cat.files("frames", 2)]
    Path(gone).unlink()  # the next build rewrites that session: deltalake reads the file
    logs = delta_logs(root)
    with pytest.raises(gc.CatalogError) as err:
        gc.open(root).commit(make_build(["p04-mug-use-00"], seed=9, build_id="b9"))
    message = str(err.value)
    assert message.startswith(f"writing table 'frames' ({root / 'tables' / 'frames'}) failed: ")
    assert gone in message and "<unknown>" not in message
    assert message.endswith("nothing of this build is committed and every earlier version is "
                            "intact")
    assert len(delta_logs(root)) == len(logs) + 1  # the orphaned sessions commit, no version
    assert gc.open(root).latest_version() == 3
    assert_reads_back(root, {1: v1})


@pytest.mark.parametrize("content, problem", [
    (b"\x89PNG\r\n\x1a\n\x00\x00", "is not UTF-8 text (byte 0)"),
    (b'{"format": "graspcap-catalog", "format_ver', "is not valid JSON (Unterminated string"),
    (b'["graspcap-catalog", 4]', "format is \"['graspcap-catalog', 4]\", expected"),
    (b'"graspcap-catalog"', "format is 'graspcap-catalog', expected"),
    (b'{"format": "graspcap-catalog", "format_version": true}', "format_version is 'True'"),
    (b"[" * 50_000, "is not valid JSON (maximum recursion depth exceeded"),
    (b" " * 100_000, "is 100000 bytes, not a catalog stamp"),
])
def test_garbage_catalog_json_names_the_file(tmp_path, content, problem):
    root = tmp_path / "cat"
    gc.open(root, create=True)
    (root / "catalog.json").write_bytes(content)
    with pytest.raises(gc.CatalogFormatError) as err:
        gc.open(root)
    assert str(err.value).startswith(f"{root / 'catalog.json'}: " if "format" in problem
                                     and "JSON" not in problem and "UTF" not in problem
                                     else f"{root / 'catalog.json'} ")
    assert problem in str(err.value)


_CLI_CASES = {
    "catalog.json": lambda root: (root / "catalog.json").write_bytes(b"\xff\xfe\x00"),
    "versions log gap": lambda root: log_entry(root, "versions", 2).unlink(),
    "garbage sessions entry": lambda root: log_entry(root, "sessions", 3).write_bytes(b"\x00\x01"),
    "no versions table": lambda root: shutil.rmtree(root / "tables" / "versions"),
}
_CLI_OK = {  # what still works: readers of intact versions, and migrate (nothing to do)
    "catalog.json": set(),
    "versions log gap": {"catalog|show", "catalog|show|3|--session|p04-mug-use-00",
                         "catalog|diff|1|3", "catalog|migrate"},
    "garbage sessions entry": {"catalog|migrate"},
    "no versions table": {"catalog|migrate"},
}
_CLI_NAMES = {  # the file each case's lines name
    "catalog.json": "cat/catalog.json is not UTF-8 text (byte 0)",
    "versions log gap": "table 'versions' lacks log entry 00000000000000000002.json",
    "garbage sessions entry": "cat/tables/sessions/_delta_log/00000000000000000003.json: "
                              "table 'sessions': the log entry for Delta version 3 is unreadable",
    "no versions table": "cat/tables/versions/_delta_log: table 'versions' has no Delta log "
                         "entries",
}
_COMMANDS = [["status"], ["catalog", "versions"], ["catalog", "show"],
             ["catalog", "show", "3", "--session", "p04-mug-use-00"], ["catalog", "diff", "1", "3"],
             ["catalog", "tag", "3", "t"], ["catalog", "vacuum", "--keep", "1"],
             ["catalog", "migrate"]]


@pytest.mark.parametrize("case", list(_CLI_CASES))
def test_cli_prints_one_line_per_problem_and_no_traceback(tmp_path, case):
    root = tmp_path / "cat"
    commit_three(root)
    _CLI_CASES[case](root)
    script = textwrap.dedent("""
        import sys
        from graspcap.cli import main
        code = 0
        for args in sys.argv[2:]:
            argv = args.split("|") + ["--catalog", sys.argv[1]]
            try:
                rc = main(argv)
            except SystemExit as exc:
                rc = exc.code
            print(f"@@ {args} -> {rc}", file=sys.stderr)
    """)
    proc = subprocess.run([sys.executable, "-c", script, str(root),
                           *("|".join(c) for c in _COMMANDS)], cwd=REPO, capture_output=True,
                          text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "<unknown>" not in proc.stderr, proc.stderr
    results = dict(line[3:].rsplit(" -> ", 1) for line in proc.stderr.splitlines()
                   if line.startswith("@@ "))
    assert {c for c, rc in results.items() if rc == "0"} == _CLI_OK[case], proc.stderr
    assert set(results.values()) <= {"0", "2"}
    for line in proc.stderr.splitlines():  # one line per problem, nothing else
        assert line.startswith(("@@ ", "graspcap status: ", "graspcap catalog ")), line
    assert _CLI_NAMES[case] in proc.stderr


# --- 5. the work area ----------------------------------------------------------------------

_KILLED_SAVE = textwrap.dedent("""
    import os, sys, time
    from graspcap.flows.workarea import WorkArea
    work = WorkArea(sys.argv[1])
    os.replace = lambda *a: (open(sys.argv[2], "w").close(), time.sleep(3600))
    work.save("stage", "key", list(range(1000)), "killed")
""")


def test_killed_build_temp_files_are_never_results_and_are_removed(tmp_path):
    work_root = tmp_path / "work"
    signal_file = tmp_path / "writing"
    child = subprocess.Popen([sys.executable, "-c", _KILLED_SAVE, str(work_root),
                              str(signal_file)], cwd=REPO)
    deadline = time.monotonic() + 60
    while not signal_file.exists():
        assert child.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    folder = work_root / "results" / "stage"
    [temp] = list(folder.iterdir())
    assert temp.name.startswith(f".tmp-{os.uname().nodename}-{child.pid}-")

    WorkArea._swept.discard(work_root.resolve())
    work = WorkArea(work_root)  # the first open in a process removes a dead writer's temps
    assert work.lookup("stage", "key") is None
    assert list(folder.iterdir()) == []

    live = folder / f".tmp-{os.uname().nodename}-{os.getpid()}-abc"  # a running writer's
    live.write_bytes(b"partial")
    assert work.remove_stale_temp() == [] and live.exists()
    old = folder / ".tmp-otherhost-1-abc"
    old.write_bytes(b"partial")
    os.utime(old, (time.time() - 7 * 3600,) * 2)
    assert work.remove_stale_temp() == [old]


def test_result_without_a_matching_record_is_not_trusted(tmp_path):
    work = WorkArea(tmp_path / "work")
    ref = work.save("stage", "key", [1, 2, 3], "b1")
    assert work.lookup("stage", "key") == dataclasses.replace(ref, cached=True)
    path = Path(ref.path)
    path.write_bytes(path.read_bytes() + b"\x00")  # another size than recorded: a miss
    assert work.lookup("stage", "key") is None
    work.save("stage", "key", [1, 2, 3], "b1")
    for garbage in (b"\xff", b"[]", b'{"digest": 1}', b"{" * 10000):
        path.with_suffix(".json").write_bytes(garbage)
        assert work.lookup("stage", "key") is None


def test_status_skips_a_torn_build_record_naming_the_line(tmp_path):
    from graspcap.flows.commands import status_text

    root = tmp_path / "cat"
    commit_three(root)
    record = {"build_id": "b3", "catalog_version": 3, "seconds": {"total": 2.0}, "sessions": [],
              "summary": {k: [] for k in ("added", "changed", "unchanged", "failed")}}
    (root / "work").mkdir()
    (root / "work" / "builds.jsonl").write_bytes(
        json.dumps(record).encode() + b"\n[1]\n" + b'{"build_id": "b4", "summ')
    assert status_text(root).splitlines() == [
        f"catalog {root}: latest version 3 (published); readers read it by default",
        f"note: {root / 'work' / 'builds.jsonl'}: line(s) [2, 3] are not build records (a "
        "build killed while writing one?); skipped",
        "build b3 (version 3, published): 0 added, 0 changed, 0 unchanged, 0 failed; 0 stage "
        "run(s), 0 cache hit(s), 2.0 s"]
