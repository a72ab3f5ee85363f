"""Code in the cache key and ``graspcap build --plan``, with real Prefect builds and counted
stage executions (not timing).

A changed helper module is simulated by handing the code digest an edited copy of its source
(``code_digest._source`` patched for that one module): the digest is computed from that text
exactly as from the file, and the installed tree, which other tests and engineers share, is
never edited. Because the module that actually runs is unchanged, the re-run stages produce
byte-identical results, so their downstream stages are cache hits again (early cutoff): the
executions are exactly the stages whose own key changed, while the plan, which cannot know a
result before it is computed, lists the downstream stages as "upstream changed"."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from graspcap.flows import code_digest
from graspcap.flows.build import build_dataset
from graspcap.flows.plan import plan_build
from graspcap.tasks import pipeline
from tests.flow_fixtures import PRESET, copy_catalog, executions, fit_hand_failing_for

HELPER = "graspcap.tasks.object_pose.registration.engine"


def _ids(root: Path) -> list[str]:
    return sorted(json.loads(p.read_text())["session_id"] for p in root.glob("*/session.json"))


def _importers(module: str) -> set[str]:
    from graspcap.tasks.pipeline import STAGES

    return {n for n, s in STAGES.items() if module in dict(code_digest.stage_code(s).modules)}


def _downstream(of: set[str]) -> set[str]:
    from graspcap.tasks.pipeline import STAGES

    out = set(of)
    for name, stage in STAGES.items():  # topological order
        if out & set(stage.upstream):
            out.add(name)
    return out


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in root.rglob("*")}


@pytest.fixture
def edited_source(monkeypatch):
    """``edit(module, change)``: the code digest sees ``change(source)`` for ``module``."""
    real = code_digest._source

    def edit(module: str, change) -> None:
        def source(name: str):
            found = real(name)
            return (change(found[0]), found[1]) if name == module and found else found

        monkeypatch.setattr(code_digest, "_source", source)
        monkeypatch.setattr(code_digest, "MEMO_ENABLED", False)  # the files did not change
        code_digest.forget()

    yield edit
    monkeypatch.undo()
    code_digest._OVERRIDES.clear()
    code_digest.forget()


def test_plan_of_an_unchanged_catalog_is_all_cached_and_writes_nothing(warm, synth_root,
                                                                       tmp_path, capsys):
    from graspcap.cli import main

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    before = _tree(catalog)
    assert main(["build", str(synth_root), "--catalog", str(catalog), "--preset", PRESET,
                 "--plan"]) == 0
    out = capsys.readouterr().out
    n = 2 * len(pipeline.STAGES)  # 2 sessions
    assert out.splitlines()[-1].startswith(f"plan: all cached ({n} stages of 2 sessions)")
    assert _tree(catalog) == before  # no result, digest, manifest or catalog file written
    # a catalog that does not exist is not created: every stage runs for a new session
    fresh = tmp_path / "none"
    plans = plan_build([synth_root], fresh, PRESET)
    assert not fresh.exists()
    assert {p.action for p in plans} == {"run"}
    assert all(("new session", "") in p.reasons for p in plans)


def test_changed_helper_reruns_its_family_and_the_plan_names_it(warm, synth_root, tmp_path,
                                                                edited_source):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    family = _importers(HELPER)
    assert family == {"register_object", "register_scan", "estimate_adjustment",
                      "propagate_poses",  # tracks the object with it
                      "build_contactmap"}  # a symmetric object's turns (symmetric_contact)
    edited_source(HELPER, lambda src: src + b"\n_CHANGED_BODY = 1\n")
    plans = plan_build([synth_root], catalog, PRESET)
    named = {(p.session_id, p.stage) for p in plans if ("changed code", HELPER) in p.reasons}
    ids = _ids(synth_root)
    assert named == {(s, st) for s in ids for st in family}
    assert {(p.session_id, p.stage) for p in plans if p.action == "run"} == named
    assert {(p.session_id, p.stage) for p in plans if p.action == "runs if upstream changes"} == {
        (s, st) for s in ids for st in _downstream(family) - family}
    build_dataset([synth_root], catalog, PRESET, build_id="helper")
    assert executions(catalog, "helper") == sorted((s, st) for s in ids for st in family)
    recs = [json.loads(x) for x in (catalog / "work" / "executions.jsonl").read_text()
            .splitlines() if '"helper"' in x]
    assert {tuple(r["why"]) for r in recs} == {(f"changed code: {HELPER}",)}
    # graspcap status shows why they ran: one line per session
    from graspcap.flows.commands import status_text

    why = [line.strip() for line in status_text(catalog).splitlines()
           if line.strip().endswith(f": changed code: {HELPER}")]
    assert len(why) == len(ids)
    assert all(set(line[4:].partition(":")[0].split(", ")) == family for line in why), why
    # and now the plan is all cached again
    assert {p.action for p in plan_build([synth_root], catalog, PRESET)} == {"cached"}


def test_docstring_only_change_reruns_nothing(warm, synth_root, tmp_path, edited_source):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    edited_source(HELPER, lambda src: src.replace(b'"""', b'"""Reworded. ', 1)
                  + b"\n# a comment\n")
    assert {p.action for p in plan_build([synth_root], catalog, PRESET)} == {"cached"}
    build_dataset([synth_root], catalog, PRESET, build_id="doc")
    assert executions(catalog, "doc") == []


def test_faked_open3d_upgrade_reruns_the_stages_that_import_it(warm, synth_root, tmp_path,
                                                               edited_source):
    from graspcap.tasks.pipeline import STAGES

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    users = {n for n, s in STAGES.items() if "open3d" in dict(code_digest.stage_code(s).libraries)}
    assert "register_object" in users and "fit_hand" not in users
    real = code_digest.library_version("open3d")
    code_digest.override("lib:open3d", "0.0-fake")
    plans = plan_build([synth_root], catalog, PRESET)
    why = ("changed library", f"open3d {real} -> 0.0-fake")
    ids = _ids(synth_root)
    assert {(p.session_id, p.stage) for p in plans if why in p.reasons} == {
        (s, st) for s in ids for st in users}
    build_dataset([synth_root], catalog, PRESET, build_id="o3d")
    assert executions(catalog, "o3d") == sorted((s, st) for s in ids for st in users)


def test_plan_says_which_file_and_config_field_changed(warm, synth_root, tmp_path):
    """A changed config field is named by the plan (which runs and writes nothing)."""
    from graspcap.tasks.pipeline import configs_for

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    before = _tree(catalog)
    cfg = configs_for(PRESET)["register_scan"]
    name, value = next((k, v) for k, v in cfg.model_dump().items()
                       if isinstance(v, float) and v != 0)
    plans = plan_build([synth_root], catalog, PRESET,
                       overrides={"register_scan": {name: value * 1.1}})
    scan = [p for p in plans if p.stage == "register_scan"]
    assert {p.reasons for p in scan} == {(("changed config", name),)}
    assert {p.action for p in plans if p.stage in ("register_object", "fit_hand")} == {"cached"}
    assert _tree(catalog) == before


def _reindent(session: Path) -> None:
    manifest = session / "session.json"
    raw = json.loads(manifest.read_text())
    manifest.write_text(json.dumps(dict(reversed(list(raw.items()))), indent=7) + "\n")


def test_a_reindented_session_json_keeps_every_key(synth_root, tmp_path):
    """session.json is digested as canonical JSON: formatting and key order change no key,
    a changed value does."""
    import shutil

    from graspcap.flows.cached import cache_key, reads_digest, session_files
    from graspcap.flows.workarea import WorkArea
    from graspcap.tasks.pipeline import configs_for

    session = tmp_path / "s"
    shutil.copytree(next(p.parent for p in sorted(synth_root.glob("*/session.json"))), session)
    work = WorkArea(tmp_path / "work")
    config = configs_for(PRESET)["load_session"]

    def keys() -> tuple:
        files = session_files(session)
        return (cache_key("load_session", session, config, {}, work),
                reads_digest(work, files, ("manifest",)))

    before = keys()
    _reindent(session)
    assert keys() == before
    raw = json.loads((session / "session.json").read_text())
    raw["intent"] = str(raw.get("intent")) + "-edited"
    (session / "session.json").write_text(json.dumps(raw))
    assert keys()[1] != before[1]


@pytest.mark.slow
def test_a_reindented_session_json_runs_nothing_and_makes_no_version(synth_root, tmp_path,
                                                                     prefect_harness):
    import shutil

    root = tmp_path / "sessions"
    for p in sorted(synth_root.glob("*/session.json")):
        shutil.copytree(p.parent, root / p.parent.name)
    catalog = tmp_path / "catalog"
    assert build_dataset([root], catalog, PRESET, build_id="b1").catalog_version == 1
    for p in sorted(root.glob("*/session.json")):
        _reindent(p.parent)
    assert {p.action for p in plan_build([root], catalog, PRESET)} == {"cached"}
    report = build_dataset([root], catalog, PRESET, build_id="b2")
    assert executions(catalog, "b2") == []
    assert report.catalog_version is None


def test_a_stored_result_of_a_renamed_class_is_a_miss_and_the_build_completes(
        warm, synth_root, tmp_path):
    """The stored fit_hand results name a class the code no longer has (as after a rename:
    their records are edited to the old name): the plan says so, the build re-runs fit_hand
    (only: its new result is byte-identical, so downstream stays cached) and completes."""
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    records = sorted((catalog / "work" / "results" / "fit_hand").glob("*[0-9a-f].json"))
    assert len(records) == 2
    for path in records:
        record = json.loads(path.read_text())
        record["types"] = {k.replace(":", ":Old", 1) if k.startswith("graspcap.tasks.hand")
                           else k: v for k, v in record["types"].items()}
        path.write_text(json.dumps(record))
    plans = [p for p in plan_build([synth_root], catalog, PRESET) if p.stage == "fit_hand"]
    assert {p.action for p in plans} == {"run"}
    for p in plans:
        (reason, note), = p.reasons
        assert reason == "stored result unusable"
        assert note.startswith("the stored fit_hand result cannot be used: its type "
                               "graspcap.tasks.hand.") and note.endswith(" no longer exists")
    report = build_dataset([synth_root], catalog, PRESET, build_id="renamed")
    assert report.failed == {}
    assert executions(catalog, "renamed") == sorted((s, "fit_hand") for s in _ids(synth_root))


def test_plan_replays_a_remembered_failure_and_retry_failed_runs_it(warm, synth_root,
                                                                    tmp_path, monkeypatch):
    import shutil

    from graspcap.flows.plan import plan_text
    from graspcap.tasks import pipeline

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    shutil.rmtree(catalog / "work" / "results" / "fit_hand")
    good, bad = _ids(synth_root)
    with monkeypatch.context() as m:
        m.setitem(pipeline.STAGES, "fit_hand", fit_hand_failing_for(bad))
        assert set(build_dataset([synth_root], catalog, PRESET, build_id="half").failed) == {bad}
    plans = {(p.session_id, p.stage): p for p in plan_build([synth_root], catalog, PRESET)}
    assert {p.action for (s, _), p in plans.items() if s == good} == {"cached"}
    fit = plans[(bad, "fit_hand")]
    assert fit.action == "fails again"
    assert fit.reasons == (("failed last time", "did not converge (injected)"),)
    after = _downstream({"fit_hand"}) - {"fit_hand"}
    assert {st for (s, st), p in plans.items() if s == bad and p.action == "not ready"} == after
    text = plan_text(list(plans.values()))
    n = 2 * len(pipeline.STAGES)  # 2 sessions
    assert text.splitlines()[-1] == (f"plan: {n} stages of 2 sessions: {n - 1 - len(after)} "
                                     f"cached, 0 run, 1 fails again, {len(after)} not ready")
    retry = [p for p in plan_build([synth_root], catalog, PRESET, retry_failed=True)
             if (p.session_id, p.stage) == (bad, "fit_hand")]
    assert retry[0].action == "run"
    assert ("failed last time", "did not converge (injected)") in retry[0].reasons


def test_first_run_reasons_tell_a_new_session_from_a_stage_that_never_ran(tmp_path):
    from graspcap.flows.cached import diff_parts, run_reasons
    from graspcap.flows.workarea import WorkArea

    work = WorkArea(tmp_path)
    assert run_reasons(work, "fit_hand", "s1", "k", {}) == [("new session", "")]
    work.save_manifest("load_session", "s1", {"key": "k0", "parts": {}, "ok": True})
    assert run_reasons(work, "fit_hand", "s1", "k", {}) == [("not run before", "")]
    old = {"version": "1", "config": {"a": 1, "n": {"b": 2}}, "files": {"depth": {"x.png": "1"}},
           "modules": {"m": "1", "gone": "1"}, "libraries": {"numpy": "2.0"},
           "upstream": {"load_session": "1"}}
    new = {"version": "2", "config": {"a": 1, "n": {"b": 3}}, "files": {"depth": {"x.png": "2",
                                                                                 "y.png": "1"}},
           "modules": {"m": "2", "new": "1"}, "libraries": {"numpy": "2.1"},
           "upstream": {"load_session": "2"}}
    assert diff_parts(old, new) == [
        ("changed stage version", "1 -> 2"), ("changed config", "n.b"),
        ("changed input file", "depth: x.png (changed)"),
        ("changed input file", "depth: y.png (new)"),
        ("changed code", "gone (no longer used)"), ("changed code", "m"),
        ("changed code", "new (new)"), ("changed library", "numpy 2.0 -> 2.1"),
        ("upstream changed", "load_session")]
