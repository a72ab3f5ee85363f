"""`graspcap catalog versions|show|diff|tag|publish|reject|optimize|remove|export|vacuum|verify|
migrate` on the command line.

``add_catalog_parser(subparsers, vacuum_work)`` adds the ``catalog`` command to graspcap's
parser. Every subcommand takes ``--catalog`` (default ``DEFAULT_CATALOG``; a path or URL;
before or after the subcommand's name), prints text for a person or ``--json`` for a
script, and exits 2 with the catalog's message on a catalog error (missing version or tag,
older format, a damaged file: one line per problem, never a traceback). Prefect-free, like
every catalog reader.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from deltalake.exceptions import DeltaError

from graspcap.catalog.card import DEFAULT_LICENCE
from graspcap.catalog.errors import CatalogError
from graspcap.catalog.layout import DEFAULT_CATALOG
from graspcap.catalog.lerobot import DEFAULT_FPS
from graspcap.schemas.tables import DATA_TABLES


def _open(args: argparse.Namespace):
    from graspcap.catalog.store import open as open_catalog

    return open_catalog(args.catalog)


def _version_arg(text: str | None) -> int | str | None:
    """A version number, a tag, or None (latest)."""
    if text is None:
        return None
    return int(text) if text.isdigit() else text


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0 or not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, indent=2, sort_keys=True, default=str))


def _plain(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 6)
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


QA_TEXT_COLUMNS = ("qa_flags", "qa_notes")
"""``sessions`` columns of QA's reasons (lists of strings, format 4), shown by ``show``."""


def _with_any(column: pa.ChunkedArray) -> int:
    """Rows whose list is non-empty (null and empty lists count as none)."""
    return int(pc.sum(pc.fill_null(pc.greater(pc.list_value_length(column), 0), False)).as_py()
               or 0)


def several_meshes(sessions: pa.Table) -> dict[str, dict[str, list[str]]]:
    """``{object_id: {mesh digest: [session ids]}}`` of the object ids whose sessions carry
    more than one object mesh (allowed: each session brings its own; worth a look)."""
    by_object: dict[str, dict[str, list[str]]] = {}
    for r in sessions.select(["session_id", "object_id", "object_mesh_digest"]).to_pylist():
        if r["object_mesh_digest"]:
            by_object.setdefault(r["object_id"], {}).setdefault(
                r["object_mesh_digest"], []).append(r["session_id"])
    return {o: {d: sorted(s) for d, s in sorted(m.items())}
            for o, m in sorted(by_object.items()) if len(m) > 1}


def summary(cat, version: int | str | None = None) -> dict:
    """A version's summary: number, build, tags, row counts, status counts, QA medians, how
    many sessions have QA flag reasons and notes, and the object ids with several meshes."""
    v = cat.resolve(version)
    info = next(r for r in cat.versions().to_pylist() if r["version"] == v)
    sessions = cat.table("sessions", v)
    build = [r for r in cat.table("builds", v).to_pylist() if r["catalog_version"] == v]
    status = sessions.group_by("status").aggregate([([], "count_all")]).to_pylist()
    qa = {}
    for field in sessions.schema:
        if field.name.startswith("qa_") and pa.types.is_floating(field.type):
            values = sessions[field.name].drop_null().to_numpy()
            values = values[np.isfinite(values)]
            qa[field.name] = float(np.median(values)) if len(values) else None
    return {
        "version": v, "time_utc": info["time_utc"].isoformat(), "build_id": info["build_id"],
        "tags": info["tags"], "format_version": info["format_version"],
        "state": info["state"], "published_version": cat.published_version(),
        "audit": cat.audit(v),
        "rows": {name: info[f"rows_{name}"] for name in DATA_TABLES},
        "status": {r["status"]: r["count_all"] for r in status},
        "qa_median": qa,
        "sessions_with": {c: _with_any(sessions[c]) for c in QA_TEXT_COLUMNS},
        "objects_with_several_meshes": several_meshes(sessions),
        "build": None if not build else {
            k: build[0][k] for k in ("build_id", "code_version", "config_digest")} | {
            k: len(build[0][k]) for k in ("sessions_added", "sessions_changed",
                                          "sessions_unchanged", "sessions_removed",
                                          "sessions_failed")},
    }


