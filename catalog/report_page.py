"""A build's report page: one static HTML file a person opens from disk (no server, no
script, no external URL; the plots are inline SVG).

    path = write_report(gc.open("catalog/"))          # the newest published version's build
    path = write_report(cat, 3)                       # version 3's, again

``<catalog>/reports/<build_id>/index.html`` (``CatalogLayout.report_file``) shows:

- the build: the version it made and the one before, its parameters (roots, preset, config
  digest, code version), the stages that ran or hit the cache, its timings, and every version
  of the catalog with a link to its own report (the lineage);
- every session of the version as a table row, failed first (with their reasons), then
  flagged (the QA flags), then ok: its labels, this build's outcome, the QA notes, the key
  ``qa_*`` metrics coloured against the build's QA limits, and thumbnails linking to the
  full pictures and the coloured contact mesh (PLY);
- per QA metric, a histogram over the version's sessions with the flag and fail limits the
  build used (its ``qa_metrics`` config), and the metric's median per catalog version.

The pictures are the catalog's content-addressed files (``CatalogLayout.picture_file``) the
build record names per session (``SessionReport.pictures``), so the report of an old version
shows its own. ``graspcap catalog export`` writes the same page beside copies of the pictures
(:func:`render` with another ``href``).
"""

from __future__ import annotations

import json
import math
import os
import statistics
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from graspcap.catalog.layout import PICTURE_SUFFIXES, path_name
from graspcap.catalog.report_svg import esc as _e
from graspcap.catalog.report_svg import histogram_svg, versions_svg
from graspcap.catalog.report_svg import level_of as _level
from graspcap.catalog.report_svg import num as _num
from graspcap.schemas.qa import QA_BY_NAME, qa_columns

if TYPE_CHECKING:
    from graspcap.catalog.store import Catalog

WORK_BUILDS_LOG = "builds.jsonl"
"""The work area's build records (``flows/build.py``): the final record, with the commit's
and the whole build's seconds, which the builds table's copy (written in the commit) lacks."""
KEY_METRICS = ("reproj_rmse_px", "inlier_ratio", "registration_rmse_mm", "fit_residual_mm",
               "penetration_max_mm", "contact_agreement", "contact_coverage")
"""The ``qa_*`` metrics shown in the sessions table (all of them are in the plots)."""
THUMBNAILS = ("keypoints.png", "reprojection.png", "contact.png", "strip.png")
"""Pictures shown as thumbnails, in this order; ``contact.ply`` is a link."""
MAX_VERSIONS_PLOTTED = 50
"""Versions in the across-versions plots (the newest up to the report's)."""
STATUS_ORDER = {"failed": 0, "flagged": 1, "ok": 2}


@dataclass(frozen=True)
class SessionEntry:
    """One row of the sessions table."""

    session_id: str
    status: str
    """The row's status (ok, flagged, failed); "failed" for a build failure without a row."""
    row: dict[str, Any] | None
    """The version's ``sessions`` row; None for a failure with no row of its own."""
    build: dict[str, Any] | None
    """The build record's entry (``SessionReport``); None when this build did not see it."""
    reasons: tuple[str, ...]
    """Why it failed or was flagged: the error's lines, then the QA flags."""
    notes: tuple[str, ...]
    """QA notes and the build's notes (pictures not written, ...)."""
    pictures: dict[str, str]
    """File name to path relative to the catalog root, only files that exist."""
    unlisted: str = ""
    """Without ``build``: what the record says of it ("unchanged", the build's record counts
    such sessions without listing them; "unchanged, or not in this build" when it cannot
    tell); empty: not in this build."""

    @property
    def failed_here(self) -> bool:
        """Failed in the version, or in this build (keeping its previous rows)."""
        return self.status == "failed" or (self.build or {}).get("outcome") == "failed"

    @property
    def order(self) -> tuple[int, str]:
        return (0 if self.failed_here else STATUS_ORDER.get(self.status, 3), self.session_id)


