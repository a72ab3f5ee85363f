"""Command-line front end: a thin layer over the library functions.

Every default lives in the library's config models, not here.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from graspcap.catalog.cli import add_catalog_parser
from graspcap.catalog.layout import DEFAULT_CATALOG
from graspcap.detect_cli import add_detect_parser
from graspcap.tasks.core.presets import PIPELINE_PRESETS

STARTED = time.perf_counter()
"""When this module was imported: what ``graspcap build`` reports its wall time from where the
process's own start time cannot be read (``flows.commands.process_seconds``)."""


def _cmd_synth(args: argparse.Namespace) -> int:
    from graspcap.synth import generate

    t0 = time.perf_counter()
    dirs = generate(
        args.out,
        sessions=args.sessions,
        seed=args.seed,
        profile=args.profile,
        frames=args.frames,
        objects=args.object,
        workers=args.workers,
    )
    for d in dirs:
        print(d)
    print(f"wrote {len(dirs)} session(s) to {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0


EXIT_USAGE = 2
"""A usage error: argparse's code, and every check here that stops before anything is made."""
EXIT_BROKEN_PIPE = 141
"""The reader of the output closed it early (``graspcap catalog show | head``): 128 + SIGPIPE,
what a shell reports for a tool killed by it."""


def missing_roots(roots: Sequence[Path], command: str) -> bool:
    """Print one line naming each root that does not exist (a typo would otherwise build from
    the other roots, or from none, without a word); True when there was one."""
    missing = [r for r in roots if not Path(r).exists()]
    for root in missing:
        print(f"graspcap {command}: {str(root)!r} does not exist (no such file or folder); "
              "name folders that hold sessions", file=sys.stderr)
    return bool(missing)


def _cmd_validate(args: argparse.Namespace) -> int:
    if missing_roots(args.dirs, "validate"):
        return EXIT_USAGE
    from graspcap.tasks.session.discover import NOT_A_SESSION, discover
    from graspcap.tasks.session.load_session import validate_session

    found = discover(args.dirs)
    for folder in found.not_sessions:
        print(f"SKIP {_shown_path(folder)}: {NOT_A_SESSION}")
    if not found.sessions:
        print(f"no session.json found under {' '.join(map(str, args.dirs))}", file=sys.stderr)
        return 2
    failed = 0
    for directory in found.sessions:
        try:
            problems = validate_session(directory, check_images=not args.no_images)
        except Exception as exc:  # noqa: BLE001 - a validator bug must not stop the others
            failed += 1
            why = f"{type(exc).__name__}: {str(exc)[:200]}"
            print(f"FAIL {_shown_path(directory)}: the validator failed on it ({why}); "
                  "please report this as a bug")
            continue
        if any(p.severity == "error" for p in problems):  # frame-level ones do not fail it
            failed += 1
            print(f"FAIL {_shown_path(directory)}: {len(problems)} problem(s)")
        else:
            print(f"OK   {_shown_path(directory)}"
                  + (f" ({len(problems)} frame(s) skipped)" * bool(problems)))
        for p in problems:
            print(f"  - {p}")
    skipped = f", {len(found.not_sessions)} not a session" * bool(found.not_sessions)
    print(f"{len(found.sessions) - failed} ok, {failed} failed{skipped}")
    return 1 if failed else 0


def _shown_path(path: Path) -> str:
    """A folder for one output line: as is, or its repr when its name holds a control
    character (a newline in a folder name must not split the line)."""
    text = str(path)
    return text if text.isprintable() else repr(text)


def _cmd_demo(args: argparse.Namespace) -> int:
    from graspcap.demo import run_demo

    options = {k: getattr(args, k) for k in ("sessions", "frames", "seed")}
    return run_demo(args.out, **{k: v for k, v in options.items() if v is not None})


BUILD_EXIT_CODES = """exit status:
  0  every session built (or unchanged)
  1  some sessions failed: the others are committed in the new version (or were
     already); every failure is in the build record with its reason
  2  usage error: bad arguments, or no session.json under the roots
  3  the build failed as a whole (catalog lock, disk, commit) and committed
     nothing; completed stage results stay in the work area and the next build
     commits them without running those stages again
  4  the new version is committed but staged: its audit failed (or --stage);
     readers stay on the published version (graspcap catalog publish|reject)"""


def _dask_arg(text: str) -> str:
    """``--dask``: ``local:N`` with N >= 1 workers, or a scheduler's address (``host:port``,
    ``tcp://host:port``); checked here, before anything is made."""
    if text.startswith("local:"):
        n = text.removeprefix("local:")
        if not (n.isdigit() and int(n) >= 1):
            raise argparse.ArgumentTypeError(
                f"{text!r}: local:N needs a number of worker processes >= 1, e.g. local:2")
    elif ":" not in text:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a Dask scheduler's address (tcp://HOST:PORT or HOST:PORT) or "
            "local:N for a local cluster of N worker processes")
    return text


