"""GraspDataset's filters: a value no session of the version has is an error naming the known
values, not an empty dataset."""

from __future__ import annotations

import pytest

import graspcap.catalog as gc
from tests.catalog_factory import make_build

IDS = ["p01-mug-use-00", "p01-drill-handoff-00", "p02-bowl-use-00"]


@pytest.fixture(scope="module")
def catalog(tmp_path_factory):
    cat = gc.open(tmp_path_factory.mktemp("filters"), create=True)
    cat.commit(make_build(IDS, seed=3, frames=2))
    return cat


@pytest.mark.parametrize("kwargs, message", [
    ({"objects": ["dril"]}, "GraspDataset(objects=...): no session of catalog version 1 has "
                            "object_id 'dril'; known: bowl, drill, mug"),
    ({"objects": ["mug", "dril", "bwl"]}, "GraspDataset(objects=...): no session of catalog "
                                          "version 1 has object_id 'dril' or 'bwl'; known: "
                                          "bowl, drill, mug"),
    ({"participants": ["p1"]}, "GraspDataset(participants=...): no session of catalog version "
                               "1 has participant 'p1'; known: p01, p02"),
    ({"intents": ["hand-off"]}, "GraspDataset(intents=...): no session of catalog version 1 "
                                "has intent 'hand-off'; known: handoff, use"),
    ({"status": ("okay",)}, "GraspDataset(status=...): no session of catalog version 1 has "
                            "status 'okay'; known: failed, flagged, ok"),
])
def test_an_unknown_filter_value_names_it_and_the_known_ones(catalog, kwargs, message):
    with pytest.raises(ValueError) as err:
        gc.GraspDataset(catalog, **kwargs)
    assert str(err.value) == message


def test_known_values_filter_as_before(catalog):
    # a value known to the version but absent after the other filters is no error: empty
    assert len(gc.GraspDataset(catalog, objects=["bowl"], participants=["p01"])) == 0
    assert gc.GraspDataset(catalog, objects="drill", unit="sessions").session_ids == [
        "p01-drill-handoff-00"]  # one value as a string, not its letters
    # a status no session has yet is still a status
    assert len(gc.GraspDataset(catalog, status=("ok", "flagged"), unit="sessions")) == 3