@dataclass(frozen=True)
class ReportData:
    """What a report page shows (gathered by :func:`gather`, drawn by :func:`render`)."""

    catalog: str
    version: int
    version_row: dict[str, Any]
    record: dict[str, Any]
    """The build record (``BuildReport.record()``) of the build shown."""
    params: dict[str, Any]
    sessions: tuple[SessionEntry, ...]
    limits: dict[str, dict[str, float | None]]
    """Flag and fail limit per metric name, from the build's ``qa_metrics`` config."""
    versions: tuple[dict[str, Any], ...]
    """Every version of the catalog: version, time_utc, build_id, tags, rows_sessions."""
    medians: dict[str, dict[int, float]] = field(default_factory=dict)
    """Per metric name, its median over the sessions of each version (where readable)."""
    unreadable_versions: tuple[int, ...] = ()
    audit: dict[str, Any] | None = None
    """The audit of the build that made the version (``Catalog.audit``); None without one."""
    published_version: int | None = None
    """The version readers read by default (the newest published)."""


def _work_record(params: Mapping[str, Any], root: Path, build_id: str) -> dict | None:
    """The work area's record of ``build_id`` (with its full timings), if it is there."""
    log = Path(params.get("work") or root / "work") / WORK_BUILDS_LOG
    try:
        lines = log.read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return None
    for line in reversed(lines):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and rec.get("build_id") == build_id and not rec.get("error"):
            return rec
    return None


def _builds(cat: Catalog, version: int) -> dict[str, dict[str, Any]]:
    """The builds table at ``version`` by build id, parameters parsed."""
    out = {}
    for row in cat.table("builds", version).to_pylist():
        try:
            row["params"] = json.loads(row["parameters_json"])
        except (TypeError, json.JSONDecodeError):
            row["params"] = {}
        out[row["build_id"]] = row
    return out


def _existing(cat: Catalog, files: Mapping[str, str]) -> dict[str, str]:
    """The pictures of ``files`` (name to path under the root) that are there (none on an
    object store: the page and the export link local files)."""
    if not cat.layout.is_local:
        return {}
    root = cat.layout.root
    return {n: p for n, p in files.items()
            if Path(n).suffix in PICTURE_SUFFIXES and (root / p).is_file()}


def _legacy_pictures(cat: Catalog, session_id: str) -> dict[str, str]:
    """Pictures of a catalog written before they were kept per build
    (``pictures/<session>/keypoints.png``, overwritten by each build)."""
    if not cat.layout.is_local:
        return {}
    folder = cat.layout.pictures_root / path_name(session_id)
    return _existing(cat, {n: f"pictures/{path_name(session_id)}/{n}"
                           for n in ("keypoints.png", "contact.png")}) if folder.is_dir() else {}


def _unlisted(record: Mapping[str, Any], builds: Mapping[str, dict], bare: list[str]
              ) -> dict[str, str]:
    """What the record says of the sessions it does not list (``bare``): the unchanged ones
    it counts (``unlisted``), by the builds row of the build when it made a version, else all
    of them when there are as many as it counts."""
    n = (record.get("unlisted") or {}).get("sessions") or 0
    if not n:
        return {}
    row = builds.get(record.get("build_id") or "")
    if row is not None:
        same = set(row.get("sessions_unchanged") or ())
        return {sid: "unchanged" for sid in bare if sid in same}
    sure = len(bare) == n
    return {sid: "unchanged" if sure else "unchanged, or not in this build" for sid in bare}


def _count(ids: Any) -> int:
    """A record's ``summary`` entry as a number: its count (a record's unchanged sessions),
    else the length of its ids."""
    return ids if isinstance(ids, int) else len(ids or ())


def _limits(params: Mapping[str, Any]) -> dict[str, dict[str, float | None]]:
    config = (params.get("configs") or {}).get("qa_metrics") or {}
    return {name: {"flag": b.get("flag"), "fail": b.get("fail")}
            for name, b in config.items() if isinstance(b, dict) and name in QA_BY_NAME}


def _medians(cat: Catalog, versions: list[int]) -> tuple[dict[str, dict[int, float]], list[int]]:
    names = [m.name for m in qa_columns()]
    out: dict[str, dict[int, float]] = {n: {} for n in names}
    unreadable = []
    for v in versions:
        try:
            table = cat.table("sessions", v)
        except Exception:  # noqa: BLE001 - a vacuumed or damaged version: said on the page
            unreadable.append(v)
            continue
        for n in names:
            if f"qa_{n}" in table.column_names:
                values = [x for x in table[f"qa_{n}"].to_pylist()
                          if x is not None and math.isfinite(x)]
                if values:
                    out[n][v] = float(statistics.median(values))
    return out, unreadable


