"""The build's view of the catalog's records: a `catalog remove` version records no build, so
the failures a rebuild replays (and makes no version for) are still found behind it."""

from __future__ import annotations

import graspcap.catalog as gc
from graspcap.flows.build import last_build_failures, recorded_failures
from graspcap.flows.workarea import WorkArea
from tests.catalog_factory import make_build

IDS = ["p01-mug-use-00", "p02-drill-use-00", "p03-bowl-handoff-00"]
FAILED = "p03-bowl-handoff-00"


def test_recorded_failures_look_past_a_remove_version(tmp_path):
    cat = gc.open(tmp_path / "cat", create=True)
    cat.commit(make_build(IDS, seed=1, build_id="b1", failed=(FAILED,)))
    error = cat.table("sessions").to_pylist()[2]["error"]
    work = WorkArea(tmp_path / "cat" / "work")  # no builds.jsonl: the catalog's record counts
    assert recorded_failures(cat) == {FAILED: error}
    assert last_build_failures(cat, work) == {FAILED}
    assert cat.remove(["p01-mug-use-00"], "mislabelled") == 2
    assert recorded_failures(cat) == {FAILED: error}
    assert last_build_failures(cat, work) == {FAILED}
