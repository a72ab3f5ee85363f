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
from urllib.parse import unquote

import pyarrow as pa
import pyarrow.compute as pc
from deltalake import DeltaTable
from pydantic import BaseModel, ConfigDict, Field

from graspcap.catalog.delta import delta_table, read_files, read_table
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
                  removed: Sequence[str] = (), *, incremental: bool = True) -> AuditResult:
    """Audit the tables at Delta versions ``pins`` (the new version, not yet published)
    against ``published`` (``(version, its pins)`` or None) with ``gates``; ``removed``:
    sessions the commit removes on purpose. What it reads of ``frames``: :func:`frames_facts`
    (``incremental=False``: every row's key, whatever the published version's audit said)."""
    reasons: list[str] = []
    measured: dict[str, Any] = {}
    schema_problems = []
    tables = {name: delta_table(layout, name, pins[name]) for name in DATA_TABLES}
    for name in DATA_TABLES:
        have = {f.name for f in tables[name].schema().fields}
        missing = [c for c in TABLE_SCHEMAS[name].names if c not in have]
        if missing:
            schema_problems.append(f"table {name!r} lacks column(s) {missing}")
    if schema_problems:
        reasons += [f"schema: {p}" for p in schema_problems]
    sessions = read_files("sessions", tables["sessions"].file_uris(),
                          ["session_id", "status", "input_digest"], layout)
    facts = frames_facts(layout, tables["frames"], published, removed, incremental,
                         tables["builds"])
    ids = sessions["session_id"].to_pylist()
    status = dict(zip(ids, sessions["status"].to_pylist(), strict=True))
    measured["sessions"] = len(ids)
    measured["frames"] = facts.rows
    dupes = len(ids) - len(set(ids))
    if dupes:
        reasons.append(f"rows: {dupes} duplicate session_id row(s) in sessions")
    measured["duplicate_frame_keys"] = facts.duplicate_keys
    measured["frames_read"] = {"how": facts.how, "keys": facts.keys_read,
                               "session_ids": facts.ids_read}
    if facts.duplicate_keys:
        reasons.append(f"rows: {facts.duplicate_keys} (session_id, frame) key(s) appear more "
                       "than once in frames")
    if gates.require_frames:
        empty = sorted(s for s, st in status.items()
                       if st != Status.FAILED and s not in facts.sessions)
        measured["sessions_without_frames"] = empty
        if empty:
            reasons.append(f"rows: {len(empty)} {Status.OK}/{Status.FLAGGED} session(s) without "
                           f"frames rows: {_few(empty)}")
    orphans = sorted(facts.sessions - set(ids))
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
        _against_published(layout, published, gates, status, sessions, facts, set(removed),
                           failed, reasons, measured)
    return AuditResult(not reasons, reasons, published[0] if published else None, measured,
                       gates.model_dump(mode="json"))


@dataclass(frozen=True)
class FramesFacts:
    """What the audit needs of ``frames`` (:func:`frames_facts`)."""

    rows: int
    """Rows of the new version."""
    duplicate_keys: int
    """(session_id, frame) keys that appear more than once in it."""
    sessions: set[str]
    """Sessions with at least one row in it."""
    published_rows: int | None
    """Rows of the published version, less those of the sessions removed on purpose (None:
    no published version)."""
    how: str
    """``full`` (every row's key read) or ``incremental`` (see :func:`frames_facts`)."""
    keys_read: int
    """Rows whose ``session_id`` and ``frame`` were read."""
    ids_read: int
    """Further rows whose ``session_id`` alone was read (the kept files')."""


