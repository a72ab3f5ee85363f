"""A stage's key covers only what it reads (its file roles and its manifest fields), with real
Prefect builds and counted stage executions (not timing).

The edits are made to the shared fixture sessions in place and undone when the test ends
(:func:`edited`): a copy of a session lives at another path, and a path is part of every key,
so a copy would need a cold build of its own."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.flows.plan import plan_build
from tests.flow_fixtures import PRESET, copy_catalog, executions


@pytest.fixture
def edited():
    """``edit(path, data)``: write ``data`` to ``path``; every edited file gets its bytes back
    when the test ends."""
    saved: dict[Path, bytes] = {}

    def edit(path: Path, data: bytes) -> None:
        saved.setdefault(path, path.read_bytes())
        path.write_bytes(data)

    yield edit
    for path, data in saved.items():
        path.write_bytes(data)


def _sessions(root: Path) -> list[tuple[str, Path]]:
    return sorted((json.loads(p.read_text())["session_id"], p.parent)
                  for p in root.glob("*/session.json"))


def test_one_grasp_depth_pixel_reruns_only_the_stages_that_read_grasp_depth(
        warm, synth_root, tmp_path, edited):
    from graspcap.tasks.pipeline import STAGES

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    (sid, session), (other, _) = _sessions(synth_root)
    grasp = json.loads((session / "session.json").read_text())["grasp"]
    frame = session / grasp["depth"].format(index=grasp["steady_from"])
    depth = cv2.imread(str(frame), cv2.IMREAD_UNCHANGED)
    y, x = (int(v) for v in np.argwhere(depth > 0)[len(np.argwhere(depth > 0)) // 2])
    depth[y, x] += 37  # one pixel of one frame, 37 mm further
    edited(frame, cv2.imencode(".png", depth)[1].tobytes())

    readers = {n for n, s in STAGES.items() if "grasp_depth" in s.reads}
    assert readers == {"load_session", "select_steady", "joint_solve", "reconstruct_hand",
                       "estimate_adjustment", "build_contactmap", "propagate_poses",
                       "pictures"}
    plans = plan_build([synth_root], catalog, PRESET)
    planned = {p.stage for p in plans if p.action == "run"}
    assert {p.session_id for p in plans if p.action == "run"} == {sid}
    own = {p.stage for p in plans if p.action == "run"
           and any(r == "changed input file" for r, _ in p.reasons)}
    assert own == readers
    for p in plans:
        if p.stage in own and p.session_id == sid:
            assert ("changed input file", f"grasp_depth: {frame.relative_to(session)} "
                                          "(changed)") in p.reasons
    for name in ("register_object", "register_scan", "detect_keypoints"):
        assert name not in planned

    report = build_dataset([synth_root], catalog, PRESET, build_id="pixel")
    assert report.failed == {}
    ran = {st for s, st in executions(catalog, "pixel") if s == sid}
    assert {s for s, _ in executions(catalog, "pixel")} == {sid}
    maybe = {p.stage for p in plans if p.action == "runs if upstream changes"}
    assert planned == readers  # the plan's "run" lines are the stages reading the file
    for p in plans:  # the rest waits only on an upstream whose result may not change
        if p.action == "runs if upstream changes":
            assert [r for r, _ in p.reasons] == ["upstream changed"], p
    assert planned <= ran <= planned | maybe
    # one pixel 37 mm off in one frame leaves every reader's result as it was (a gated depth
    # reading), so nothing downstream runs: the plan's "run" lines are exactly what ran
    assert ran == planned
    assert not {"register_object", "register_scan"} & ran
    cached = {st for s in report.sessions if s.session_id == sid for st in s.cached}
    assert {"register_object", "register_scan"} <= cached
    assert other not in {s for s, _ in executions(catalog, "pixel")}


def test_an_edited_intent_runs_no_stage_and_makes_one_version_naming_it(
        warm, synth_root, tmp_path, edited):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    (sid, session), (other, _) = _sessions(synth_root)
    manifest = session / "session.json"
    raw = json.loads(manifest.read_text())
    raw["intent"] = raw["intent"] + "-edited"
    edited(manifest, json.dumps(raw, indent=2).encode())

    assert {p.action for p in plan_build([synth_root], catalog, PRESET)} == {"cached"}
    before = gc.open(catalog).latest_version()
    report = build_dataset([synth_root], catalog, PRESET, build_id="label")
    assert executions(catalog, "label") == []
    assert report.catalog_version == before + 1
    cat = gc.open(catalog)
    diff = cat.diff(before, report.catalog_version)
    assert diff["added"] == [] and diff["removed"] == []
    assert set(diff["changed"]) == {sid}
    assert "intent" in diff["changed"][sid]
    assert not {"participant", "object_id", "status", "T_adj"} & set(diff["changed"][sid])
    row = cat.table("sessions").to_pylist()
    assert {r["session_id"]: r["intent"] for r in row}[sid] == raw["intent"]
    # an unchanged rebuild then makes no version
    again = build_dataset([synth_root], catalog, PRESET, build_id="label2")
    assert executions(catalog, "label2") == [] and again.catalog_version is None


def test_a_stage_reading_an_undeclared_manifest_field_fails_loudly(synth_root, monkeypatch):
    """A glue that reads a field its ``Stage.fields`` does not declare raises naming the stage
    and the field (its key would not cover the field: a change would serve a stale result)."""
    import dataclasses

    from graspcap.tasks import pipeline
    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage
    from graspcap.tasks.session.manifest_guard import UndeclaredManifestField

    _, session = _sessions(synth_root)[0]
    configs = configs_for(PRESET)
    loaded = run_stage(STAGES["load_session"], session, configs["load_session"], {})
    fit = STAGES["fit_hand"]
    # fit_hand declares "hand" only: reading the steady frame is not allowed (the section
    # above it is named: nothing in it is declared)
    sneaky = dataclasses.replace(fit, run=lambda s, c, **up: s.manifest.grasp.steady_from)
    with pytest.raises(UndeclaredManifestField, match=r"fit_hand: reads session.json field "
                                                      r"'grasp', which its Stage.fields"):
        run_stage(sneaky, session, configs["fit_hand"], {"load_session": loaded,
                                                          "reconstruct_hand": None})
    sneaky = dataclasses.replace(fit, fields=("grasp.count",),
                                 run=lambda s, c, **up: s.manifest.grasp.steady_from)
    with pytest.raises(UndeclaredManifestField, match=r"'grasp.steady_from'"):
        run_stage(sneaky, session, configs["fit_hand"], {"load_session": loaded,
                                                          "reconstruct_hand": None})
    # a method of a section reads through the guard too: frame_path needs grasp.count
    grasp_only = dataclasses.replace(fit, fields=("grasp.depth",),
                                     run=lambda s, c, **up: s.grasp_path("depth", 0))
    with pytest.raises(UndeclaredManifestField, match=r"'grasp.count'"):
        run_stage(grasp_only, session, configs["fit_hand"], {"load_session": loaded,
                                                              "reconstruct_hand": None})
    declared = dataclasses.replace(fit, fields=("grasp.depth", "grasp.count"),
                                   reads=("grasp_depth",),
                                   run=lambda s, c, **up: s.grasp_path("depth", 0))
    assert run_stage(declared, session, configs["fit_hand"],
                     {"load_session": loaded, "reconstruct_hand": None}).is_file()
    # the labels are not in load_session's result at all
    assert loaded.manifest.intent == pipeline.LABEL_PLACEHOLDER
    # a misspelt declaration is refused when the pipeline is imported
    monkeypatch.setitem(pipeline.STAGES, "fit_hand",
                        dataclasses.replace(fit, fields=("grasp.steady",)))
    with pytest.raises(RuntimeError, match=r"fit_hand: Stage.fields names 'grasp.steady'"):
        pipeline._check_fields()


def test_every_stage_key_takes_its_declared_fields_only(synth_root, tmp_path, edited):
    """Editing a field changes the keys of exactly the stages that declare it (and of
    load_session, which validates all of it); a label changes none."""
    from graspcap.flows.cached import cache_key
    from graspcap.flows.workarea import ResultRef, WorkArea
    from graspcap.tasks.pipeline import STAGES, configs_for

    _, session = _sessions(synth_root)[0]
    work, configs = WorkArea(tmp_path / "work"), configs_for(PRESET)
    fake = {n: ResultRef(n, "k", "p", f"digest-{n}", "b") for n in STAGES if n != "load_session"}

    def keys() -> dict[str, str | None]:
        return {n: cache_key(n, session, configs[n], fake, work) for n in STAGES}

    manifest = session / "session.json"
    raw = json.loads(manifest.read_text())
    before = keys()
    assert None not in before.values()
    for field, change in (("grasp.steady_from", lambda g: {**g, "steady_from": 1}),
                          ("hand", None), ("color_camera.dist", None)):
        new = json.loads(json.dumps(raw))
        if field == "hand":
            new["hand"] = "left" if raw["hand"] == "right" else "right"
        elif field == "color_camera.dist":  # the lens: every stage that reads depth or pixels
            new["color_camera"]["dist"] = [0.1, -0.25, 0.001, -0.002, 0.08]
        else:
            new["grasp"] = change(raw["grasp"])
        edited(manifest, json.dumps(new).encode())
        now = keys()
        changed = {n for n in STAGES if now[n] != before[n]}
        top = field.split(".")[0]
        assert changed == {"load_session"} | {
            n for n, s in STAGES.items()
            if any(f == field or f == top or f.startswith(field + ".") for f in s.fields)}
    new = {**raw, "intent": raw["intent"] + "!", "participant": raw["participant"] + "!"}
    edited(manifest, json.dumps(new).encode())
    assert keys() == before
    # an invalid label: no key at all (every stage runs uncached; load_session reports it)
    edited(manifest, json.dumps({**raw, "intent": ""}).encode())
    assert keys() == dict.fromkeys(STAGES)
    from graspcap.flows.cached import _label_key

    assert _label_key("intent", "pour") == _label_key("intent", "cut")
    assert _label_key("intent", "") == "" and _label_key("participant", 3) == 3


def test_a_stage_opening_a_file_of_an_undeclared_role_fails_loudly(synth_root):
    """A glue that opens a file of a role its ``Stage.reads`` does not declare raises naming
    the stage, the file and its role (its key would not cover the file's bytes)."""
    import dataclasses

    from graspcap.tasks.pipeline import STAGES, configs_for, run_stage
    from graspcap.tasks.session.manifest_guard import UndeclaredFileRole

    _, session = _sessions(synth_root)[0]
    configs = configs_for(PRESET)
    loaded = run_stage(STAGES["load_session"], session, configs["load_session"], {})
    up = {"load_session": loaded, "reconstruct_hand": None}
    fit = STAGES["fit_hand"]
    depth = dataclasses.replace(fit, fields=("grasp.depth", "grasp.count"),
                                run=lambda s, c, **up: s.read_depth_m(s.grasp_path("depth", 0)))
    rel = loaded.manifest.grasp.depth.format(index=0)
    with pytest.raises(UndeclaredFileRole, match=rf"fit_hand: reads {rel} \(a grasp_depth "
                                                 r"file\), which its Stage.reads"):
        run_stage(depth, session, configs["fit_hand"], up)
    mesh = dataclasses.replace(fit, fields=("object_mesh",), run=lambda s, c, **up: s.read_mesh())
    with pytest.raises(UndeclaredFileRole, match=r"\(a object_mesh file\)"):
        run_stage(mesh, session, configs["fit_hand"], up)
    vertices, _ = run_stage(dataclasses.replace(mesh, reads=("object_mesh",)), session,
                            configs["fit_hand"], up)
    assert len(vertices) > 0
    # every stage of the pipeline reads only what it declares: a real build of every stage
    # runs under the guard (tests/flows/test_build.py and the others), this checks the roles
    # the guard knows are the roles the stages declare
    known = set(loaded.input_files())
    assert all(set(st.reads) <= known for st in STAGES.values())
