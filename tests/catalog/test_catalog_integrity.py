"""Object meshes per session (content-addressed), and a catalog that never reads wrong: damaged
on purpose (a chunk deleted or altered, a Parquet file deleted), reads fail naming the array,
``export`` fails naming it and its sessions, ``graspcap catalog verify`` lists each."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
from pathlib import Path, PurePosixPath

import numpy as np
import pytest

import graspcap.catalog as gc
from graspcap.catalog.arrays import DamagedArrayError, remove_temp_groups, verify_group
from graspcap.catalog.export import export_version
from graspcap.catalog.layout import CatalogLayout
from graspcap.catalog.migrate import migrate_catalog
from graspcap.catalog.verify import verify_version
from graspcap.cli import main
from tests.catalog_factory import make_build
from tests.golden.make_golden import SESSION, archive, expected, unpack

A, B, C = "p01-mug-use-00", "p02-mug-use-00", "p03-mug-handoff-00"


def _mesh(n: int, seed: int) -> gc.ObjectMesh:
    rng = np.random.default_rng(seed)
    return gc.ObjectMesh(rng.normal(size=(n, 3)).astype(np.float32) * 0.05,
                         rng.integers(0, n, size=(2 * n, 3)).astype(np.int32))


def _two_mugs() -> gc.BuildCommit:
    """Three mug sessions: A and C with one 40-vertex mesh, B with its own of 55 vertices."""
    build = make_build([A, B, C], seed=3)
    small, large = _mesh(40, 1), _mesh(55, 2)
    rng = np.random.default_rng(9)
    arrays = dict(build.session_arrays)
    arrays[B] = dataclasses.replace(arrays[B], contact=rng.uniform(0, 1, 55).astype(np.float32),
                                    observed=rng.uniform(size=55) > 0.3)
    return dataclasses.replace(build, session_arrays=arrays,
                               object_meshes={A: small, B: large, "mug": small})


def test_sessions_of_one_object_id_keep_their_own_meshes(tmp_path, capsys):
    cat = gc.open(tmp_path / "cat", create=True)
    build = _two_mugs()
    assert cat.commit(build) == 1
    rows = {r["session_id"]: r for r in cat.table("sessions", 1).to_pylist()}
    assert rows[A]["object_mesh_digest"] == rows[C]["object_mesh_digest"]  # C: the "mug" key
    assert rows[A]["object_mesh_digest"] != rows[B]["object_mesh_digest"]
    for sid, mesh in ((A, build.object_meshes[A]), (B, build.object_meshes[B]),
                      (C, build.object_meshes[A])):
        verts, faces = cat.object_mesh(session_id=sid, version=1)
        np.testing.assert_array_equal(verts, mesh.vertices)
        np.testing.assert_array_equal(faces, mesh.faces)
        values, observed = cat.contactmap(sid, 1)
        np.testing.assert_array_equal(values, build.session_arrays[sid].contact)
        assert len(values) == len(observed) == len(verts)
    assert cat.object_meshes("mug", 1) == {rows[A]["object_mesh_digest"]: [A, C],
                                           rows[B]["object_mesh_digest"]: [B]}
    with pytest.raises(gc.CatalogError, match=rf"object 'mug' has 2 different meshes .*"
                       rf"{A}, {C}.*{B}.*object_mesh\(session_id=\.\.\.\)"):
        cat.object_mesh("mug", 1)
    with pytest.raises(KeyError, match="of object 'mug', not 'bowl'"):
        cat.object_mesh("bowl", 1, session_id=A)

    code = main(["catalog", "show", "--catalog", str(cat.layout.root)])
    out = capsys.readouterr().out
    d_a, d_b = sorted([rows[A]["object_mesh_digest"], rows[B]["object_mesh_digest"]])
    users = {rows[A]["object_mesh_digest"]: f"{A}, {C}", rows[B]["object_mesh_digest"]: B}
    assert code == 0 and (f"meshes: object 'mug' has 2 different meshes (each session keeps its "
                          f"own): {d_a[:12]}: {users[d_a]}; {d_b[:12]}: {users[d_b]}") in out

    ds = gc.GraspDataset(cat, unit="sessions")
    items = {ds[i]["session_id"]: ds[i] for i in range(len(ds))}
    assert {s: len(it["object_vertices"]) for s, it in items.items()} == {A: 40, B: 55, C: 40}
    for sid, item in items.items():
        assert len(item["contact"]) == len(item["object_vertices"])
        np.testing.assert_array_equal(item["contact"], build.session_arrays[sid].contact)

    # the contact map is checked against the session's own mesh, naming it
    bad = dataclasses.replace(build, object_meshes={A: build.object_meshes[A],
                                                     B: build.object_meshes[A], "mug": None})
    with pytest.raises(gc.CatalogSchemaError, match=rf"session '{B}'.*55 contact values for "
                       r"the session's object mesh of 40 vertices \(object 'mug'\)"):
        cat.commit(bad)


def test_one_mesh_per_object_still_reads_by_object_id(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    build = make_build(["p01-bowl-use-00", "p02-bowl-use-00"], seed=2)
    cat.commit(build)
    verts, _ = cat.object_mesh("bowl")
    np.testing.assert_array_equal(verts, build.object_meshes["bowl"].vertices)
    with pytest.raises(KeyError, match="object 'cup' has no mesh"):
        cat.object_mesh("cup")


@pytest.fixture()
def damaged(tmp_path):
    """A committed catalog (two sessions, one with an all-zero contact map) and its rows."""
    cat = gc.open(tmp_path / "cat", create=True)
    build = make_build(["p01-bowl-use-00", "p02-drill-use-00"], seed=5)
    arrays = dict(build.session_arrays)
    zero = arrays["p01-bowl-use-00"]
    arrays["p01-bowl-use-00"] = dataclasses.replace(
        zero, contact=np.zeros_like(zero.contact), observed=np.zeros_like(zero.observed))
    cat.commit(dataclasses.replace(build, session_arrays=arrays))
    rows = {r["session_id"]: r for r in cat.table("sessions", 1).to_pylist()}
    assert verify_version(cat).ok
    return cat, rows


def _verify_cli(cat) -> tuple[int, str]:
    import io
    from contextlib import redirect_stdout

    out = io.StringIO()
    with redirect_stdout(out):
        code = main(["catalog", "verify", "--catalog", str(cat.layout.root)])
    return code, out.getvalue()


def test_missing_chunk_fails_reads_export_and_verify(damaged, tmp_path):
    cat, rows = damaged
    sid = "p02-drill-use-00"
    digest = rows[sid]["hand_mesh_digest"]
    (cat.layout.array_group(digest) / "vertices" / "c" / "0" / "0").unlink()
    with pytest.raises(DamagedArrayError, match=rf"{digest}: file vertices/c/0/0 of array "
                       "'vertices' is missing"):
        cat.hand_mesh(sid)
    np.testing.assert_array_equal(cat.hand_joints(sid).shape, (21, 3))  # joints are intact
    # the object-store read path (fsspec; run on a file:// store) checks the same
    remote = gc.Catalog(CatalogLayout(PurePosixPath(cat.layout.root),
                                      url=cat.layout.root.as_uri()))
    with pytest.raises(DamagedArrayError, match=rf"{digest}: file vertices/c/0/0 of array "
                       "'vertices' is missing"):
        remote.hand_mesh(sid)
    assert [d.name for d in verify_version(remote).damaged] == [digest]
    with pytest.raises(DamagedArrayError, match=rf"session '{sid}' \(catalog version 1\): "
                       rf"array group {digest}: file vertices/c/0/0"):
        gc.GraspDataset(cat, objects=["drill"])[0]
    with pytest.raises(DamagedArrayError, match=rf"cannot export hand_mesh of session\(s\) "
                       rf"{sid}: array group {digest}: file vertices/c/0/0"):
        export_version(cat, None, tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()

    # an all-zero contact map's chunk exists too: deleting it is damage, not zeros
    zero = rows["p01-bowl-use-00"]["contact_digest"]
    (cat.layout.array_group(zero) / "values" / "c" / "0").unlink()
    with pytest.raises(DamagedArrayError, match="values/c/0 of array 'values' is missing"):
        cat.contactmap("p01-bowl-use-00")

    report = verify_version(cat)
    assert not report.ok and report.arrays == 6
    assert [(d.kind, d.name, d.group_kind, d.sessions) for d in report.damaged] == sorted(
        [("array", digest, "hand_mesh", (sid,)),
         ("array", zero, "contact", ("p01-bowl-use-00",))], key=lambda t: t[1])
    problems = {d.name: d.problem for d in report.damaged}
    assert problems[digest] == "file vertices/c/0/0 of array 'vertices' is missing"
    code, out = _verify_cli(cat)
    assert code == 1
    assert (f"array hand_mesh {digest}: file vertices/c/0/0 of array 'vertices' is missing "
            f"(referenced by session(s) {sid})") in out
    assert "version 1: 3 table file(s) and 6 array group(s) checked, 2 damaged:" in out


def test_altered_chunk_fails_reads_and_verify(damaged):
    cat, rows = damaged
    sid = "p01-bowl-use-00"
    digest = rows[sid]["object_mesh_digest"]
    chunk = cat.layout.array_group(digest) / "vertices" / "c" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[-1] ^= 0xFF
    chunk.write_bytes(bytes(data))
    with pytest.raises(DamagedArrayError, match=rf"{digest}: file vertices/c/0/0 of array "
                       r"'vertices' does not match the group's manifest"):
        cat.object_mesh(session_id=sid)
    report = verify_version(cat)
    assert {(d.name, d.sessions) for d in report.damaged} == {(digest, (sid,))}
    assert report.damaged[0].problem == ("file vertices/c/0/0 of array 'vertices' was altered "
                                         "(its sha256 differs from the manifest)")


def test_altered_metadata_is_caught_by_verify_only(damaged):
    """The root zarr.json is not in the manifest: verify compares the content with the
    digest; the normal read path does not (docs/catalog.md, Integrity)."""
    cat, rows = damaged
    digest = rows["p02-drill-use-00"]["contact_digest"]
    path = cat.layout.array_group(digest) / "zarr.json"
    meta = json.loads(path.read_text())
    meta["attributes"]["chunks"] = {}  # the manifest gone: reads check nothing
    meta["consolidated_metadata"]["metadata"]["values"]["fill_value"] = 0.5
    (cat.layout.array_group(digest) / "values" / "c" / "0").unlink()
    path.write_text(json.dumps(meta))
    values, _ = cat.contactmap("p02-drill-use-00")
    assert (values == 0.5).all()  # read wrong, silently: only verify can tell
    assert verify_group(cat.layout, digest) == [
        "its content does not match its digest (an altered or missing chunk, or altered "
        "metadata)"]


def test_missing_group_metadata_and_a_group_of_the_wrong_kind(damaged):
    cat, rows = damaged
    sid = "p02-drill-use-00"
    digest = rows[sid]["hand_mesh_digest"]
    (cat.layout.array_group(digest) / "zarr.json").unlink()
    with pytest.raises(DamagedArrayError, match=rf"{digest}: its zarr.json is missing"):
        cat.hand_joints(sid)
    shutil.rmtree(cat.layout.array_group(rows[sid]["contact_digest"]))
    with pytest.raises(DamagedArrayError, match="is missing from .* removed by vacuum or the "
                       "catalog is damaged"):
        cat.contactmap(sid)
    # another group's files under this digest (a botched restore from a backup)
    other = rows["p01-bowl-use-00"]["object_mesh_digest"]
    shutil.copytree(cat.layout.array_group(rows["p01-bowl-use-00"]["contact_digest"]),
                    cat.layout.array_group(rows[sid]["contact_digest"]))
    problems = {(d.name, d.problem) for d in verify_version(cat).damaged}
    assert problems == {
        (digest, f"its zarr.json is missing ({cat.layout.array_group(digest)}/zarr.json)"),
        (rows[sid]["contact_digest"], "its content does not match its digest (an altered or "
                                      "missing chunk, or altered metadata)")}
    assert verify_group(cat.layout, other, "contact") == [
        "it holds a 'object_mesh' group where a 'contact' one is referenced"]


def test_deleted_parquet_file_is_named_by_verify(damaged):
    cat, _ = damaged
    frames = Path(cat.files("frames")[0])
    frames.unlink()
    code, out = _verify_cli(cat)
    assert code == 1 and f"table frames: file {frames} is missing" in out
    sessions = Path(cat.files("sessions")[0])
    sessions.write_bytes(b"not parquet")
    report = verify_version(cat)
    lines = [d.line() for d in report.damaged]
    assert lines[0].startswith(f"table sessions: file {sessions} is not a readable Parquet "
                               "file")
    assert lines[1] == f"table frames: file {frames} is missing"
    assert lines[2] == ("table sessions: unreadable at this version, so the array groups it "
                        "references were not checked")
    assert report.arrays == 0 and len(lines) == 3


def test_verify_json_and_errors(damaged, capsys):
    cat, _ = damaged
    assert main(["catalog", "verify", "1", "--json", "--catalog", str(cat.layout.root)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["ok"], out["version"], out["arrays"], out["damaged"]) == (True, 1, 6, [])
    assert out["table_files"] == {"sessions": 1, "frames": 1, "builds": 1}
    assert main(["catalog", "verify", "4", "--catalog", str(cat.layout.root)]) == 2
    assert "no version 4" in capsys.readouterr().err


def test_temp_leftovers_of_dead_writers_go_at_the_next_commit(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    tmp = cat.layout.arrays_tmp
    sleeper = subprocess.Popen(["sleep", "60"])
    try:
        dead = subprocess.Popen(["true"])
        dead.wait()
        names = {"dead": f"{'a' * 64}.{dead.pid}.{'0' * 32}.zarr",
                 "live": f"{'b' * 64}.{sleeper.pid}.{'1' * 32}.zarr",
                 "format4": f"{'c' * 64}.{'2' * 32}.zarr"}  # before the pid was in the name
        for name in names.values():
            (tmp / name / "values").mkdir(parents=True)
            (tmp / name / "values" / "zarr.json").write_text("{}")
        cat.commit(make_build(["p01-bowl-use-00"], seed=1))
        assert sorted(os.listdir(tmp)) == [names["live"]]  # a live process's stays
        sleeper.kill()
        sleeper.wait()
        assert remove_temp_groups(cat.layout) == [names["live"]]
        (tmp / names["dead"]).mkdir()
        assert cat.vacuum(1).freed_bytes >= 0 and os.listdir(tmp) == []
    finally:
        sleeper.kill()
        sleeper.wait()


def test_migration_adds_manifests_and_names_a_damaged_old_group(tmp_path, capsys):
    src = unpack(archive(4), tmp_path / "v4")
    digests = sorted(p.name.removesuffix(".zarr") for p in (src / "arrays").glob("??/*.zarr"))
    layout = CatalogLayout(src)
    contact = next(d for d in digests
                   if json.loads((layout.array_group(d) / "zarr.json").read_text())
                   ["attributes"]["kind"] == "contact")
    # a format-4 group has no manifest: only its digest tells a missing chunk
    (layout.array_group(contact) / "observed" / "c" / "0").unlink()
    assert verify_group(layout, contact) == [
        "its content does not match its digest (an altered or missing chunk, or altered "
        "metadata)"]
    copy = tmp_path / "copy"
    shutil.copytree(src, copy)
    report = migrate_catalog(src)
    assert report.arrays_upgraded == 2
    assert report.damaged_arrays == {contact: "its content does not match its digest (an "
                                     "altered or missing chunk)"}
    cat = gc.open(src)
    e = expected()
    verts, faces = cat.object_mesh("cube")
    np.testing.assert_array_equal(verts, e["vertices"])
    for d in digests:
        attrs = json.loads((layout.array_group(d) / "zarr.json").read_text())["attributes"]
        assert ("chunks" in attrs) == (d != contact), d
        assert verify_group(layout, d) == ([] if d != contact else [
            "its content does not match its digest (an altered or missing chunk, or altered "
            "metadata)"])
    hand = cat.table("sessions")["hand_mesh_digest"][0].as_py()
    chunk = layout.array_group(hand) / "faces" / "c" / "0" / "0"
    chunk.unlink()  # a migrated group's chunks are checked on every read
    with pytest.raises(DamagedArrayError, match="faces/c/0/0 of array 'faces' is missing"):
        cat.hand_mesh(SESSION)
    code, _ = _verify_cli(cat)
    assert code == 1

    assert main(["catalog", "migrate", str(copy)]) == 0
    out = capsys.readouterr().out
    assert f"migrated {copy} from format 4 to 7; new version 2 pins the upgraded tables" in out
    assert (f"  array group {contact} left as it was: its content does not match its digest (an "
            "altered or missing chunk) (`graspcap catalog verify` names the sessions using it)"
            ) in out