def report_problems(cat, command: str) -> int:
    """Print the catalog's problems (``Catalog.problems``) one a line; 2 when there are any."""
    problems = cat.problems()
    for line in problems:
        print(f"{command}: {line}", file=sys.stderr)
    return 2 if problems else 0


def _cmd_versions(args: argparse.Namespace) -> int:
    cat = _open(args)
    code = _listed_versions(args, cat)
    return code or report_problems(cat, "graspcap catalog versions")


def _listed_versions(args: argparse.Namespace, cat) -> int:
    from graspcap.catalog.vacuum import vacuumed_versions

    table = cat.versions()
    gone = vacuumed_versions(cat.layout) if cat.layout.is_local else {}
    rows = [{"version": r["version"], "time_utc": r["time_utc"].isoformat(timespec="seconds"),
             "build_id": r["build_id"], "tags": r["tags"], "format": r["format_version"],
             "state": r["state"],
             "readable": r["version"] not in gone, "vacuumed_utc": gone.get(r["version"]),
             **{f"rows_{n}": r[f"rows_{n}"] for n in DATA_TABLES}} for r in table.to_pylist()]
    if args.json:
        _print_json(rows)
        return 0
    if not rows:
        print(f"catalog {args.catalog}: no versions yet")
        return 0
    published = cat.published_version()
    print(f"{'version':>7}  {'committed (UTC)':<25}  {'build':<24} {'state':<10} {'sessions':>8} "
          f"{'frames':>9}  tags")
    for r in rows:
        gone = ("" if r["readable"] else
                f"  [vacuumed {r['vacuumed_utc']}: can no longer be read]")
        mark = "  <- readers' default" if r["version"] == published else ""
        print(f"{r['version']:>7}  {r['time_utc']:<25}  {r['build_id']:<24} {r['state']:<10} "
              f"{r['rows_sessions']:>8} {r['rows_frames']:>9}  {', '.join(r['tags'])}{gone}"
              f"{mark}")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    cat = _open(args)
    version = _version_arg(args.version)
    if args.session is None:
        out = summary(cat, version)
        if args.json:
            _print_json(out)
            return 0
        print(f"version {out['version']}  build {out['build_id']}  committed "
              f"{out['time_utc']}  format {out['format_version']}  tags "
              f"{', '.join(out['tags']) or '-'}")
        print(f"state:  {out['state']}" + (" (readers' default)"
                                            if out["published_version"] == out["version"]
                                            else f" (readers' default: version "
                                            f"{out['published_version']})"))
        print("audit:  " + audit_line(out["audit"]))
        for reason in (out["audit"] or {}).get("reasons", []):
            print(f"        {reason}")
        print("rows:   " + ", ".join(f"{k} {v}" for k, v in out["rows"].items()))
        print("status: " + ", ".join(f"{k} {v}" for k, v in sorted(out["status"].items())))
        if out["build"]:
            b = out["build"]
            print(f"build:  code {b['code_version']}, config {b['config_digest'][:12]}, added "
                  f"{b['sessions_added']}, changed {b['sessions_changed']}, unchanged "
                  f"{b['sessions_unchanged']}, removed {b['sessions_removed']}, failed "
                  f"{b['sessions_failed']}")
        w = out["sessions_with"]
        print(f"QA:     {w['qa_flags']} session(s) with flag reasons, {w['qa_notes']} with "
              "notes (show --session ID lists them)")
        for obj, meshes in out["objects_with_several_meshes"].items():
            print(f"meshes: object {obj!r} has {len(meshes)} different meshes (each session "
                  "keeps its own): " + "; ".join(f"{d[:12]}: {', '.join(s)}"
                                                 for d, s in meshes.items()))
        print("QA medians:")
        for k, v in out["qa_median"].items():
            print(f"  {k:<26} {'-' if v is None else f'{v:.4g}'}")
        return 0
    v = cat.resolve(version)
    sessions = cat.table("sessions", v)
    row = sessions.filter(pc.equal(sessions["session_id"], args.session)).to_pylist()
    if not row:
        print(f"session {args.session!r} is not in catalog version {v}", file=sys.stderr)
        return 2
    if args.json:
        _print_json({"version": v, **row[0]})
        return 0
    print(f"session {args.session} in catalog version {v}")
    first = ("session_id", "participant", "object_id", "intent", "hand", "status", "error",
             *QA_TEXT_COLUMNS)  # why a session is flagged, next to its status
    for k in [*first, *(k for k in row[0] if k not in first)]:
        value = row[0][k]
        if k in QA_TEXT_COLUMNS:  # one reason a line; "-": none, "null": QA did not run
            lines = ["null"] if value is None else (value or ["-"])
            print(f"  {k:<26} " + ("\n" + " " * 29).join(lines))
        else:
            print(f"  {k:<26} {_plain(value)}")
    return 0


