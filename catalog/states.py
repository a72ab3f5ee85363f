"""Which catalog versions are published, staged or rejected (write-audit-publish).

A version's state is its newest ``publications`` row (a change by hand: ``publish`` or
``reject``), else the ``state`` its ``versions`` row was committed with, else (a version of a
catalog before format 7) published. Readers' default is the newest published version; the
next build writes on top of the newest version that is not rejected (its *base*).
"""

from __future__ import annotations

import pyarrow as pa

from graspcap.catalog.delta import read_latest
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import TABLE_SCHEMAS, VersionState


def version_states(layout: CatalogLayout, versions: pa.Table | None = None
                   ) -> dict[int, VersionState]:
    """``{version: state}`` of every version (``versions``: the versions table, if read)."""
    versions = read_latest(layout, "versions") if versions is None else versions
    states = (versions["state"].to_pylist() if "state" in versions.column_names
              else [None] * versions.num_rows)  # a golden catalog of an older format
    out = {int(v): VersionState(s or VersionState.PUBLISHED) for v, s in zip(
        versions["version"].to_pylist(), states, strict=True)}
    if "publications" not in TABLE_SCHEMAS:
        return out
    changes = read_latest(layout, "publications").sort_by("time_utc").to_pylist()
    for row in changes:  # the newest row of a version wins
        if row["version"] in out:
            out[row["version"]] = VersionState(row["state"])
    return out


def published_of(states: dict[int, VersionState]) -> int | None:
    """The newest published version, None when none is."""
    return max((v for v, s in states.items() if s == VersionState.PUBLISHED), default=None)


def base_of(states: dict[int, VersionState]) -> int | None:
    """The newest version that is not rejected: what the next build writes on top of."""
    return max((v for v, s in states.items() if s != VersionState.REJECTED), default=None)
