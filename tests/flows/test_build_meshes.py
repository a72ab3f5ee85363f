"""A real build of sessions that share an object_id but bring different meshes (the session
contract allows it): all commit, each with its own mesh and contact map (before format 5 the
commit checked every contact map against one mesh per object_id and the whole build was lost).
The new session's stages run: ~12 s beside the warm build the flow tests share."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from tests.flow_fixtures import PRESET, copy_catalog, require_pipeline_passes


def _sessions(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if (p / "session.json").exists())


def test_one_object_id_with_two_meshes_commits_every_session(warm, synth_root, tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    first, second = _sessions(synth_root)
    label = json.loads((first / "session.json").read_text())["object_id"]
    twin = tmp_path / "more" / "twin"
    shutil.copytree(second, twin)
    manifest = json.loads((twin / "session.json").read_text())
    manifest.update(session_id="twin-of-second", object_id=label)
    (twin / "session.json").write_text(json.dumps(manifest))
    # the same surface with 20 faces split in four: a rescan's mesh, more vertices
    path = twin / manifest["object_mesh"]
    mesh = trimesh.load(path, force="mesh", process=False)
    v, f = trimesh.remesh.subdivide(mesh.vertices, mesh.faces, face_index=np.arange(20))
    trimesh.Trimesh(v, f, process=False).export(path)
    meshes = {p: trimesh.load(p / manifest["object_mesh"], force="mesh", process=False)
              for p in (first, twin)}
    assert len(meshes[twin].vertices) > len(meshes[first].vertices)

    report = build_dataset([synth_root, tmp_path / "more"], catalog, PRESET, build_id="twin")
    require_pipeline_passes(report)
    assert report.added == ["twin-of-second"]
    cat = gc.open(catalog)
    rows = {r["session_id"]: r for r in cat.table("sessions").to_pylist()}
    first_id, second_id = (json.loads((p / "session.json").read_text())["session_id"]
                           for p in (first, second))
    assert rows["twin-of-second"]["object_id"] == rows[first_id]["object_id"] == label
    owners = cat.object_meshes(label)  # the fixture's two sessions share one object and mesh
    assert rows[second_id]["object_id"] == label
    (twin_report,) = [s for s in report.sessions if s.session_id == "twin-of-second"]
    assert any("labels 2 different object meshes" in n and first_id in n and second_id in n
               and "twin-of-second" in n for n in twin_report.notes), twin_report.notes
    assert owners == {rows[first_id]["object_mesh_digest"]: sorted([first_id, second_id]),
                      rows["twin-of-second"]["object_mesh_digest"]: ["twin-of-second"]}
    for sid, folder in ((first_id, first), ("twin-of-second", twin)):
        verts, faces = cat.object_mesh(session_id=sid)
        np.testing.assert_allclose(verts, np.asarray(meshes[folder].vertices, np.float32))
        values, observed = cat.contactmap(sid)
        assert len(values) == len(observed) == len(verts) == len(meshes[folder].vertices)
    with pytest.raises(gc.CatalogError, match=rf"object '{label}' has 2 different meshes"):
        cat.object_mesh(label)
    ds = gc.GraspDataset(cat, unit="sessions", status=("ok", "flagged"))
    for i in range(len(ds)):
        item = ds[i]
        assert len(item["contact"]) == len(item["object_vertices"])
