"""Where Prefect runs: the embedded default, task runners, and a supervised local server.

Embedded default (nothing to start by hand): unless the user set ``PREFECT_API_URL`` or
``PREFECT_HOME``, Prefect's home (its SQLite database, profiles, logs) is ``<work>/prefect``,
inside the catalog's work area, so a build never writes to ``~/.prefect`` and deleting the work
area removes every trace. Flow-run heartbeats are off (``heartbeat_frequency=None``; each flow
run otherwise pays ~1 s joining the heartbeat thread), the ephemeral API gets 120 s to start on
a loaded machine, logs are quiet (WARNING), the ephemeral server sends no analytics and the
client none either (``DO_NOT_TRACK=1``: without it Prefect prints its telemetry notice on a
terminal the first time it runs in a new home, that is in every new catalog, across the build's
progress bars). Prefect's console handler shows warnings only (``graspcap build`` draws its
own progress), whatever level reaches the API; the ``graspcap`` loggers reach the run's log
(``PREFECT_LOGGING_EXTRA_LOGGERS``). Every setting the user put in the environment wins.

``graspcap serve``'s supervised server (:func:`local_server`) gets its own address as the
address its UI calls (``PREFECT_UI_API_URL``; Prefect's default is 127.0.0.1:4200 whatever
port the server listens on) and no promotional banners.

:func:`configure` must run before ``prefect`` is imported (the CLI does it first thing).
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

DEFAULTS = {
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_SERVER_LOGGING_LEVEL": "CRITICAL",
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL": "WARNING",
    "PREFECT_LOGGING_EXTRA_LOGGERS": "graspcap",
    "PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW": "ignore",  # a graspcap log outside a run
}


def configure(work_root: Path | str, create: bool = True) -> dict[str, str]:
    """Set the embedded defaults (module docstring) in ``os.environ`` where unset; returns
    what it set. Has no effect on settings once ``prefect`` is imported. ``create=False``
    leaves making Prefect's home (``PREFECT_HOME`` of the result) to the caller: a command
    that may still stop on a usage error creates nothing."""
    env = {}
    if "PREFECT_API_URL" not in os.environ and "PREFECT_HOME" not in os.environ:
        env["PREFECT_HOME"] = str(Path(work_root).expanduser().resolve() / "prefect")
        if create:
            Path(env["PREFECT_HOME"]).mkdir(parents=True, exist_ok=True)
    for key, value in DEFAULTS.items():
        if key not in os.environ:
            env[key] = value
    os.environ.update(env)
    return env


def schedule_problem(cron: str | None, interval_s: float | None) -> str | None:
    """Why ``graspcap serve``'s schedule is invalid (one line naming it and the fix), or None:
    checked before anything is made or started, with the cron parser Prefect's
    ``CronSchedule`` validates with (random and hashed fields refused, as Prefect does)."""
    if interval_s is not None and not (math.isfinite(interval_s) and interval_s > 0):
        return f"--interval {interval_s:g}: give a number of seconds > 0, e.g. --interval 3600"
    if cron is None:
        return None
    parser = _cron_parser()
    if parser is None or (parser.is_valid(cron) and not any(
            field.lower() in ("r", "h") for field in cron.split())):
        return None  # (no parser: Prefect checks it when the deployment is made)
    return (f"--cron {cron!r} is not a cron schedule: give five fields, minute hour "
            'day-of-month month day-of-week, e.g. --cron "0 2 * * *" (every day at 02:00)')


def _cron_parser():
    """``croniter`` (the class): the installed package, else the copy Prefect vendors, loaded
    from its file. Importing ``prefect`` itself here would read its settings before the work
    area exists and make its home folder (a usage error must create nothing); None when
    neither is found."""
    import importlib.util

    try:
        from croniter import croniter

        return croniter
    except ImportError:
        pass
    spec = importlib.util.find_spec("prefect")  # finds the package without running it
    if spec is None or spec.origin is None:
        return None
    path = Path(spec.origin).parent / "_vendor" / "croniter" / "croniter.py"
    vendored = importlib.util.spec_from_file_location("graspcap_prefect_croniter", path)
    if not path.is_file() or vendored is None or vendored.loader is None:
        return None
    module = importlib.util.module_from_spec(vendored)
    vendored.loader.exec_module(module)
    return getattr(module, "croniter", None)


_derived_settings: dict[tuple, tuple] = {}
"""(id of the base settings, updates) -> (base, derived): deriving Prefect's settings
re-validates all of them (measured 0.3 s idle, 1.5 s under load), once per build otherwise."""


@contextlib.contextmanager
def build_settings(api_url: str | None = None) -> Iterator[None]:
    """Settings for a build's flow run: heartbeats off unless the user set a frequency, and
    ``api_url`` when given (the API every Dask worker must report to). What
    ``prefect.settings.temporary_settings`` does, with the derived settings kept for the next
    build of this process while the base settings are the same object."""
    import prefect.context
    from prefect.settings import PREFECT_API_URL, PREFECT_FLOWS_HEARTBEAT_FREQUENCY

    updates: dict = {}
    if "PREFECT_FLOWS_HEARTBEAT_FREQUENCY" not in os.environ:
        updates[PREFECT_FLOWS_HEARTBEAT_FREQUENCY] = None
    if api_url:
        updates[PREFECT_API_URL] = api_url
    context = prefect.context.get_settings_context()
    key = (id(context.settings), tuple(sorted((k.name, repr(v)) for k, v in updates.items())))
    base, derived = _derived_settings.get(key, (None, None))
    if base is not context.settings:
        derived = context.settings.copy_with_update(updates=updates)
        if len(_derived_settings) > 8:
            _derived_settings.clear()
        _derived_settings[key] = (context.settings, derived)
    with prefect.context.SettingsContext(profile=context.profile, settings=derived):
        yield


@contextlib.contextmanager
def worker_api(dask: str | None) -> Iterator[str | None]:
    """The API URL Dask workers must use: the configured one, or (no API configured and Dask
    asked for) Prefect's ephemeral server started here in the parent on 127.0.0.1; without it
    each worker process would start its own temporary API. None for the thread-pool runner."""
    from prefect.settings import get_current_settings

    url = get_current_settings().api.url
    if dask is None or url:
        yield url
        return
    from prefect.server.api.server import SubprocessASGIServer

    server = SubprocessASGIServer()
    server.start(timeout=int(os.environ.get(
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")))
    yield server.api_url


def task_runner(dask: str | None = None, workers: int = 2):
    """A Prefect task runner: threads in this process (``dask=None``, ``workers`` threads),
    a Dask ``LocalCluster`` of N single-threaded worker processes (``"local:N"``, each with
    ``flows/worker.py`` preloaded and Open3D bounded to cores / N threads), or an existing Dask
    scheduler (its address, e.g. ``"tcp://10.0.0.5:8786"``). The cluster starts at the first
    submitted task: a build with nothing to run starts none."""
    if dask is None:
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=workers)
    from prefect_dask import DaskTaskRunner

    if dask.startswith("local:"):
        from graspcap.flows.worker import THREADS_ENV

        n = int(dask.split(":", 1)[1])
        threads = max(1, (os.cpu_count() or 1) // n)  # Open3D's pool: the worker's cores
        return DaskTaskRunner(cluster_class="graspcap.flows.worker.local_cluster", cluster_kwargs={
            "n_workers": n, "threads_per_worker": 1, "processes": True,
            "dashboard_address": None, "preload": ["graspcap.flows.worker"],
            "env": {THREADS_ENV: str(threads)}})
    return DaskTaskRunner(address=dask)


# --- a supervised local Prefect server (for schedules) ------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


UI_API_URL_KEYS = ("PREFECT_UI_API_URL", "PREFECT_SERVER_UI_API_URL")
"""Where a user may have named the API the UI calls (a proxy in front of the server)."""


def server_env(host: str, port: int, environ: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a supervised ``prefect server start --host HOST --port PORT``:
    ``environ`` (default ``os.environ``) with the server's own API address as the one its UI
    calls (unless the user named one), the same host and port as Prefect's settings (what
    ``prefect`` commands and the server's own services read), telemetry and the UI's
    promotional content off unless set."""
    env = dict(os.environ if environ is None else environ)
    if not any(key in env for key in UI_API_URL_KEYS):
        env["PREFECT_UI_API_URL"] = f"http://{host}:{port}/api"
    env["PREFECT_SERVER_API_HOST"] = host
    env["PREFECT_SERVER_API_PORT"] = str(port)
    for key, value in {"PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
                       "PREFECT_SERVER_UI_SHOW_PROMOTIONAL_CONTENT": "false"}.items():
        env.setdefault(key, value)
    return env