def _cmd_diff(args: argparse.Namespace) -> int:
    d = _open(args).diff(_version_arg(args.a), _version_arg(args.b))
    if args.json:
        _print_json(d)
        return 0
    print(f"added ({len(d['added'])}): {', '.join(d['added']) or '-'}")
    print(f"removed ({len(d['removed'])}): {', '.join(d['removed']) or '-'}")
    print(f"changed ({len(d['changed'])}):")
    for sid, cols in sorted(d["changed"].items()):
        print(f"  {sid}: {', '.join(cols)}")
    return 0


def _cmd_tag(args: argparse.Namespace) -> int:
    cat = _open(args)
    v = cat.resolve(_version_arg(args.version))
    before = cat.tags().get(args.name)
    if not cat.tag(v, args.name, force=args.force):
        print(f"tag {args.name} -> version {v} (already)")
    elif before is not None:
        print(f"tag {args.name} -> version {v} (moved from version {before})")
    else:
        print(f"tag {args.name} -> version {v}")
    return 0


def audit_line(audit: dict | None) -> str:
    """One line on a version's audit (``Catalog.audit``)."""
    if audit is None:
        return "none (committed without an audit)"
    against = (f" against published version {audit['compared_to']}"
               if audit["compared_to"] is not None else " (no published version before)")
    if audit["passed"]:
        return "passed" + against
    return f"FAILED{against}: {len(audit['reasons'])} gate(s)"


def _cmd_publish(args: argparse.Namespace) -> int:
    cat = _open(args)
    v = cat.resolve(_version_arg(args.version))
    changed = cat.publish(v, args.reason or "")
    print(f"version {v} {'published' if changed else 'was already published'}; readers' "
          f"default is version {cat.published_version()}")
    return 0


def _cmd_reject(args: argparse.Namespace) -> int:
    cat = _open(args)
    v = cat.resolve(_version_arg(args.version))
    changed = cat.reject(v, args.reason or "")
    readers = cat.published_version()
    base = cat.base_version()
    print(f"version {v} {'rejected' if changed else 'was already rejected'}; readers' default "
          f"is {'version ' + str(readers) if readers is not None else 'no version'}; the next "
          f"build is written on top of {'version ' + str(base) if base else 'an empty catalog'}")
    return 0


def _cmd_optimize(args: argparse.Namespace) -> int:
    from graspcap.catalog.optimize import optimize_catalog

    print(optimize_catalog(_open(args)).text())
    return 0


def _cmd_remove(args: argparse.Namespace) -> int:
    cat = _open(args)
    v = cat.remove(args.sessions, args.reason or "")
    ids = sorted(set(args.sessions))
    print(f"removed {len(ids)} session(s) ({', '.join(ids)}) in new version {v}"
          + (f"; reason: {args.reason}" if args.reason else "")
          + f"; versions before {v} still hold them")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from graspcap.catalog.export import export_version

    report = export_version(_open(args), _version_arg(args.version), args.out, args.format,
                            licence=args.licence, fps=args.fps)
    print(f"exported version {report.version} to {report.out} ({report.bytes / 1e6:.2f} MB): "
          + ", ".join(f"{k} {v}" for k, v in report.rows.items()))
    return 0


def _cmd_vacuum(args: argparse.Namespace) -> int:
    if args.keep is None and not args.work:
        print("graspcap catalog vacuum: say what to delete: --keep N (table files and arrays "
              "of older versions), --work (cached stage results), or both", file=sys.stderr)
        return 2
    cat = _open(args)
    if args.keep is not None:
        print(cat.vacuum(args.keep).text(args.keep))
    if args.work:
        cat.layout.require_local("cleaning a work area")
        print(args.vacuum_work(cat.layout.root / "work").text())
    return 0


def _cmd_repair(args: argparse.Namespace) -> int:
    from graspcap.catalog.repair import main

    return main([args.catalog])