def gather(cat: Catalog, version: int | str | None = None, record: dict | None = None
           ) -> ReportData:
    """Everything the page of ``version`` shows (default: the newest published). ``record``:
    the build record to show (a build passes its own; a build that made no version shows the
    version it left); by default the record of the build that made the version."""
    v = cat.resolve(version)
    versions = cat.versions().to_pylist()
    vrow = next(r for r in versions if r["version"] == v)
    builds = _builds(cat, v)
    made = builds.get(vrow["build_id"], {})
    params = dict(made.get("params") or {})
    if record is None:
        record = (_work_record(params, cat.layout.root, vrow["build_id"])
                  or params.get("report") or {"build_id": vrow["build_id"], "sessions": []})
    else:
        params = dict(record.get("parameters") or {}) or params
    params.pop("report", None)
    params.setdefault("code_version", made.get("code_version"))
    params.setdefault("config_digest", made.get("config_digest"))
    in_build: dict[str, list[dict]] = {}
    for s in record.get("sessions", []):
        in_build.setdefault(s["session_id"], []).append(s)
    entries = []
    rows = {r["session_id"]: r for r in cat.table("sessions", v).to_pylist()}
    unlisted = _unlisted(record, builds, [sid for sid in rows if sid not in in_build])
    for sid, row in rows.items():
        mine = in_build.get(sid, [])
        build = mine[0] if mine else None  # later folders with the id: duplicates (below)
        files = (build or {}).get("pictures") or {}
        if not files:  # a session this build did not see: the build that wrote its row
            writer = builds.get(row.get("build_id") or "", {}).get("params", {}).get("report")
            for s in (writer or {}).get("sessions", []):
                if s["session_id"] == sid and s.get("pictures"):
                    files = s["pictures"]
        pictures = _existing(cat, files) or _legacy_pictures(cat, sid)
        reasons = [ln for ln in (row.get("error") or "").splitlines() if ln.strip()]
        if build and build.get("outcome") == "failed" and row.get("status") != "failed":
            reasons.insert(0, f"failed in this build (its previous rows are kept): "
                              f"{build.get('error')}")
        reasons += [f for f in row.get("qa_flags") or () if f not in reasons]
        notes = list(row.get("qa_notes") or ()) + list((build or {}).get("notes") or ())
        entries.append(SessionEntry(sid, row["status"], row, build, tuple(reasons),
                                    tuple(notes), pictures, unlisted.get(sid, "")))
    for sid, mine in in_build.items():  # failures without a row of their own: folders
        for s in mine if sid not in rows else mine[1:]:  # reusing an id, or no row written
            if s.get("outcome") == "failed":
                entries.append(SessionEntry(sid, "failed", None, s, (s.get("error") or "",),
                                            tuple(s.get("notes") or ()), {}))
    entries.sort(key=lambda e: e.order)
    plotted = sorted(r["version"] for r in versions if r["version"] <= v)[-MAX_VERSIONS_PLOTTED:]
    medians, unreadable = _medians(cat, plotted)
    return ReportData(cat.layout.uri, v, vrow, record, params, tuple(entries), _limits(params),
                      tuple(versions), medians, tuple(unreadable), cat.audit(v),
                      cat.published_version())


STYLE = """
.audit{margin:12px 0;padding:8px;border:1px solid #ddd;background:#fff}
.audit.bad{border-color:#c33;background:#fff3f3}.audit.ok{border-color:#3a3}
body{font:14px/1.4 system-ui,sans-serif;margin:24px;color:#222;background:#fafafa}
h1{font-size:22px;margin:0 0 4px}h2{font-size:18px;margin:28px 0 8px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;background:#fff}td,th{border:1px solid #ddd;padding:4px 6px;
vertical-align:top;text-align:left}th{background:#eee}.muted{color:#777}
.cards{display:flex;gap:12px;flex-wrap:wrap}.card{background:#fff;border:1px solid #ddd;
padding:8px 12px;min-width:120px}.card b{font-size:20px;display:block}
.status{font-weight:bold;padding:1px 6px;border-radius:3px;color:#fff}
.status-ok{background:#2ca02c}.status-flagged{background:#ff9f1a}.status-failed{background:#d62728}
tr.failed{background:#fdecea}tr.flagged{background:#fff6e5}
td.fail{background:#f8c9c5}td.flag{background:#ffe2b3}
ul.reasons{margin:0;padding-left:16px}ul.reasons li.reason{color:#a00}
ul.reasons li.note{color:#555}
img.thumb{height:90px;border:1px solid #ccc;margin:2px}.plots{display:flex;flex-wrap:wrap;
gap:10px}svg.plot{background:#fff;border:1px solid #ddd;font-size:10px}
svg .ptitle{font-size:11px;font-weight:bold}code{font-size:12px}
"""