def _die_with_parent() -> None:
    """In the server's child process (Linux): SIGTERM when the process that started it dies,
    even by SIGKILL, so no server outlives ``graspcap serve``."""
    import ctypes
    import signal

    PR_SET_PDEATHSIG = 1
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)


@contextlib.contextmanager
def local_server(port: int | None = None, timeout_s: float = 180.0,
                 log_file: Path | None = None) -> Iterator[str]:
    """Run ``prefect server start`` on 127.0.0.1 as a child process until the block exits
    (environment: :func:`server_env`, so its UI calls this server's API); yields its API URL
    once ``/api/health`` answers."""
    port = port or free_port()
    url = f"http://127.0.0.1:{port}/api"
    log = open(log_file, "ab") if log_file else subprocess.DEVNULL  # noqa: SIM115
    proc = subprocess.Popen(
        [sys.executable, "-m", "prefect", "server", "start", "--host", "127.0.0.1",
         "--port", str(port)], stdout=log, stderr=subprocess.STDOUT,
        env=server_env("127.0.0.1", port), start_new_session=True,
        preexec_fn=_die_with_parent if sys.platform == "linux" else None)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            if proc.poll() is not None:
                raise RuntimeError(f"prefect server exited with {proc.returncode} while "
                                   f"starting" + (f"; see {log_file}" if log_file else ""))
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"prefect server on port {port} not healthy after "
                                   f"{timeout_s:g} s")
            time.sleep(0.5)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if log_file:
            log.close()