def _cmd_migrate(args: argparse.Namespace) -> int:
    from graspcap.catalog.migrate import migrate_catalog

    path = args.path if args.path is not None else args.catalog
    r = migrate_catalog(path, args.out)
    if r.from_format == r.to_format:
        print(f"{r.root} is already format {r.to_format}; nothing to do")
    else:
        made = f"; new version {r.new_version} pins the upgraded tables" if r.new_version else ""
        print(f"migrated {r.root} from format {r.from_format} to {r.to_format}{made}")
        for digest, problem in sorted(r.damaged_arrays.items()):
            print(f"  array group {digest} left as it was: {problem} (`graspcap catalog "
                  "verify` names the sessions using it)")
    return 0


VERIFY_DAMAGED = 1
"""Exit status of ``catalog verify`` when something the version needs is missing or altered
(2, as for every subcommand, when the catalog or version cannot be opened at all)."""


def _cmd_verify(args: argparse.Namespace) -> int:
    from graspcap.catalog.verify import verify_version

    report = verify_version(_open(args), _version_arg(args.version))
    if args.json:
        _print_json(report.as_dict())
        return 0 if report.ok else VERIFY_DAMAGED
    files = sum(report.table_files.values())
    checked = f"{files} table file(s) and {report.arrays} array group(s)"
    if report.ok:
        print(f"version {report.version}: {checked} checked, nothing damaged")
        return 0
    print(f"version {report.version}: {checked} checked, {len(report.damaged)} damaged:")
    for d in report.damaged:
        print(f"  {d.line()}")
    return VERIFY_DAMAGED


def problem_lines(exc: BaseException) -> list[str]:
    """One line per problem of a catalog error (a Rust backtrace or a traceback never)."""
    if isinstance(exc, DeltaError):  # deltalake's text ends in a Rust backtrace
        return [(str(exc).strip().splitlines() or [type(exc).__name__])[0]]
    return [line for line in str(exc).splitlines() if line.strip()] or [type(exc).__name__]