def _anchor(session_id: str) -> str:
    return "s-" + path_name(session_id)


def _session_row(e: SessionEntry, limits: Mapping[str, Mapping[str, float | None]],
                 href: Callable[[str], str]) -> str:
    row = e.row or {}
    status = "failed" if e.failed_here else e.status
    labels = " / ".join(str(row.get(k) or "–") for k in ("object_id", "participant", "intent",
                                                         "hand")) if row else "no row"
    b = e.build or {}
    outcome = (f"{_e(b.get('outcome'))}<br><span class=muted>{len(b.get('ran') or ())} ran, "
               f"{len(b.get('cached') or ())} cached</span>" if b else
               f'<span class=muted>{_e(e.unlisted or "not in this build")}</span>')
    items = [f'<li class="reason">{_e(r)}</li>' for r in e.reasons]
    items += [f'<li class="note">note: {_e(n)}</li>' for n in e.notes]
    reasons = f'<ul class="reasons">{"".join(items)}</ul>' if items else ""
    cells = []
    for name in KEY_METRICS:
        m = QA_BY_NAME[name]
        value = row.get(f"qa_{name}")
        level = _level(m, value, limits.get(name, {}))
        cells.append(f'<td class="metric {level}" data-metric="{name}">{_num(value)}</td>')
    thumbs = "".join(
        f'<a href="{_e(href(e.pictures[n]))}"><img class="thumb" loading="lazy" alt="{_e(n)}" '
        f'title="{_e(n)}" src="{_e(href(e.pictures[n]))}"></a>'
        for n in THUMBNAILS if n in e.pictures)
    if "contact.ply" in e.pictures:
        thumbs += (f'<br><a class="mesh" href="{_e(href(e.pictures["contact.ply"]))}">contact '
                   'mesh (PLY, vertex colours: open in MeshLab, Blender, ...)</a>')
    where = f"<br><span class=muted>{_e(b['session_dir'])}</span>" if b.get(
        "session_dir") else ""
    return (f'<tr id="{_e(_anchor(e.session_id))}" class="session {status}" '
            f'data-session="{_e(e.session_id)}" data-status="{_e(status)}">'
            f'<td><b>{_e(e.session_id)}</b>{where}</td><td>{_e(labels)}</td>'
            f'<td><span class="status status-{_e(status)}">{_e(status)}</span></td>'
            f'<td>{outcome}</td><td>{reasons}</td>{"".join(cells)}'
            f'<td>{thumbs or "<span class=muted>no pictures</span>"}</td></tr>')


def _publication_html(data: ReportData) -> str:
    """The version's state and its audit (write-audit-publish): a box above the lineage."""
    state = data.version_row.get("state") or "published"
    audit = data.audit
    readers = (f"readers read version {data.published_version} by default"
               if data.published_version is not None else "no version is published")
    if audit is None:
        verdict = "committed without an audit"
    else:
        against = (f" against published version {audit['compared_to']}"
                   if audit.get("compared_to") is not None else "")
        verdict = ("audit passed" if audit["passed"] else "audit FAILED") + against
    cls = "ok" if state == "published" else "bad"
    out = [f'<div class="audit {cls}" id="audit"><b>{_e(state)}</b>: {_e(verdict)}; '
           f"{_e(readers)}"]
    if audit and audit.get("reasons"):
        out.append("<ul>" + "".join(f"<li>{_e(r)}</li>" for r in audit["reasons"]) + "</ul>")
    if state == "staged":
        out.append(f"<div>publish it: <code>graspcap catalog publish {data.version}</code>; "
                   f"reject it: <code>graspcap catalog reject {data.version}</code></div>")
    if audit:
        shown = {"measured": audit.get("measured"), "gates": audit.get("gates")}
        out.append("<details><summary>measured and gates</summary><pre>"
                   f"{_e(json.dumps(shown, indent=1, sort_keys=True))}</pre></details>")
    return "".join(out) + "</div>"


