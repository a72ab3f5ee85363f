"""A stored stage result whose classes' modules are gone (an old layout) is a cache miss."""

from __future__ import annotations

import json
import sys

import numpy as np

from graspcap.flows.workarea import WorkArea
from graspcap.tasks.hand.model import HandSide


def test_the_record_lists_the_modules_and_a_lookup_hits(tmp_path):
    work = WorkArea(tmp_path)
    work.save("fit_hand", "k1", {"side": HandSide.RIGHT, "x": np.zeros(3)}, "b1")
    record = json.loads(work.result_path("fit_hand", "k1").with_suffix(".json").read_text())
    assert "graspcap.tasks.hand.model" in record["modules"]
    assert "numpy" in record["modules"]
    ref = work.lookup("fit_hand", "k1")
    assert ref is not None and ref.cached
    assert WorkArea.load(ref)["side"] is HandSide.RIGHT


def test_a_result_of_a_module_that_moved_is_a_miss(tmp_path, monkeypatch):
    (tmp_path / "oldmod_t16.py").write_text(
        "from dataclasses import dataclass\n@dataclass\nclass Old:\n    a: int\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    import oldmod_t16

    work = WorkArea(tmp_path / "work")
    work.save("reconstruct_hand", "k2", oldmod_t16.Old(3), "b1")
    assert work.lookup("reconstruct_hand", "k2") is not None
    (tmp_path / "oldmod_t16.py").unlink()  # the module moves away
    monkeypatch.delitem(sys.modules, "oldmod_t16")
    assert work.lookup("reconstruct_hand", "k2") is None


def test_a_record_from_before_the_module_list_is_a_miss(tmp_path):
    work = WorkArea(tmp_path)
    work.save("select_steady", "k3", [1, 2], "b1")
    path = work.result_path("select_steady", "k3").with_suffix(".json")
    record = json.loads(path.read_text())
    del record["modules"]
    path.write_text(json.dumps(record))
    assert work.lookup("select_steady", "k3") is None


def _module(tmp_path, name: str, body: str):
    (tmp_path / f"{name}.py").write_text("from dataclasses import dataclass\n" + body)
    sys.modules.pop(name, None)
    return __import__(name)


def test_a_result_whose_class_was_renamed_is_a_miss_with_a_note(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = _module(tmp_path, "renamed_t17", "@dataclass\nclass Fit:\n    a: int\n")
    work = WorkArea(tmp_path / "work")
    work.save("fit_hand", "k4", [mod.Fit(1)], "b1")
    record = json.loads(work.result_path("fit_hand", "k4").with_suffix(".json").read_text())
    assert record["types"] == {"renamed_t17:Fit": ["a"]}
    assert work.check("fit_hand", "k4") == (work.lookup("fit_hand", "k4"), None)
    _module(tmp_path, "renamed_t17", "@dataclass\nclass HandFit:\n    a: int\n")  # renamed
    monkeypatch.delitem(sys.modules, "renamed_t17")
    assert work.check("fit_hand", "k4") == (
        None, "the stored fit_hand result cannot be used: its type renamed_t17.Fit no longer "
              "exists")


def test_a_result_missing_a_field_the_code_now_expects_is_a_miss(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = _module(tmp_path, "grown_t17", "@dataclass\nclass Fit:\n    a: int\n    b: int\n")
    work = WorkArea(tmp_path / "work")
    work.save("fit_hand", "k5", {"fit": mod.Fit(1, 2)}, "b1")
    _module(tmp_path, "grown_t17", "@dataclass\nclass Fit:\n    a: int\n    c: int = 0\n")
    monkeypatch.delitem(sys.modules, "grown_t17")
    assert work.check("fit_hand", "k5") == (
        None, "the stored fit_hand result cannot be used: its type grown_t17.Fit lacks field(s) "
              "c and has field(s) b the code no longer has")
    assert work.lookup("fit_hand", "k5") is None


def test_pydantic_models_are_checked_too_and_records_without_types_are_misses(tmp_path):
    from graspcap.tasks.hand.fit_hand import FitHandConfig

    work = WorkArea(tmp_path)
    work.save("fit_hand", "k6", FitHandConfig(), "b1")
    path = work.result_path("fit_hand", "k6").with_suffix(".json")
    record = json.loads(path.read_text())
    assert record["types"]["graspcap.tasks.hand.fit_hand:FitHandConfig"] == sorted(
        FitHandConfig.model_fields)
    assert work.lookup("fit_hand", "k6") is not None
    del record["types"]
    path.write_text(json.dumps(record))
    assert work.check("fit_hand", "k6")[1] == (
        "the stored fit_hand result cannot be used: its record predates the result type check")
