"""What ``graspcap build``, ``status`` and ``serve`` do (the CLI parses, this acts).

Call :func:`graspcap.flows.runtime.configure` before importing this module's Prefect users;
the functions here import them lazily for that reason.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import time
import traceback
from collections.abc import Sequence
from pathlib import Path

from graspcap.flows.runtime import configure

EXIT_OK = 0
"""``graspcap build``: every session built (or unchanged)."""
EXIT_SESSIONS_FAILED = 1
"""Some sessions failed; the others are committed (or were already), the failures recorded."""
EXIT_USAGE = 2
"""A usage error: bad arguments (argparse's code), or no session under the roots."""
EXIT_BUILD_FAILED = 3
"""The build failed as a whole and committed nothing (the catalog's lock, the disk, the
commit); completed stage results stay in the work area for the next build."""
EXIT_STAGED = 4
"""The new version is committed but staged, not published: its audit failed (or ``--stage``);
readers stay on the published version (``graspcap catalog publish|reject VERSION``)."""


class _NoTraceback(logging.Filter):
    """Drops the traceback from Prefect's "Encountered exception during execution" line for
    an expected failure (``graspcap build`` prints its reason once, without a traceback)."""

    def __init__(self, types: tuple[type[BaseException], ...]):
        super().__init__()
        self.types = types

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and isinstance(record.exc_info[1], self.types):
            record.exc_info = record.exc_text = None
        return True


def process_seconds(fallback_start: float | None = None) -> float:
    """Seconds since this process started (Linux: its start time in ``/proc``), so a command's
    summary counts the imports and Prefect's start-up too; elsewhere since ``fallback_start``
    (a ``time.perf_counter()`` taken early), else 0."""
    try:
        stat = Path("/proc/self/stat").read_text()
        ticks = int(stat.rpartition(")")[2].split()[19])  # field 22: starttime, in clock ticks
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return max(0.0, uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0 if fallback_start is None else time.perf_counter() - fallback_start


def run_build(roots: Sequence[Path], catalog: Path, preset: str = "default",
              dask: str | None = None, retry_failed: bool = False,
              settings: Sequence[str] = (), started: float | None = None,
              gates: Sequence[str] = (), stage: bool = False,
              keep_runs: int | None = None) -> int:
    """``graspcap build``: :data:`EXIT_OK`, :data:`EXIT_SESSIONS_FAILED`, :data:`EXIT_USAGE`
    or :data:`EXIT_BUILD_FAILED` (its reason on stderr, a traceback only for a bug); a wrong
    ``--set`` is :data:`EXIT_USAGE` (the message names it). The summary's wall time counts from
    the process's start (``started``: a ``perf_counter`` of it where that cannot be read)."""
    from graspcap.catalog.audit import parse_gates
    from graspcap.catalog.errors import CatalogError
    from graspcap.flows.report import BuildFailed
    from graspcap.flows.retention import RunRetention
    from graspcap.tasks.pipeline import settings_overrides
    from graspcap.tasks.session.discover import discover_sessions

    try:
        overrides = settings_overrides(list(settings), preset)
        audit = parse_gates(gates, {"auto_publish": False} if stage else None)
        retention = RunRetention() if keep_runs is None else RunRetention(max_runs=keep_runs)
    except ValueError as exc:
        print(f"graspcap build: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if not discover_sessions(list(roots)):
        print(f"no session.json found under {' '.join(map(str, roots))}", file=sys.stderr)
        return EXIT_USAGE
    expected = (BuildFailed, CatalogError, KeyError, OSError)
    quiet = _NoTraceback(expected)
    flow_log = logging.getLogger("prefect.flow_runs")
    flow_log.addFilter(quiet)
    try:
        import graspcap.catalog as gc

        gc.open(catalog, create=True)  # a catalog it cannot open fails before Prefect starts
        configure(Path(catalog) / "work")
        from graspcap.flows.build import build_dataset
        from graspcap.flows.progress import ConsoleProgress

        with ConsoleProgress(sys.stdout) as progress:
            report = build_dataset(roots, catalog, preset, dask=dask,
                                   retry_failed=retry_failed, progress=progress,
                                   overrides=overrides or None, gates=audit,
                                   retention=retention)
    except KeyboardInterrupt:
        raise
    except Exception as exc:  # noqa: BLE001 - any error here means nothing was committed
        if not isinstance(exc, expected):
            traceback.print_exc()  # a bug: its traceback helps
        print(f"graspcap build: the build failed, nothing committed: {exc}", file=sys.stderr)
        return EXIT_BUILD_FAILED
    finally:
        flow_log.removeFilter(quiet)
    report.seconds["wall"] = process_seconds(started)
    # Prefect's event worker says at exit that it is still sending events to the API: a line
    # after the summary that asks nothing of the user
    logging.getLogger("EventsWorker").setLevel(logging.ERROR)
    print(report.summary())
    if report.publication.get("state") == "staged":
        return EXIT_STAGED
    return EXIT_SESSIONS_FAILED if report.failed else EXIT_OK


def status_text(catalog: Path, limit: int = 5) -> str:
    """Recent builds (newest first): outcome counts, failures with reasons, stage runs."""
    import graspcap.catalog as gc
    from graspcap.flows.workarea import BUILDS_LOG

    cat = gc.open(catalog)
    out = []
    log = cat.layout.root / "work" / BUILDS_LOG
    records, torn = _build_records(log)
    committed = {}
    removed: list[str] = []
    if cat.latest_version() is not None:  # the newest version, published or not
        for row in cat.table("builds", cat.latest_version()).sort_by(
                "catalog_version").to_pylist():
            committed[row["build_id"]] = row
            params = json.loads(row["parameters_json"])
            rec = params.get("report")
            if rec and rec["build_id"] not in {r["build_id"] for r in records}:
                records.append(rec)
            if params.get("command") == "catalog remove":  # a version no build made
                removed.append(f"version {row['catalog_version']} ({row['build_id']}): catalog "
                               f"remove of {', '.join(row['sessions_removed'])}"
                               + (f"; reason: {params['reason']}" if params.get("reason")
                                  else ""))
    out += removed[::-1][:limit]
    if torn:
        out.append(f"note: {log}: line(s) {torn} are not build records (a build killed while "
                   "writing one?); skipped")
    if not records:
        return "\n".join([f"catalog {cat.layout.root}: no builds yet", *out])
    states = cat.states()
    latest, published = cat.latest_version(), cat.published_version()
    head = f"catalog {cat.layout.root}: latest version {latest}"
    if latest is not None:
        head += f" ({states[latest]})"
    head += ("; no version is published" if published is None else
             f"; published version {published} (readers' default)" if published != latest
             else "; readers read it by default")
    out.insert(0, head)
    from graspcap.flows.workarea import WorkArea

    work = WorkArea.reader(cat.layout.root / "work")
    for rec in records[::-1][:limit]:
        why = _run_reasons(work, rec["build_id"])
        s = rec["summary"]
        version = rec.get("catalog_version")
        where = (f"version {version}" if version is not None
                 else "FAILED, nothing committed" if rec.get("error") else "no new version")
        if version is not None and version in states:
            where += f", {states[version]}"
        unlisted = rec.get("unlisted") or {}  # unchanged sessions counted, not listed
        ran = sum(len(x["ran"]) for x in rec["sessions"])
        hit = sum(len(x["cached"]) for x in rec["sessions"]) \
            + sum((unlisted.get("cached") or {}).values())
        out.append(f"build {rec['build_id']} ({where}): {len(s['added'])} added, "
                   f"{len(s['changed'])} changed, {_count(s['unchanged'])} unchanged, "
                   f"{len(s['failed'])} failed; {ran} stage run(s), {hit} cache hit(s), "
                   f"{rec['seconds'].get('total', 0):.1f} s")
        if rec.get("error"):
            out.append(f"    ERROR: {rec['error']}")
        if version is not None and rec["build_id"] not in committed and version in states:
            try:  # a version the newest was not written on top of (rejected), if readable
                for row in cat.table("builds", version).to_pylist():
                    committed.setdefault(row["build_id"], row)
            except gc.CatalogError:
                pass
        out += _audit_lines(committed.get(rec["build_id"]), version, states)
        for x in rec["sessions"]:
            line = f"    {x['session_id']:<32} {x['outcome']:<9}"
            if x["ran"]:
                line += f" ran: {', '.join(x['ran'])}"
            if x["retries"]:
                line += f" retries: {x['retries']}"
            for reasons, stages in why.get(x["session_id"], {}).items():
                line += f"\n{' ' * 46}why {', '.join(stages)}: {reasons}"
            if x["error"]:
                line += f" ERROR: {x['error'].splitlines()[0]}"
                line += "".join(f"\n{' ' * 46}{e}" for e in x["error"].splitlines()[1:6])
            line += "".join(f"\n{' ' * 46}note: {n}" for n in x.get("notes", ()))
            page = rec.get("report_page")
            if x.get("status") in ("flagged", "failed") and page and Path(page).is_file():
                line += f"\n{' ' * 46}{x['status']}; pictures and reasons: {page}"
            out.append(line)
        if unlisted.get("sessions"):
            out.append(f"    {unlisted['sessions']} more unchanged (every stage cached)"
                       + _unlisted_status(unlisted.get("status") or {},
                                          rec.get("report_page")))
    return "\n".join(out)


def _count(ids: list | int) -> int:
    """A record's number of unchanged sessions: a count, or (older records) their ids."""
    return ids if isinstance(ids, int) else len(ids)


def _unlisted_status(status: dict[str, int], page: str | None) -> str:
    """``status``'s line's tail on the unlisted sessions' flagged and failed rows."""
    bad = [f"{status[k]} {k}" for k in ("flagged", "failed") if status.get(k)]
    if not bad:
        return ""
    where = f": pictures and reasons: {page}" if page and Path(page).is_file() else ""
    return f", their rows {' and '.join(bad)}{where}"


def _audit_lines(row: dict | None, version: int | None, states: dict) -> list[str]:
    """A build's audit (its builds row) for ``status``: passed, or each failed gate."""
    if row is None or row.get("audit_passed") is None:
        return []
    audit = json.loads(row["audit_json"] or "{}")
    against = (f" against published version {audit['compared_to']}"
               if audit.get("compared_to") is not None else "")
    if row["audit_passed"]:
        return [f"    audit passed{against}"]
    out = [f"    AUDIT FAILED{against}:"] + [f"      {r}" for r in row["audit_reasons"]]
    if version is not None and str(states.get(version)) == "staged":
        out.append(f"      staged: publish it with `graspcap catalog publish {version}` or "
                   f"reject it with `graspcap catalog reject {version}`")
    return out


def _run_reasons(work, build_id: str) -> dict[str, dict[str, list[str]]]:
    """Why the stages of ``build_id`` ran (the ``why`` of their executions): by session, the
    stages by their reasons (``"; "``-joined), in the order they ran."""
    out: dict[str, dict[str, list[str]]] = {}
    for rec in work.executions(build_id):
        if rec.get("why"):
            stages = out.setdefault(str(rec.get("session_id")), {}).setdefault(
                "; ".join(rec["why"]), [])
            if rec.get("stage") not in stages:
                stages.append(str(rec.get("stage")))
    return out


BUILD_RECORD_KEYS = frozenset({"build_id", "summary", "sessions", "seconds"})


def _build_records(log: Path) -> tuple[list[dict], list[int]]:
    """The build records of ``builds.jsonl`` and the numbers of its lines that are none."""
    records, torn = [], []
    try:
        lines = log.read_text(errors="replace").splitlines()
    except FileNotFoundError:
        return [], []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except (ValueError, RecursionError):
            record = None
        if isinstance(record, dict) and BUILD_RECORD_KEYS <= record.keys():
            records.append(record)
        else:
            torn.append(i)
    return records, torn


def serve(roots: Sequence[Path], catalog: Path, preset: str = "default", *,
          cron: str | None = None, interval_s: float | None = None,
          name: str = "graspcap-build", gates: Sequence[str] = ()) -> int:
    """``graspcap serve``: run the build on a schedule with Prefect's ``serve``; an invalid
    ``cron`` or ``interval_s`` is :data:`EXIT_USAGE`, one line, before anything starts.

    ``serve`` refuses Prefect's ephemeral API, so without ``PREFECT_API_URL`` a local Prefect
    server is started on 127.0.0.1 (database: the one ``graspcap build`` uses, under the
    catalog's work area, so its UI lists the earlier builds too), its UI calling its own API,
    supervised and stopped when this returns (Ctrl-C). Once the deployment is registered it
    prints the UI and API addresses and a ``prefect deployment run`` command that works pasted
    in another shell; then one line per finished run (:func:`run_line`). The runs log each
    stage to the API (level INFO unless ``PREFECT_LOGGING_LEVEL`` is set; the console shows
    warnings only).
    """
    from contextlib import nullcontext

    from graspcap.flows.runtime import local_server, schedule_problem
    from graspcap.flows.workarea import BUILDS_LOG

    work = Path(catalog).expanduser().resolve() / "work"
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")  # the runs' logs, in the UI
    env = configure(work, create=False)
    from graspcap.catalog.audit import parse_gates

    problem = schedule_problem(cron, interval_s)
    try:
        audit = parse_gates(gates).model_dump()
    except ValueError as exc:
        problem = problem or str(exc)
    if problem is not None:  # before anything is made or started
        print(f"graspcap serve: {problem}", file=sys.stderr)
        return EXIT_USAGE
    if "PREFECT_HOME" in env:
        Path(env["PREFECT_HOME"]).mkdir(parents=True, exist_ok=True)
    own = "PREFECT_API_URL" not in os.environ
    # Ctrl-C stops the server even when a shell started this in the background (which
    # ignores SIGINT for its children)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    server = local_server(log_file=work / "prefect-server.log") if own else nullcontext(None)
    with server as url:
        if url:
            os.environ["PREFECT_API_URL"] = url
        api = os.environ["PREFECT_API_URL"]
        from prefect import serve as prefect_serve

        from graspcap.flows.build import build_flow

        params = {"roots": [str(Path(r).resolve()) for r in roots],
                  "catalog": str(Path(catalog).resolve()), "preset": preset, "gates": audit}
        # one build of a catalog at a time: a scheduled run that comes due while the last
        # one is still going waits instead of redoing the same cold work beside it
        deployment = build_flow.to_deployment(
            name=name, cron=cron, interval=interval_s, parameters=params, concurrency_limit=1)
        when = f"cron {cron!r}" if cron is not None else f"every {interval_s:g} s"
        watcher = RunWatcher(api, f"{build_flow.name}/{name}", work / BUILDS_LOG,
                             when, sys.stdout)
        watcher.start()
        import warnings

        # Prefect's SIGTERM handler calls the runner's async stop without awaiting it (the
        # runner stops all the same): its RuntimeWarning asks nothing of the user
        warnings.filterwarnings("ignore", "coroutine 'Runner.astop' was never awaited",
                                RuntimeWarning)
        try:
            prefect_serve(deployment, print_starting_message=False)
        except KeyboardInterrupt:
            pass
        finally:
            watcher.stop()
    return 0


def serve_banner(api_url: str, deployment: str, when: str) -> str:
    """What ``graspcap serve`` prints once its deployment is registered: the UI and API
    addresses and a command that starts a build now from any shell (the API named in it)."""
    import shlex

    ui = api_url.rstrip("/").removesuffix("/api")
    run = (f"PREFECT_API_URL={shlex.quote(api_url)} {shlex.quote(sys.executable)} -m prefect "
           f"deployment run {shlex.quote(deployment)}")
    return "\n".join([
        f"Prefect UI:  {ui}  (the builds' flow runs: {ui}/runs)",
        f"Prefect API: {api_url}",
        f"serving {deployment} ({when}); Ctrl-C stops it",
        "run a build now, from another shell:",
        f"  {run}"])


def run_line(run_name: str, state: str, message: str | None, record: dict | None) -> str:
    """One line for a finished flow run of ``graspcap serve``: the build's outcome from its
    record (``builds.jsonl``: version made, sessions added / changed / unchanged / failed,
    the report page), else Prefect's state and message (a run that wrote no record)."""
    head = f"[{time.strftime('%H:%M:%S')}] run {run_name} {state}"
    if record is None:
        return f"{head}: {(message or 'no build record').splitlines()[0]}"
    s = record["summary"]
    if record.get("error"):
        return f"{head}: build {record['build_id']} FAILED, nothing committed: " \
               f"{str(record['error']).splitlines()[0]}"
    version = record.get("catalog_version")
    made = (f"catalog version {version}" if version is not None
            else f"no new version (still {record.get('previous_version')})")
    failed = "".join(f"; FAILED {sid}: {why.splitlines()[0] if why else ''}"
                     for sid, why in s["failed"].items())
    page = f"; report {record['report_page']}" if record.get("report_page") else ""
    return (f"{head}: build {record['build_id']}: {made}: {len(s['added'])} added, "
            f"{len(s['changed'])} changed, {_count(s['unchanged'])} unchanged, "
            f"{len(s['failed'])} failed{failed}{page}")


class RunWatcher:
    """A thread beside ``prefect.serve``: waits until the deployment is registered, prints
    :func:`serve_banner`, then one :func:`run_line` per flow run of the deployment that
    reaches a final state (runs already final when it starts are not repeated)."""

    FINAL = ("COMPLETED", "FAILED", "CRASHED", "CANCELLED")

    def __init__(self, api_url: str, deployment: str, builds_log: Path, when: str,
                 out, poll_s: float = 2.0):
        import threading

        self.api_url, self.deployment, self.builds_log = api_url, deployment, builds_log
        self.when, self.out, self.poll_s = when, out, poll_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="graspcap-serve-runs",
                                        daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _say(self, text: str) -> None:
        print(text, file=self.out, flush=True)

    def _run(self) -> None:
        from prefect.client.orchestration import get_client
        from prefect.client.schemas.filters import (
            DeploymentFilter,
            DeploymentFilterId,
            FlowRunFilter,
            FlowRunFilterState,
            FlowRunFilterStateType,
        )
        from prefect.client.schemas.objects import StateType

        deployment_id = None
        seen: set[str] | None = None
        while not self._stop.is_set():
            try:
                with get_client(sync_client=True) as client:
                    if deployment_id is None:
                        deployment_id = client.read_deployment_by_name(self.deployment).id
                        self._say(serve_banner(self.api_url, self.deployment, self.when))
                    runs = client.read_flow_runs(
                        deployment_filter=DeploymentFilter(id=DeploymentFilterId(
                            any_=[deployment_id])),
                        flow_run_filter=FlowRunFilter(state=FlowRunFilterState(
                            type=FlowRunFilterStateType(any_=[StateType(t)
                                                              for t in self.FINAL]))))
            except Exception:  # noqa: BLE001 - not registered yet, or the API busy: poll again
                self._stop.wait(self.poll_s)
                continue
            new = [r for r in runs if seen is not None and str(r.id) not in seen]
            seen = (seen or set()) | {str(r.id) for r in runs}
            if new:
                records = {str((rec.get("parameters") or {}).get("flow_run_id")): rec
                           for rec in _build_records(self.builds_log)[0]}
                for r in sorted(new, key=lambda r: r.end_time or r.created):
                    state = r.state.name if r.state else "?"
                    self._say(run_line(r.name, state, r.state.message if r.state else None,
                                       records.get(str(r.id))))
            self._stop.wait(self.poll_s)
