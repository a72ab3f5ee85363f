"""Write-audit-publish: the audit that decides whether a committed version is published.

A build writes its version (``commit.commit_build``); before the ``versions`` row lands, the
audit compares the new version's tables with the previously *published* version and checks
the configured gates (``AuditGates``). The outcome goes into the build's ``builds`` row
(``audit_passed``, ``audit_reasons``, ``audit_json``) and the version's ``state`` in its
``versions`` row: ``published`` when the audit passed (and ``auto_publish`` is on), else
``staged``: committed and readable by number, but not what ``open()``/``GraspDataset`` read by
default. ``graspcap catalog publish VERSION`` / ``reject VERSION`` change the state by hand.
The anchors are Iceberg's write-audit-publish (a staged snapshot that is cherry-picked into
``main`` once audited) and lakeFS merges (a branch is merged into ``main`` after its checks
pass); here the published pointer is "the newest version whose state is published".
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
from pydantic import BaseModel, ConfigDict, Field

from graspcap.catalog.delta import delta_table, read_table
from graspcap.catalog.layout import CatalogLayout
from graspcap.schemas.tables import DATA_TABLES, TABLE_SCHEMAS, Status

VERDICT_RANK = {Status.OK.value: 0, Status.FLAGGED.value: 1, Status.FAILED.value: 2}
"""QA verdicts from best to worst: ok -> flagged -> failed is a regression."""


class AuditGates(BaseModel):
    """The gates a version must pass to be published (``graspcap build --gate NAME=VALUE``).

    Shares are fractions in [0, 1]; ``None`` turns a gate off. The comparisons are against the
    previously published version; a catalog's first version has none, so only the failed-share
    cap, the schema and the row checks apply to it.
    """

    model_config = ConfigDict(frozen=True, extra="forbid", use_attribute_docstrings=True)

    max_failed_share: float | None = Field(None, ge=0, le=1)
    """Most sessions of the version that may have status failed, as a share (off by default:
    a dataset of hard captures may legitimately fail most of them; the rise gate catches a
    build that breaks)."""
    max_failed_share_rise: float | None = Field(0.10, ge=0, le=1)
    """How much the share of failed sessions may rise over the published version's."""
    max_regressed_share: float | None = Field(0.05, ge=0, le=1)
    """Most sessions whose inputs did not change (same ``input_digest`` as in the published
    version) whose QA verdict got worse (ok -> flagged -> failed), as a share of those
    sessions."""
    tolerated_sessions: int = Field(2, ge=0)
    """The share gates above pass whatever the share when at most this many sessions make
    it (more failed sessions than in the published version; regressed sessions): in a small
    catalog one bad capture is a large share, not a sign that the build broke."""
    max_lost_sessions: int | None = Field(0, ge=0)
    """Sessions of the published version missing from the new one (not removed on purpose)."""
    max_frames_drop_share: float | None = Field(0.5, ge=0, le=1)
    """How much the number of ``frames`` rows may fall below the published version's, as a
    share of it (sessions removed on purpose do not count)."""
    require_frames: bool = True
    """Every session with status ok or flagged has at least one ``frames`` row."""
    auto_publish: bool = True
    """Publish the version when the audit passes (False: stage every version; publish by hand)."""


@dataclass(frozen=True)
class AuditResult:
    """An audit's outcome: passed or not, one reason per failed gate, what was measured."""

    passed: bool
    reasons: list[str]
    compared_to: int | None
    """The published version the new one was compared with (None: there was none)."""
    measured: dict[str, Any] = field(default_factory=dict)
    gates: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True, default=str)

    @classmethod
    def from_json(cls, text: str) -> AuditResult:
        return cls(**json.loads(text))


def _share(n: int, total: int) -> float:
    return n / total if total else 0.0


