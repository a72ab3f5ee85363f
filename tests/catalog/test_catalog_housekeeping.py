"""`graspcap catalog remove | tag --force | vacuum | versions` on small real catalogs."""

from __future__ import annotations

import json
import re

import pyarrow.compute as pc
import pytest

import graspcap.catalog as gc
from graspcap.cli import main
from tests.catalog_factory import make_build

IDS = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-use-00"]


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main(["catalog", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture
def catalog(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(make_build(IDS, seed=1, build_id="b1"))
    cat.commit(make_build(["p04-mug-use-00"], seed=2, build_id="b2"))
    return cat


def test_remove_makes_a_version_without_the_sessions_and_records_why(catalog, capsys):
    root = str(catalog.layout.root)
    code, out, err = run(capsys, "remove", "p01-mug-use-00", "p03-bowl-use-00", "--reason",
                         "wrong object label", "--catalog", root)
    assert (code, err) == (0, "")
    assert out == ("removed 2 session(s) (p01-mug-use-00, p03-bowl-use-00) in new version 3; "
                   "reason: wrong object label; versions before 3 still hold them\n")
    cat = gc.open(root)
    assert cat.latest_version() == 3
    kept = ["p02-drill-use-00", "p04-mug-use-00"]
    assert sorted(cat.table("sessions", 3)["session_id"].to_pylist()) == kept
    assert sorted(set(cat.table("frames", 3)["session_id"].to_pylist())) == kept
    # time travel: version 2 still has them, rows and frames unchanged
    assert cat.table("sessions", 2).equals(catalog.table("sessions", 2))
    assert sorted(set(cat.table("frames", 2)["session_id"].to_pylist())) == sorted(
        [*IDS, "p04-mug-use-00"])
    builds = cat.table("builds", 3)
    row = builds.filter(pc.equal(builds["catalog_version"], 3)).to_pylist()[0]
    assert row["sessions_removed"] == ["p01-mug-use-00", "p03-bowl-use-00"]
    assert row["sessions_added"] == row["sessions_changed"] == row["sessions_failed"] == []
    assert json.loads(row["parameters_json"]) == {
        "command": "catalog remove", "reason": "wrong object label",
        "removed": ["p01-mug-use-00", "p03-bowl-use-00"], "previous_version": 2}
    assert row["build_id"].startswith("rm-") and row["config_digest"] == "c" * 64
    assert main(["status", "--catalog", root]) == 0
    assert capsys.readouterr().out.splitlines()[:2] == [
        f"catalog {root}: no builds yet",  # (the factory's versions record no build report)
        f"version 3 ({row['build_id']}): catalog remove of p01-mug-use-00, p03-bowl-use-00; "
        "reason: wrong object label"]


def test_remove_of_an_unknown_session_commits_nothing(catalog, capsys):
    code, out, err = run(capsys, "remove", "p01-mug-use-00", "p09-dril-use-00",
                         "--catalog", str(catalog.layout.root))
    assert code == 2 and out == ""
    assert err == ("graspcap catalog remove: session(s) ['p09-dril-use-00'] not in catalog "
                   "version 2 (its sessions: ['p01-mug-use-00', 'p02-drill-use-00', "
                   "'p03-bowl-use-00', 'p04-mug-use-00'])\n")
    assert gc.open(catalog.layout.root).latest_version() == 2


def test_tag_moves_only_with_force(catalog, capsys):
    root = str(catalog.layout.root)
    assert run(capsys, "tag", "1", "paper", "--catalog", root) == (
        0, "tag paper -> version 1\n", "")
    code, out, err = run(capsys, "tag", "2", "paper", "--catalog", root)
    assert (code, out) == (2, "")
    assert err == ("graspcap catalog tag: tag 'paper' already points at version 1; to move it "
                   "to version 2, pass --force (Catalog.tag(..., force=True))\n")
    assert gc.open(root).tags() == {"paper": 1}
    assert run(capsys, "tag", "1", "paper", "--catalog", root) == (
        0, "tag paper -> version 1 (already)\n", "")
    assert run(capsys, "tag", "2", "paper", "--force", "--catalog", root) == (
        0, "tag paper -> version 2 (moved from version 1)\n", "")
    assert gc.open(root).tags() == {"paper": 2}


def test_vacuum_says_exactly_what_it_removed_and_versions_marks_what_no_longer_reads(
        tmp_path, capsys):
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(make_build(["p01-mug-use-00"], seed=1, build_id="b1"))
    cat.commit(make_build(["p01-mug-use-00"], seed=2, build_id="b2"))  # rewrites its rows
    cat.commit(make_build(["p02-drill-use-00"], seed=3, build_id="b3"))  # only adds files
    root = str(cat.layout.root)
    code, out, err = run(capsys, "vacuum", "--keep", "1", "--catalog", root)
    assert (code, err) == (0, "")
    # version 1's rows and arrays were replaced in version 2; version 2's files are all
    # version 3's too: it still reads
    assert re.fullmatch(
        r"kept version\(s\) 3 \(the newest 1, every tagged one and the published one\); "
        r"version\(s\) 1 can no "
        r"longer be read \(files they need were removed; they stay listed\); version\(s\) 2 "
        r"not kept but still readable \(they share every file with kept ones\); removed 2 "
        r"table file\(s\) \(sessions 1, frames 1\), 2 array group\(s\): \d+\.\d\d MB freed\n",
        out), out
    fresh = gc.open(root)
    assert fresh.table("frames", 2).num_rows == 3  # still reads
    with pytest.raises(gc.CatalogError, match="dropped by `catalog vacuum`"):
        fresh.table("frames", 1)

    code, out, _ = run(capsys, "versions", "--catalog", root)
    lines = out.splitlines()
    assert code == 0 and len(lines) == 4
    assert re.search(r"\[vacuumed \S+: can no longer be read\]$", lines[1]), lines[1]
    assert "vacuumed" not in lines[2] and "vacuumed" not in lines[3]
    code, out, _ = run(capsys, "versions", "--catalog", root, "--json")
    assert [(r["version"], r["readable"]) for r in json.loads(out)] == [
        (1, False), (2, True), (3, True)]

    code, out, err = run(capsys, "vacuum", "--catalog", root)
    assert (code, out) == (2, "")
    assert err.startswith("graspcap catalog vacuum: say what to delete: --keep N")