def frames_facts(layout: CatalogLayout, new: DeltaTable,
                 published: tuple[int, Mapping[str, int]] | None,
                 removed: Sequence[str] = (), incremental: bool = True,
                 builds: DeltaTable | None = None) -> FramesFacts:
    """The facts of ``frames`` at the new version (``new``) the audit checks, read in
    proportion to what changed since ``published`` where that is exact.

    Row counts come from the Delta log (each file's ``numRecords``), never from the rows.
    The files of the new version are those it shares with the published one (*kept*: their
    rows are the published version's) and those added since. When the published version's
    own audit found no duplicate key (its builds row says so), the kept files have none
    among themselves either, so only the added files' ``(session_id, frame)`` are read, the
    kept files' ``session_id`` only (one dictionary-encoded column: which sessions have rows),
    and both columns of a kept file only for a session that also has added rows (a commit
    that left a rewritten session's old rows: exactly the duplicates to find). Otherwise (no
    published version, or one whose audit did not find its keys unique) every row's key is
    read, as before. The same facts either way; ``tests/catalog/test_catalog_wap.py``."""
    files = _file_rows(layout, new)
    rows = sum(files.values())
    if published is None:
        keys = read_files("frames", list(files), ["session_id", "frame"], layout)
        return FramesFacts(rows, _duplicates(keys), set(pc.unique(keys["session_id"])
                                                        .to_pylist()), None, "full",
                           keys.num_rows, 0)
    number, pins = published
    old_files = _file_rows(layout, delta_table(layout, "frames", pins["frames"]))
    gone = pa.array(sorted(set(removed)), pa.string())
    if incremental and _published_keys_unique(layout, builds, number, pins):
        kept = [f for f in files if f in old_files]
        added = [f for f in files if f not in old_files]
        fresh = read_files("frames", added, ["session_id", "frame"], layout)
        held = read_files("frames", kept, ["session_id"], layout)["session_id"]
        fresh_ids = pc.unique(fresh["session_id"])
        both = pc.filter(fresh_ids, pc.is_in(fresh_ids, pc.unique(held)))
        if len(both):
            old_keys = read_files("frames", kept, ["session_id", "frame"], layout)
            fresh = pa.concat_tables([fresh, old_keys.filter(pc.is_in(old_keys["session_id"],
                                                                      both))])
        published_rows = sum(old_files.values())
        if len(gone):
            dropped = [f for f in old_files if f not in files]
            old_ids = read_files("frames", dropped, ["session_id"], layout)["session_id"]
            published_rows -= _count_in(held, gone) + _count_in(old_ids, gone)
        sessions = set(fresh_ids.to_pylist()) | set(pc.unique(held).to_pylist())
        return FramesFacts(rows, _duplicates(fresh), sessions, published_rows, "incremental",
                           fresh.num_rows, len(held))
    keys = read_files("frames", list(files), ["session_id", "frame"], layout)
    published_rows = sum(old_files.values())
    if len(gone):
        old_ids = read_files("frames", list(old_files), ["session_id"], layout)["session_id"]
        published_rows -= _count_in(old_ids, gone)
    return FramesFacts(rows, _duplicates(keys), set(pc.unique(keys["session_id"]).to_pylist()),
                       published_rows, "full", keys.num_rows, 0)


def _file_rows(layout: CatalogLayout, table: DeltaTable) -> dict[str, int]:
    """``{file URI: rows}`` of a ``frames`` version, the rows from its log's statistics (the
    file's ``session_id`` column where the log has none)."""
    uris = table.file_uris()
    actions = pa.table(table.get_add_actions(flatten=True)).select(["path", "num_records"])
    stats = {unquote(p).rsplit("/", 1)[-1]: n for p, n in zip(
        actions["path"].to_pylist(), actions["num_records"].to_pylist(), strict=True)}
    out = {}
    for uri in uris:
        n = stats.get(unquote(uri).rsplit("/", 1)[-1])
        out[uri] = int(n) if n is not None else read_files("frames", [uri], ["session_id"],
                                                           layout).num_rows
    return out


def _published_keys_unique(layout: CatalogLayout, builds: DeltaTable, number: int,
                           pins: Mapping[str, int]) -> bool:
    """Whether the published version ``number``'s own audit found every (session_id, frame)
    key of its ``frames`` unique (False when it has no audit, or one from before the count was
    kept). Its builds row is in ``builds`` (the new version's builds table: the published
    version is never newer than the version a build commits on), else at its own pins."""
    for table in ([builds] if builds is not None else []) + [None]:
        files = table.file_uris() if table is not None else None
        rows = (read_files("builds", files, ["catalog_version", "audit_json"], layout)
                if files is not None else read_table(layout, "builds", pins["builds"],
                                                     ["catalog_version", "audit_json"]))
        for row in rows.filter(pc.equal(rows["catalog_version"], number)).to_pylist():
            if row["audit_json"]:
                measured = json.loads(row["audit_json"]).get("measured", {})
                return measured.get("duplicate_frame_keys") == 0
            return False
    return False


def _duplicates(keys: pa.Table) -> int:
    """(session_id, frame) keys of ``keys`` that appear more than once."""
    counted = keys.group_by(["session_id", "frame"]).aggregate([([], "count_all")])
    return int(pc.sum(pc.greater(counted["count_all"], 1)).as_py() or 0)


def _count_in(values: pa.ChunkedArray | pa.Array, wanted: pa.Array) -> int:
    return int(pc.sum(pc.is_in(values, wanted)).as_py() or 0)


def _against_published(layout: CatalogLayout, published: tuple[int, Mapping[str, int]],
                       gates: AuditGates, status: dict[str, str], sessions: pa.Table,
                       facts: FramesFacts, removed: set[str], failed: int, reasons: list[str],
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
    old_frames, frames_rows = facts.published_rows, facts.rows
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