def audit_version(layout: CatalogLayout, pins: Mapping[str, int],
                  published: tuple[int, Mapping[str, int]] | None, gates: AuditGates,
                  removed: Sequence[str] = ()) -> AuditResult:
    """Audit the tables at Delta versions ``pins`` (the new version, not yet published)
    against ``published`` (``(version, its pins)`` or None) with ``gates``; ``removed``:
    sessions the commit removes on purpose."""
    reasons: list[str] = []
    measured: dict[str, Any] = {}
    schema_problems = []
    for name in DATA_TABLES:
        have = {f.name for f in delta_table(layout, name, pins[name]).schema().fields}
        missing = [c for c in TABLE_SCHEMAS[name].names if c not in have]
        if missing:
            schema_problems.append(f"table {name!r} lacks column(s) {missing}")
    if schema_problems:
        reasons += [f"schema: {p}" for p in schema_problems]
    sessions = read_table(layout, "sessions", pins["sessions"],
                          ["session_id", "status", "input_digest"])
    frames = read_table(layout, "frames", pins["frames"], ["session_id", "frame"])
    ids = sessions["session_id"].to_pylist()
    status = dict(zip(ids, sessions["status"].to_pylist(), strict=True))
    measured["sessions"] = len(ids)
    measured["frames"] = frames.num_rows
    dupes = len(ids) - len(set(ids))
    if dupes:
        reasons.append(f"rows: {dupes} duplicate session_id row(s) in sessions")
    keys = frames.group_by(["session_id", "frame"]).aggregate([([], "count_all")])
    dup_frames = int(pc.sum(pc.greater(keys["count_all"], 1)).as_py() or 0)
    if dup_frames:
        reasons.append(f"rows: {dup_frames} (session_id, frame) key(s) appear more than once "
                       "in frames")
    per_session = dict(zip(*[c.to_pylist() for c in frames.group_by("session_id").aggregate(
        [([], "count_all")]).select(["session_id", "count_all"]).columns], strict=True))
    if gates.require_frames:
        empty = sorted(s for s, st in status.items()
                       if st != Status.FAILED and not per_session.get(s))
        measured["sessions_without_frames"] = empty
        if empty:
            reasons.append(f"rows: {len(empty)} {Status.OK}/{Status.FLAGGED} session(s) without "
                           f"frames rows: {_few(empty)}")
    orphans = sorted(set(per_session) - set(ids))
    if orphans:
        reasons.append(f"rows: frames of {len(orphans)} session(s) not in sessions: "
                       f"{_few(orphans)}")
    failed = sum(1 for st in status.values() if st == Status.FAILED)
    share = _share(failed, len(ids))
    measured["failed_sessions"] = failed
    measured["failed_share"] = round(share, 6)
    if gates.max_failed_share is not None and share > gates.max_failed_share:
        reasons.append(f"failed share: {failed} of {len(ids)} sessions failed ({share:.1%} > "
                       f"max_failed_share {gates.max_failed_share:.1%})")
    if published is not None:
        _against_published(layout, published, gates, status, sessions, frames.num_rows,
                           set(removed), failed, reasons, measured)
    return AuditResult(not reasons, reasons, published[0] if published else None, measured,
                       gates.model_dump(mode="json"))