def _table(rows: list[tuple[str, Any]]) -> str:
    return "<table>" + "".join(f"<tr><th>{_e(k)}</th><td>{v}</td></tr>" for k, v in rows) + \
        "</table>"


def render(data: ReportData, href: Callable[[str], str],
           version_link: Callable[[dict], str | None] = lambda row: None) -> str:
    """The page of ``data`` as HTML. ``href`` turns a picture's path under the catalog root
    into the link the page uses; ``version_link`` gives the link to a version's report (None:
    no link)."""
    rec, p, v = data.record, data.params, data.version
    made = rec.get("catalog_version")
    statuses = [("failed" if e.failed_here else e.status) for e in data.sessions]
    summary = rec.get("summary") or {}
    unlisted = rec.get("unlisted") or {}  # unchanged sessions counted, not listed
    seconds = rec.get("seconds") or {}
    cards = [("sessions", len({e.session_id for e in data.sessions})),
             ("ok", statuses.count("ok")), ("flagged", statuses.count("flagged")),
             ("failed", statuses.count("failed")),
             ("stage runs", sum(len(s.get("ran") or ()) for s in rec.get("sessions", []))),
             ("cache hits", sum(len(s.get("cached") or ()) for s in rec.get("sessions", []))
              + sum((unlisted.get("cached") or {}).values())),
             ("build time", f"{seconds['total']:.1f} s" if "total" in seconds else "–")]
    head = (f"version {v}" if made == v else
            f"build {rec.get('build_id')}: no new version; version {v} shown")
    out = ["<!DOCTYPE html><html lang=en><head><meta charset=utf-8>",
           f"<title>graspcap report: {_e(data.catalog)} version {v}</title>",
           f"<style>{STYLE}</style></head><body>",
           f"<h1>graspcap build report: {_e(head)}</h1>",
           f'<div class=muted>catalog {_e(data.catalog)} · build {_e(rec.get("build_id"))} · '
           f'page written {datetime.now(UTC).isoformat(timespec="seconds")}</div>',
           '<div class="cards">' + "".join(f'<div class="card"><b>{_e(val)}</b>{_e(k)}</div>'
                                           for k, val in cards) + "</div>",
           _publication_html(data)]
    # lineage and parameters
    out.append("<h2>Build and lineage</h2>")
    configs = p.get("configs") or {}
    out.append(_table([
        ("build", _e(rec.get("build_id"))),
        ("made version", _e(made) if made is not None else "none (nothing changed)"),
        ("previous version", _e(rec.get("previous_version") or "none")),
        ("version committed", _e(data.version_row.get("time_utc"))),
        ("tags", _e(", ".join(data.version_row.get("tags") or ()) or "–")),
        ("state", _e(data.version_row.get("state") or "–")),
        ("readers' default", _e(data.published_version or "none (no version published)")),
        ("code version", _e(p.get("code_version") or "–")),
        ("config digest", f'<code>{_e(p.get("config_digest") or "–")}</code>'),
        ("preset", _e(p.get("preset", "–"))),
        ("session roots", "<br>".join(_e(r) for r in p.get("roots", ())) or "–"),
        ("retry failed only", _e(p.get("retry_failed", "–"))),
        ("outcome", _e(", ".join(f"{_count(summary.get(k))} {k}" for k in
                                 ("added", "changed", "unchanged", "failed")))),
        ("not sessions (skipped)", "<br>".join(_e(x) for x in p.get("not_sessions", ()))
         or "–"),
        ("stage configs", f"<details><summary>{len(configs)} stages</summary><pre>"
                          f"{_e(json.dumps(configs, indent=1, sort_keys=True))}</pre></details>"),
    ]))
    out.append("<h3>Timings</h3>" + _table([(k, f"{x:.2f} s") for k, x in seconds.items()])
               if seconds else "")
    stages: dict[str, list[int]] = {}
    for s in rec.get("sessions", []):
        for i, key in enumerate(("ran", "cached", "not_run")):
            for st in s.get(key) or ():
                stages.setdefault(st, [0, 0, 0, 0])[i] += 1
        for st, n in (s.get("retries") or {}).items():
            stages.setdefault(st, [0, 0, 0, 0])[3] += n
    for st, n in (unlisted.get("cached") or {}).items():
        stages.setdefault(st, [0, 0, 0, 0])[1] += n
    if stages:
        out.append("<h3>Stages</h3><table><tr><th>stage</th><th>ran</th><th>cached</th>"
                   "<th>not run</th><th>retries</th></tr>" + "".join(
                       f"<tr><td>{_e(st)}</td>" + "".join(f"<td>{n}</td>" for n in c) + "</tr>"
                       for st, c in stages.items()) + "</table>")
    out.append("<h3>Versions</h3><table><tr><th>version</th><th>committed</th><th>build</th>"
               "<th>state</th><th>tags</th><th>sessions</th><th>report</th></tr>")
    for row in sorted(data.versions, key=lambda r: -r["version"]):
        link = version_link(row)
        mark = " (this page)" if row["version"] == v else ""
        out.append(f'<tr class="version"><td>{row["version"]}{mark}</td>'
                   f'<td>{_e(row["time_utc"])}</td><td>{_e(row["build_id"])}</td>'
                   f'<td>{_e(row.get("state") or "–")}</td>'
                   f'<td>{_e(", ".join(row.get("tags") or ()))}</td>'
                   f'<td>{_e(row.get("rows_sessions"))}</td><td>'
                   + (f'<a href="{_e(link)}">report</a>' if link else "–") + "</td></tr>")
    out.append("</table>")
    # sessions
    out.append(f"<h2>Sessions of version {v}</h2><p class=muted>Failed first (with their "
               "reasons), then flagged, then ok. Metric cells: amber beyond the flag limit, "
               "red beyond the fail limit of this build's <code>qa_metrics</code> config. "
               "Click a thumbnail for the full picture.</p>")
    heads = "".join(f'<th title="{_e(QA_BY_NAME[n].label)}">{_e(n)}</th>' for n in KEY_METRICS)
    out.append(f'<table id="sessions"><tr><th>session</th><th>object / participant / '
               f'intent / hand</th><th>status</th><th>this build</th><th>reasons and notes'
               f'</th>{heads}<th>pictures</th></tr>')
    out += [_session_row(e, data.limits, href) for e in data.sessions]
    out.append("</table>")
    # plots
    out.append(f"<h2>QA metrics across the sessions of version {v}</h2><p class=muted>Dashed: "
               "this build's flag (amber) and fail (red) limits.</p><div class=plots>")
    for m in qa_columns():
        values = [e.row[m.column] for e in data.sessions if e.row is not None
                  and e.row.get(m.column) is not None and math.isfinite(e.row[m.column])]
        out.append(histogram_svg(m, values, data.limits.get(m.name, {})))
    out.append("</div>")
    out.append("<h2>QA metrics across versions</h2><p class=muted>Median over each version's "
               "sessions (the ringed point is this page's version)"
               + (f"; versions {', '.join(map(str, data.unreadable_versions))} can no longer "
                  "be read (vacuumed)" if data.unreadable_versions else "")
               + ".</p><div class=plots>")
    for m in qa_columns():
        out.append(versions_svg(m, data.medians.get(m.name, {}), v,
                                data.limits.get(m.name, {})))
    out.append("</div></body></html>\n")
    return "\n".join(out)


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_report(cat: Catalog, version: int | str | None = None,
                 record: dict | None = None) -> Path:
    """Write the report page of ``version`` (default: the newest published) to
    ``reports/<build_id>/index.html`` of the catalog and return its path; ``record`` (a
    build's own record) names the build, else the build that made the version."""
    cat.layout.require_local("writing a report page")
    data = gather(cat, version, record)
    page = cat.layout.report_file(data.record.get("build_id") or data.version_row["build_id"])
    up = os.path.relpath(cat.layout.root, page.parent)

    def href(rel: str) -> str:
        return f"{up}/{rel}"

    def version_link(row: dict) -> str | None:
        other = cat.layout.report_file(row["build_id"])
        return os.path.relpath(other, page.parent) if other.is_file() or other == page else None

    _write_atomic(page, render(data, href, version_link))
    return page


__all__ = ["ReportData", "SessionEntry", "gather", "histogram_svg", "render", "versions_svg",
           "write_report"]
