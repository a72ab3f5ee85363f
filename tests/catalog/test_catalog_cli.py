"""`graspcap catalog ...` on a small real catalog: each subcommand against the Python API."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest

import graspcap.catalog as gc
from graspcap.cli import main
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION
from tests.catalog_factory import make_build
from tests.golden.make_golden import GOLDEN_FORMATS, SESSION, archive, expected, unpack

IDS_1 = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-handoff-00"]
FAILED = "p03-bowl-handoff-00"


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli") / "cat"
    cat = gc.open(root, create=True)
    cat.commit(make_build(IDS_1, seed=1, build_id="b1", failed=(FAILED,)))
    cat.commit(make_build(["p01-mug-use-00", "p04-mug-use-00"], seed=2, build_id="b2"))
    return cat


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main(["catalog", *argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_versions_and_show(catalog, capsys):
    root = str(catalog.layout.root)
    code, out, _ = run(capsys, "versions", "--catalog", root, "--json")
    rows = json.loads(out)
    assert code == 0 and [r["version"] for r in rows] == [1, 2]
    assert [r["build_id"] for r in rows] == ["b1", "b2"] and rows[1]["rows_sessions"] == 4
    code, out, _ = run(capsys, "versions", "--catalog", root)
    assert code == 0 and re.search(r"^\s+2\s.*b2\s+published\s+4\s+9.*<- readers' default$",
                                   out, re.M), out

    code, out, _ = run(capsys, "show", "1", "--catalog", root, "--json")
    s = json.loads(out)
    sessions = catalog.table("sessions", 1)
    assert s["rows"] == {"sessions": 3, "frames": 6, "builds": 1}
    assert s["status"] == {"ok": 2, "failed": 1}
    assert s["build"]["sessions_added"] == 3 and s["build"]["sessions_failed"] == 1
    want = np.median(sessions["qa_crosscheck_mm"].drop_null().to_numpy())
    assert s["qa_median"]["qa_crosscheck_mm"] == pytest.approx(want, rel=1e-12)
    assert "qa_flags" not in s["qa_median"] and "qa_notes" not in s["qa_median"]
    assert s["sessions_with"] == {"qa_flags": 0, "qa_notes": 1}  # the mug's (factory) note
    code, out, _ = run(capsys, "show", "--catalog", root)  # latest, as text
    assert code == 0 and out.startswith("version 2  build b2")
    assert re.search(r"status: .*ok 3", out) and "qa_contact_coverage" in out
    assert "QA:     0 session(s) with flag reasons, 2 with notes" in out

    # a session's flag reasons and notes, one a line, next to its status
    code, out, _ = run(capsys, "show", "--session", "p04-mug-use-00", "--catalog", root)
    lines = out.splitlines()
    at = {line.split()[0]: i for i, line in enumerate(lines[1:], 1)}
    assert code == 0 and at["status"] < at["qa_flags"] < at["qa_notes"] < at["steady_from"]
    assert lines[at["qa_flags"]].split() == ["qa_flags", "-"]
    assert lines[at["qa_notes"]].split(None, 1) == [
        "qa_notes", "estimate_adjustment: ambiguous (the pose nearest stage 1 kept)"]
    code, out, _ = run(capsys, "show", "--session", "p04-mug-use-00", "--catalog", root,
                       "--json")
    row = json.loads(out)
    assert row["qa_flags"] == [] and row["qa_notes"] == [
        "estimate_adjustment: ambiguous (the pose nearest stage 1 kept)"]
    code, out, _ = run(capsys, "show", "1", "--session", FAILED, "--catalog", root)
    assert re.search(r"^  qa_flags\s+null$", out, re.M) and re.search(r"^  qa_notes\s+null$",
                                                                        out, re.M), out

    code, out, _ = run(capsys, "show", "1", "--session", FAILED, "--catalog", root, "--json")
    row = json.loads(out)
    assert row["status"] == "failed" and "platter" in row["error"] and row["T_adj"] is None
    code, out, err = run(capsys, "show", "1", "--session", "nobody", "--catalog", root)
    assert code == 2 and "not in catalog version 1" in err


def test_diff_and_tag(catalog, capsys):
    root = str(catalog.layout.root)
    code, out, _ = run(capsys, "diff", "1", "2", "--catalog", root, "--json")
    assert code == 0 and json.loads(out) == catalog.diff(1, 2)
    code, out, _ = run(capsys, "diff", "1", "2", "--catalog", root)
    assert "added (1): p04-mug-use-00" in out and "p01-mug-use-00: " in out
    code, out, _ = run(capsys, "tag", "1", "first", "--catalog", root)
    assert code == 0 and gc.open(root).resolve("first") == 1
    code, out, err = run(capsys, "tag", "1", "9bad", "--catalog", root)
    assert code == 2 and "use a letter" in err
    code, out, err = run(capsys, "show", "7", "--catalog", root)
    assert code == 2 and "no version 7" in err
    code, out, err = run(capsys, "show", "nope", "--catalog", root)
    assert code == 2 and "no tag 'nope'" in err


def _by_digest(table: pa.Table) -> dict[str, dict]:
    return {r["digest"]: r for r in table.to_pylist()}


def test_export_parquet_reads_with_pyarrow_alone(catalog, capsys, tmp_path):
    code, out, _ = run(capsys, "export", "2", "--out", str(tmp_path / "x"),
                       "--catalog", str(catalog.layout.root))
    assert code == 0 and "exported version 2" in out
    manifest = json.loads((tmp_path / "x" / "manifest.json").read_text())
    assert manifest["version"] == 2 and manifest["rows"]["frames"] == 9
    for name in ("sessions", "frames", "builds"):
        assert pq.read_table(tmp_path / "x" / f"{name}.parquet").equals(
            catalog.table(name, 2)), name
    sessions = pq.read_table(tmp_path / "x" / "sessions.parquet").to_pylist()
    contact = _by_digest(pq.read_table(tmp_path / "x" / "contact.parquet"))
    hands = _by_digest(pq.read_table(tmp_path / "x" / "hand_mesh.parquet"))
    objects = _by_digest(pq.read_table(tmp_path / "x" / "object_mesh.parquet"))
    for row in sessions:
        if row["status"] == "failed":
            continue
        values, observed = catalog.contactmap(row["session_id"], 2)
        got = contact[row["contact_digest"]]
        np.testing.assert_array_equal(np.array(got["values"], np.float32), values)
        np.testing.assert_array_equal(np.array(got["observed"]), observed)
        verts, faces = catalog.hand_mesh(row["session_id"], 2)
        np.testing.assert_array_equal(np.array(hands[row["hand_mesh_digest"]]["vertices"],
                                               np.float32), verts)
        np.testing.assert_array_equal(np.array(hands[row["hand_mesh_digest"]]["faces"]), faces)
        over, _ = catalog.object_mesh(row["object_id"], 2)
        np.testing.assert_array_equal(np.array(objects[row["object_mesh_digest"]]["vertices"],
                                               np.float32), over)
    code, _, err = run(capsys, "export", "2", "--out", str(tmp_path / "x"),
                       "--catalog", str(catalog.layout.root))
    assert code == 2 and "exists" in err


def test_export_csv_keeps_lists_as_json(catalog, capsys, tmp_path):
    code, _, _ = run(capsys, "export", "1", "--out", str(tmp_path / "c"), "--format", "csv",
                     "--catalog", str(catalog.layout.root))
    assert code == 0
    frames = pacsv.read_csv(tmp_path / "c" / "frames.csv").to_pylist()
    want = catalog.table("frames", 1).to_pylist()
    assert len(frames) == len(want) == 6
    for got, row in zip(frames, want, strict=True):
        assert got["session_id"] == row["session_id"] and got["frame"] == row["frame"]
        np.testing.assert_array_equal(json.loads(got["T_c_o"]), row["T_c_o"])  # exact repr
    contact = pacsv.read_csv(tmp_path / "c" / "contact.csv").to_pylist()
    assert len(contact) == 2 and len(json.loads(contact[0]["values"])) > 0


def test_vacuum(tmp_path, capsys):
    cat = gc.open(tmp_path / "v", create=True)
    cat.commit(make_build(["p01-mug-use-00"], seed=1, build_id="b1"))
    cat.commit(make_build(["p01-mug-use-00"], seed=2, build_id="b2"))
    code, out, _ = run(capsys, "vacuum", "--keep", "1", "--catalog", str(cat.layout.root))
    assert code == 0 and out.startswith("kept version(s) 2 (the newest 1, every tagged one "
                                        "and the published one); version(s) 1 can no longer "
                                        "be read"), out
    with pytest.raises(gc.CatalogError, match="vacuum"):
        gc.open(cat.layout.root).table("frames", 1)
    code, _, err = run(capsys, "vacuum", "--keep", "0", "--catalog", str(cat.layout.root))
    assert code == 2 and "keep must be >= 1" in err
    code, _, err = run(capsys, "export", "1", "--out", str(tmp_path / "e"),
                       "--catalog", str(cat.layout.root))
    assert code == 2 and "vacuum" in err
    assert not (tmp_path / "e").exists() and not (tmp_path / "e.partial").exists()


@pytest.mark.parametrize("fmt", GOLDEN_FORMATS)
def test_the_command_the_format_error_names_migrates(tmp_path, fmt):
    src = unpack(archive(fmt), tmp_path / "old")
    with pytest.raises(gc.CatalogFormatError) as info:
        gc.open(src)
    command = re.search(r"`(graspcap catalog migrate [^`]+)`", str(info.value)).group(1)
    argv = [sys.executable, "-m", "graspcap.cli", *shlex.split(command)[1:]]
    done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"from format {fmt} to {CATALOG_FORMAT_VERSION}" in done.stdout
    values, observed = gc.open(src).contactmap(SESSION, "golden")
    np.testing.assert_array_equal(values, expected()["contact"])
    np.testing.assert_array_equal(observed, expected()["observed"])