def _cmd_build(args: argparse.Namespace) -> int:
    if missing_roots(args.roots, "build"):  # before the catalog is made
        return EXIT_USAGE
    if args.verify is not None:
        from graspcap.flows.verify_cache import run_verify

        return run_verify(args.roots, args.catalog, args.verify, args.preset,
                          settings=args.settings)
    if args.plan:
        from graspcap.flows.plan import run_plan

        return run_plan(args.roots, args.catalog, args.preset, retry_failed=args.retry_failed,
                        settings=args.settings)
    from graspcap.flows.commands import run_build

    return run_build(args.roots, args.catalog, args.preset, dask=args.dask,
                     retry_failed=args.retry_failed, settings=args.settings,
                     started=STARTED, gates=args.gates, stage=args.stage,
                     keep_runs=args.keep_runs)


def _cmd_status(args: argparse.Namespace) -> int:
    from deltalake.exceptions import DeltaError

    import graspcap.catalog as gc
    from graspcap.catalog.cli import problem_lines, report_problems
    from graspcap.flows.commands import status_text

    try:
        text = status_text(args.catalog, limit=args.limit)
        print(text)
        return report_problems(gc.open(args.catalog), "graspcap status")
    except BrokenPipeError:
        raise  # the reader went away: main() ends quietly
    except (gc.CatalogError, ValueError, OSError, DeltaError) as exc:  # one line per problem
        for line in problem_lines(exc):
            print(f"graspcap status: {line}", file=sys.stderr)
        return 2


def _vacuum_work(work: Path):
    from graspcap.flows.work_vacuum import vacuum_work

    return vacuum_work(work)


def _cmd_report(args: argparse.Namespace) -> int:
    from deltalake.exceptions import DeltaError

    import graspcap.catalog as gc
    from graspcap.catalog.cli import problem_lines
    from graspcap.catalog.report_page import write_report

    version = args.version
    if version is not None and version.lstrip("-").isdigit():
        version = int(version)
    try:
        print(write_report(gc.open(args.catalog), version))
        return 0
    except (gc.CatalogError, ValueError, OSError, DeltaError) as exc:  # one line per problem
        for line in problem_lines(exc):
            print(f"graspcap report: {line}", file=sys.stderr)
        return 2