def _against_published(layout: CatalogLayout, published: tuple[int, Mapping[str, int]],
                       gates: AuditGates, status: dict[str, str], sessions: pa.Table,
                       frames_rows: int, removed: set[str], failed: int, reasons: list[str],
                       measured: dict[str, Any]) -> None:
    """The gates that compare with the published version (``audit_version``)."""
    share = _share(failed, len(status))
    number, pins = published
    old = read_table(layout, "sessions", pins["sessions"], ["session_id", "status",
                                                            "input_digest"])
    old_status = dict(zip(old["session_id"].to_pylist(), old["status"].to_pylist(),
                          strict=True))
    old_input = dict(zip(old["session_id"].to_pylist(), old["input_digest"].to_pylist(),
                         strict=True))
    new_input = dict(zip(sessions["session_id"].to_pylist(),
                         sessions["input_digest"].to_pylist(), strict=True))
    old_failed = sum(1 for st in old_status.values() if st == Status.FAILED)
    old_share = _share(old_failed, len(old_status))
    measured["published_failed_share"] = round(old_share, 6)
    rise = gates.max_failed_share_rise
    if rise is not None and share > old_share + rise + 1e-12 \
            and failed - old_failed > gates.tolerated_sessions:
        reasons.append(f"failed share: {share:.1%} of sessions failed, {old_share:.1%} in "
                       f"published version {number} (rise {share - old_share:.1%} > "
                       f"max_failed_share_rise {rise:.1%})")
    lost = sorted(set(old_status) - set(status) - removed)
    measured["lost_sessions"] = lost
    if gates.max_lost_sessions is not None and len(lost) > gates.max_lost_sessions:
        reasons.append(f"lost sessions: {len(lost)} session(s) of published version {number} "
                       f"are missing: {_few(lost)} (max_lost_sessions "
                       f"{gates.max_lost_sessions})")
    same_inputs = [s for s in status if s in old_input and old_input[s] == new_input[s]]
    regressed = sorted(s for s in same_inputs if VERDICT_RANK.get(status[s], 0)
                       > VERDICT_RANK.get(old_status[s], 0))
    improved = sorted(s for s in same_inputs if VERDICT_RANK.get(status[s], 0)
                      < VERDICT_RANK.get(old_status[s], 0))
    measured["unchanged_inputs"] = len(same_inputs)
    measured["regressed"] = {s: f"{old_status[s]} -> {status[s]}" for s in regressed}
    measured["improved"] = {s: f"{old_status[s]} -> {status[s]}" for s in improved}
    limit = gates.max_regressed_share
    if limit is not None and _share(len(regressed), len(same_inputs)) > limit \
            and len(regressed) > gates.tolerated_sessions:
        which = ", ".join(f"{s} ({measured['regressed'][s]})" for s in regressed[:5])
        more = f" (+{len(regressed) - 5} more)" if len(regressed) > 5 else ""
        reasons.append(f"QA regressions: {len(regressed)} of {len(same_inputs)} session(s) "
                       f"whose inputs did not change got a worse verdict than in published "
                       f"version {number}: {which}{more} "
                       f"({_share(len(regressed), len(same_inputs)):.1%} > max_regressed_share "
                       f"{limit:.1%})")
    old_frames = delta_table(layout, "frames", pins["frames"]).count()
    if removed:
        gone = read_table(layout, "frames", pins["frames"], ["session_id"])
        old_frames -= int(pc.sum(pc.is_in(gone["session_id"], pa.array(sorted(removed),
                                                                       pa.string()))).as_py()
                          or 0)
    measured["published_frames"] = old_frames
    drop = gates.max_frames_drop_share
    if drop is not None and frames_rows < old_frames * (1 - drop) - 1e-9:
        fell = _share(old_frames - frames_rows, old_frames)
        reasons.append(f"row count: frames has {frames_rows} rows, published version {number} "
                       f"had {old_frames} (a drop of {fell:.1%} > max_frames_drop_share "
                       f"{drop:.1%})")


def _few(items: Sequence[str], n: int = 5) -> str:
    return ", ".join(items[:n]) + (f" (+{len(items) - n} more)" if len(items) > n else "")


def parse_gates(items: Sequence[str], base: Mapping[str, Any] | None = None) -> AuditGates:
    """``AuditGates`` from ``NAME=VALUE`` texts (``graspcap build --gate``) over ``base``:
    a number, ``true``/``false``, or ``off``/``none`` (the gate is off); ``ValueError`` naming
    the gate and the valid names otherwise."""
    values: dict[str, Any] = dict(base or {})
    for item in items:
        name, sep, text = item.partition("=")
        name, text = name.strip(), text.strip()
        if not sep or name not in AuditGates.model_fields:
            raise ValueError(f"--gate {item!r}: give NAME=VALUE with NAME one of "
                             f"{', '.join(AuditGates.model_fields)}")
        low = text.lower()
        values[name] = (None if low in ("off", "none") else True if low == "true"
                        else False if low == "false" else text)
    try:
        return AuditGates(**values)
    except ValueError as exc:  # pydantic's ValidationError: name the gate, not the model
        first = str(exc).splitlines()
        raise ValueError(f"--gate: {'; '.join(first[1:3]) or first[0]}") from None
