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
