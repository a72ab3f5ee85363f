"""Progress of a build: one event per finished stage task, to a callback scoped to the call.

The build flow reports each task as it completes (in completion order, not submission order)
through :func:`emit`; whoever called :func:`graspcap.flows.build.build_dataset` with a
``progress`` callback receives the events. The callback lives in a :class:`ContextVar` set by
:func:`reporting_to` around the call and reset after it, so there is no module-level state:
two builds in two threads (or two contexts) each reach only their own callback, and a flow run
started by a schedule (``graspcap serve``) reports to nobody. Prefect runs a sync flow's body in
the calling thread and context, which is where the events are made (task workers, threads or
Dask processes, never call it).

:class:`ConsoleProgress` is what ``graspcap build`` shows: a ``rich`` bar over sessions (done /
total, elapsed, ETA) and one over stage tasks on a terminal; one plain log line per finished
session (with the ETA) otherwise.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from contextvars import ContextVar
from dataclasses import dataclass
from typing import TextIO


@dataclass(frozen=True)
class StageEvent:
    """One stage task of one session reached a final state."""

    session_id: str
    stage: str
    state: str
    """Prefect's state name: Completed, Failed, NotReady (an upstream failed), Crashed, ..."""
    done: int
    """Tasks of the build finished so far, this one included."""
    total: int
    """Tasks of the build."""
    session_done: bool
    """This was the last of the session's tasks to finish."""
    sessions_done: int
    """Sessions whose tasks have all finished, this one included."""
    sessions_total: int


ProgressFn = Callable[[StageEvent], None]
"""``progress(event)``: called in the build's thread after each task."""

_SINK: ContextVar[ProgressFn | None] = ContextVar("graspcap_build_progress", default=None)


@contextlib.contextmanager
def reporting_to(progress: ProgressFn | None) -> Iterator[None]:
    """Send the events of builds run inside this block to ``progress`` (None: nowhere)."""
    token = _SINK.set(progress)
    try:
        yield
    finally:
        _SINK.reset(token)


class Tracker:
    """Counts finished tasks per session and emits a :class:`StageEvent` for each."""

    def __init__(self, tasks_per_session: Mapping[str, int]):
        self.left = dict(tasks_per_session)
        self.total = sum(self.left.values())
        self.done = 0
        self.sessions_done = 0
        self.sink = _SINK.get()

    def finished(self, session_id: str, stage: str, state: str) -> StageEvent:
        self.done += 1
        self.left[session_id] -= 1
        session_done = self.left[session_id] == 0
        self.sessions_done += session_done
        event = StageEvent(session_id, stage, state, self.done, self.total, session_done,
                           self.sessions_done, len(self.left))
        if self.sink is not None:
            try:
                self.sink(event)
            except Exception as exc:  # noqa: BLE001 - feedback never fails a build
                logging.getLogger(__name__).warning(
                    "build progress callback %r failed (%s: %s); no more progress is reported",
                    self.sink, type(exc).__name__, exc)
                self.sink = None
        return event


class ConsoleProgress:
    """``graspcap build``'s feedback: rich bars on a terminal, a line per session otherwise.

    Use as a context manager around the build (the bars are drawn while it is open).
    """

    def __init__(self, stream: TextIO = sys.stderr, tty: bool | None = None,
                 clock: Callable[[], float] = time.perf_counter):
        self.stream = stream
        self.tty = stream.isatty() if tty is None else tty
        self.clock = clock
        self.t0 = clock()
        self.failed: dict[str, str] = {}
        self._bars = None
        self._sessions = self._tasks = None
        self._first: tuple[float, int] | None = None
        """(time, tasks done) at the first event: the ETA's rate is measured from there (not
        from the start, which includes Prefect's start-up)."""

    def eta(self, e: StageEvent) -> str:
        """``"ETA 0:01:23"``: the build's remaining stage tasks at the rate tasks finished
        since the first event; ``"ETA …"`` until that rate is known, "" once all are done."""
        now = self.clock()
        if self._first is None:
            self._first = (now, e.done)
        if e.done >= e.total:
            return ""
        t_first, done_first = self._first
        if e.done <= done_first or now <= t_first:
            return "ETA …"
        left = round((now - t_first) / (e.done - done_first) * (e.total - e.done))
        return f"ETA {left // 3600}:{left % 3600 // 60:02d}:{left % 60:02d}"

    def __enter__(self) -> ConsoleProgress:
        if self.tty:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )

            self._bars = Progress(TextColumn("{task.description:<10}"), BarColumn(),
                                  MofNCompleteColumn(), TimeElapsedColumn(),
                                  TextColumn("{task.fields[eta]}"),
                                  TextColumn("{task.fields[last]}"),
                                  console=Console(file=self.stream, force_terminal=True),
                                  transient=False)
            self._bars.start()
            self._sessions = self._bars.add_task("sessions", total=None, last="", eta="")
            self._tasks = self._bars.add_task("stages", total=None, last="starting Prefect",
                                              eta="")
        return self

    def __exit__(self, *exc) -> None:
        if self._bars is not None:
            self._bars.stop()
            self._bars = None

    def __call__(self, e: StageEvent) -> None:
        bad = e.state not in ("Completed", "Cached")
        if bad and e.state != "NotReady":
            self.failed.setdefault(e.session_id, e.stage)
        eta = self.eta(e)
        if self._bars is not None:
            self._bars.update(self._sessions, total=e.sessions_total, completed=e.sessions_done,
                              last=f"{e.session_id} done" if e.session_done else "", eta=eta)
            self._bars.update(self._tasks, total=e.total, completed=e.done,
                              last=f"{e.session_id}: {e.stage} {e.state}")
            return
        if bad and e.state != "NotReady":
            self._line(f"{e.session_id}: {e.stage} {e.state}")
        if e.session_done:
            what = (f"failed at {self.failed[e.session_id]}" if e.session_id in self.failed
                    else "all stages done")
            self._line(f"{e.session_id}: {what} (session {e.sessions_done}/{e.sessions_total}, "
                       f"task {e.done}/{e.total}{', ' * bool(eta)}{eta})")

    def _line(self, text: str) -> None:
        self.stream.write(f"[{self.clock() - self.t0:7.1f} s] {text}\n")
        self.stream.flush()