def _cmd_serve(args: argparse.Namespace) -> int:
    from graspcap.flows.commands import serve

    if missing_roots(args.roots, "serve"):
        return EXIT_USAGE
    return serve(args.roots, args.catalog, args.preset, cron=args.cron, interval_s=args.interval,
                 gates=args.gates)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="graspcap", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("synth", help="write synthetic capture sessions with ground truth")
    p.add_argument("out", type=Path, help="folder to write the sessions into")
    p.add_argument("--sessions", type=int, default=4, help="number of sessions")
    p.add_argument("--seed", type=int, default=0, help="random seed (deterministic per seed)")
    p.add_argument(
        "--profile", "--difficulty", dest="profile", default="realistic",
        choices=["easy", "realistic", "hard", "real-detector", "wild"], metavar="PROFILE",
        help="easy, realistic (default), hard, real-detector or wild (every randomisation "
        "factor: hands, cameras, lens, objects, detector, depth; docs/synth.md); "
        "--difficulty is an alias",
    )
    p.add_argument("--frames", type=int, default=None, help="grasp-video frames per session")
    p.add_argument(
        "--object", type=Path, action="append", default=[],
        help="object mesh file in metres (repeatable); default: procedural objects",
    )
    p.add_argument("--workers", type=int, default=1, help="processes to generate sessions with")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("validate", help="check sessions against the capture-session contract")
    p.add_argument("dirs", type=Path, nargs="+", help="session folders or roots holding many")
    p.add_argument("--no-images", action="store_true", help="skip decoding every image")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("demo", help="synthesise sessions, validate them and run the pipeline")
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder")
    p.add_argument("--sessions", type=int, help="number of synthetic sessions")
    p.add_argument("--frames", type=int, help="grasp-video frames per session")
    p.add_argument("--seed", type=int, help="random seed")
    p.set_defaults(func=_cmd_demo)
    p = sub.add_parser(
        "build", help="build or update the catalog from capture sessions",
        formatter_class=argparse.RawDescriptionHelpFormatter, epilog=BUILD_EXIT_CODES)
    p.add_argument("roots", type=Path, nargs="+", help="session folders or roots holding many")
    p.add_argument("--catalog", type=Path, default=DEFAULT_CATALOG, help="catalog folder")
    p.add_argument("--preset", default="default", choices=list(PIPELINE_PRESETS),
                   metavar="PRESET", help="pipeline preset: " + ", ".join(PIPELINE_PRESETS))
    p.add_argument("--set", dest="settings", action="append", default=[],
                   metavar="STAGE.FIELD=VALUE",
                   help="override one config field over the preset, checked against the "
                        "stage's config (repeatable), e.g. reconstruct_hand.huber_k=1.5")
    p.add_argument("--dask", default=None, metavar="ADDRESS|local:N", type=_dask_arg,
                   help="run on a Dask scheduler, or a local cluster of N worker processes")
    p.add_argument("--retry-failed", action="store_true",
                   help="re-run only the sessions that failed in the last build")
    p.add_argument("--plan", action="store_true",
                   help="run and write nothing: print per session and stage whether the build "
                        "would use the cache or run, and why (changed file, config field, "
                        "code module, library, upstream, failed last time)")
    p.add_argument("--verify", type=int, default=None, metavar="N",
                   help="write nothing: re-run N randomly chosen cached stages and compare "
                        "their results with the stored ones (finds a key that misses "
                        "something); exit 1 on a mismatch")
    p.add_argument("--gate", dest="gates", action="append", default=[], metavar="NAME=VALUE",
                   help="an audit gate (repeatable; off: NAME=off), e.g. max_lost_sessions=0, "
                        "max_failed_share_rise=0.1, max_regressed_share=0.05 (docs/catalog.md, "
                        "Write-audit-publish); the new version is published only when every "
                        "gate passes, else staged")
    p.add_argument("--stage", action="store_true",
                   help="stage the new version even when its audit passes (publish it with "
                        "`graspcap catalog publish VERSION`)")
    p.add_argument("--keep-runs", type=int, default=None, metavar="N",
                   help="keep the newest N finished flow runs in Prefect's database (default "
                        "100; older ones are deleted after the build)")
    p.set_defaults(func=_cmd_build)

    p = sub.add_parser("status", help="recent builds, failures with reasons, stage runs")
    p.add_argument("--catalog", type=Path, default=DEFAULT_CATALOG, help="catalog folder")
    p.add_argument("--limit", type=int, default=5, help="number of builds to show")
    p.set_defaults(func=_cmd_status)

    p = sub.add_parser("report", help="write a version's report page (HTML: sessions, "
                                      "reasons, pictures, QA plots) and print its path")
    p.add_argument("version", nargs="?", default=None,
                   help="version number or tag (default: the newest published)")
    p.add_argument("--catalog", type=Path, default=DEFAULT_CATALOG, help="catalog folder")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("serve", help="run the build on a schedule (Prefect serve)")
    p.add_argument("roots", type=Path, nargs="+", help="session folders or roots holding many")
    p.add_argument("--catalog", type=Path, default=DEFAULT_CATALOG, help="catalog folder")
    p.add_argument("--preset", default="default", choices=list(PIPELINE_PRESETS),
                   metavar="PRESET", help="pipeline preset: " + ", ".join(PIPELINE_PRESETS))
    when = p.add_mutually_exclusive_group(required=True)
    when.add_argument("--cron", help='cron schedule, e.g. "0 2 * * *"')
    when.add_argument("--interval", type=float, help="run every this many seconds")
    p.add_argument("--gate", dest="gates", action="append", default=[], metavar="NAME=VALUE",
                   help="an audit gate of every scheduled build (as for build)")
    p.set_defaults(func=_cmd_serve)

    add_catalog_parser(sub, _vacuum_work)
    add_detect_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        code = args.func(args)
        sys.stdout.flush()  # a closed pipe shows here, not at the interpreter's exit
        return code
    except BrokenPipeError:
        _quiet_stdout()
        return EXIT_BROKEN_PIPE


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: the interpreter's last flush of what is still buffered for a
    closed pipe would print a second BrokenPipeError."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # not a real file (a test's capture)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