def _guard(func):
    def run(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except BrokenPipeError:
            raise  # the reader went away: graspcap's main() ends quietly
        except (CatalogError, ValueError, OSError, DeltaError) as exc:
            for line in problem_lines(exc):
                print(f"graspcap catalog {args.catalog_command}: {line}", file=sys.stderr)
            return 2
    return run


def add_catalog_parser(subparsers: argparse._SubParsersAction,
                       vacuum_work: Callable[[Path], Any]) -> argparse.ArgumentParser:
    """Add ``catalog`` and its subcommands to graspcap's ``subparsers``; ``vacuum_work`` (the
    work area is the builder's, above the catalog: ``flows.work_vacuum.vacuum_work``) cleans
    a work area for ``vacuum --work``."""
    catalog_help = (f"catalog folder or URL (file://, s3://, ... read-only; default "
                    f"{DEFAULT_CATALOG}); before or after the subcommand")
    # --catalog before the subcommand (`catalog --catalog X versions`) or after it: the
    # subcommands' copy has no default, so it only overrides the group's when given
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--catalog", default=argparse.SUPPRESS, help=catalog_help)
    as_json = argparse.ArgumentParser(add_help=False)
    as_json.add_argument("--json", action="store_true", help="print JSON")
    parser = subparsers.add_parser("catalog", help="list, show, compare, tag, export, vacuum, "
                                   "verify, repair, migrate catalog versions and remove "
                                   "sessions")
    parser.add_argument("--catalog", default=str(DEFAULT_CATALOG), help=catalog_help)
    sub = parser.add_subparsers(dest="catalog_command", required=True)

    p = sub.add_parser("versions", parents=[common, as_json], help="every version")
    p.set_defaults(func=_guard(_cmd_versions))
    p = sub.add_parser("show", parents=[common, as_json],
                       help="a version's summary, or one session's row")
    p.add_argument("version", nargs="?",
                   help="version number or tag (default: the newest published)")
    p.add_argument("--session", help="print this session's row instead")
    p.set_defaults(func=_guard(_cmd_show))
    p = sub.add_parser("diff", parents=[common, as_json],
                       help="sessions added, removed and changed (with columns) from A to B")
    p.add_argument("a", help="version number or tag")
    p.add_argument("b", help="version number or tag")
    p.set_defaults(func=_guard(_cmd_diff))
    p = sub.add_parser("tag", parents=[common], help="point a tag at a version")
    p.add_argument("version", help="version number (or a tag to copy)")
    p.add_argument("name", help="tag name: a letter, then letters, digits, '.', '_', '-'")
    p.add_argument("--force", action="store_true",
                   help="move the tag when it already points at another version")
    p.set_defaults(func=_guard(_cmd_tag))
    p = sub.add_parser("publish", parents=[common],
                       help="publish a version by hand: readers read the newest published "
                       "version by default")
    p.add_argument("version", help="version number (or tag)")
    p.add_argument("--reason", help="why (recorded in the publications table)")
    p.set_defaults(func=_guard(_cmd_publish))
    p = sub.add_parser("reject", parents=[common],
                       help="reject a version: no reader's default, and the next build is "
                       "written on top of the newest version not rejected")
    p.add_argument("version", help="version number (or tag)")
    p.add_argument("--reason", help="why (recorded in the publications table)")
    p.set_defaults(func=_guard(_cmd_reject))
    p = sub.add_parser("optimize", parents=[common],
                       help="compact the newest version's table files into a new version "
                       "(same rows) and checkpoint the Delta logs; older versions unchanged")
    p.set_defaults(func=_guard(_cmd_optimize))
    p = sub.add_parser("remove", parents=[common],
                       help="a new version without these sessions (older versions keep them)")
    p.add_argument("sessions", nargs="+", metavar="SESSION", help="session ids to remove")
    p.add_argument("--reason", help="why (recorded in the new version's builds row)")
    p.set_defaults(func=_guard(_cmd_remove))
    p = sub.add_parser("export", parents=[common],
                       help="a version as plain Parquet (or CSV) files with its arrays, a "
                       "dataset card (README.md) and normalisation statistics (stats.json); "
                       "or as a LeRobot v3.0-style dataset (--format lerobot)")
    p.add_argument("version", nargs="?",
                   help="version number or tag (default: the newest published)")
    p.add_argument("--out", required=True, help="new folder to write")
    p.add_argument("--format", choices=["parquet", "csv", "lerobot"], default="parquet",
                   help="parquet or csv: the catalog's tables and arrays; lerobot: "
                   "data/chunk-000/file-000.parquet + meta/ (docs/catalog.md)")
    p.add_argument("--licence", default=DEFAULT_LICENCE,
                   help=f"licence written into the card (default: {DEFAULT_LICENCE!r})")
    p.add_argument("--fps", type=_positive_float, default=DEFAULT_FPS,
                   help="frame rate of the grasp videos, for the LeRobot timestamps (the "
                   f"catalog does not record it; default {DEFAULT_FPS:g})")
    p.set_defaults(func=_guard(_cmd_export))
    p = sub.add_parser("vacuum", parents=[common],
                       help="delete files no kept version needs (newest N plus tagged), and "
                       "cached stage results no build needs (--work)")
    p.add_argument("--keep", type=int, help="newest versions to keep (>= 1); the others "
                   "stay listed, and those that lose a file can no longer be read")
    p.set_defaults(vacuum_work=vacuum_work)
    p.add_argument("--work", action="store_true",
                   help="also delete the work area's cached stage results that neither the "
                   "newest build used nor are a session's latest run (results of the last "
                   "hour stay)")
    p.set_defaults(func=_guard(_cmd_vacuum))
    p = sub.add_parser("verify", parents=[common, as_json],
                       help="check that every file a version needs exists and every array "
                       "matches its digest; exit 1 naming what is damaged")
    p.add_argument("version", nargs="?",
                   help="version number or tag (default: the newest published)")
    p.set_defaults(func=_guard(_cmd_verify))
    p = sub.add_parser("repair", parents=[common],
                       help="mend a damaged versions log (garbled entries moved aside, holes "
                       "filled, lost versions rows restored from their files)")
    p.set_defaults(func=_cmd_repair)
    p = sub.add_parser("migrate", parents=[common],
                       help="upgrade an older-format catalog to this graspcap's format")
    p.add_argument("path", nargs="?", help="the catalog (default: --catalog)")
    p.add_argument("--out", help="upgrade a copy in this new folder, leaving PATH as it is")
    p.set_defaults(func=_guard(_cmd_migrate))
    return parser


__all__ = ["add_catalog_parser", "problem_lines", "report_problems", "summary"]
