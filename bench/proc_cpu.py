"""CPU accounting of a build for the benches: CPU seconds per process (and per thread of the
benchmarking process), sampled while the build runs.

    with ProcessCPU() as cpu:
        build_dataset(...)
    print(cpu.summary(wall_s))

A sampler thread polls this process and all its descendants (``psutil``) every ``interval_s``
and keeps each process's last cumulative CPU time, so processes that end with the build (the
Dask workers, a temporary Prefect server) are counted up to their last sample (at most
``interval_s`` of their CPU is lost). Processes are named by role: ``parent`` (this process:
the flow, the Dask scheduler and nannies of a ``LocalCluster``, the client), ``prefect-api``
(a Prefect server subprocess), ``dask-worker`` (spawned worker processes), else their command.
The parent's threads are named by their Python thread name. ``other`` is the machine's busy
CPU outside these processes (other users of the cores).
"""

from __future__ import annotations

import re
import threading
import time
from collections import defaultdict

import psutil


def _role(proc: psutil.Process, root: int) -> str:
    if proc.pid == root:
        return "parent"
    try:
        cmd = " ".join(proc.cmdline())
    except psutil.Error:
        return "gone"
    if "uvicorn" in cmd or "prefect" in cmd and "server" in cmd:
        return "prefect-api"
    if "spawn_main" in cmd or "forkserver" in cmd:
        return "dask-worker" if "resource_tracker" not in cmd else "mp-tracker"
    return cmd.split(" ")[-1][-40:] or "?"


def _busy(times) -> float:
    return sum(getattr(times, f, 0.0) for f in ("user", "system", "nice", "irq", "softirq",
                                                 "steal"))


class ProcessCPU:
    """Sample CPU seconds of this process tree while the block runs (module docstring)."""

    def __init__(self, interval_s: float = 1.0):
        self.interval_s = interval_s
        self.root = psutil.Process()
        self._procs: dict[int, tuple[psutil.Process, str]] = {}
        self._start: dict[int, float] = {}
        self._last: dict[int, float] = {}
        self._threads0: dict[int, float] = {}
        self._threads1: dict[int, float] = {}
        self._names: dict[int, str] = {}
        self._wthreads: dict[int, dict[int, float]] = {}
        """per worker process: its threads' last CPU seconds (tid -> s)"""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _cpu(self, proc: psutil.Process) -> float | None:
        try:
            t = proc.cpu_times()
            return t.user + t.system
        except psutil.Error:
            return None

    def _sample(self, first: bool = False) -> None:
        try:
            kids = self.root.children(recursive=True)
        except psutil.Error:
            kids = []
        for proc in [self.root, *kids]:
            if proc.pid not in self._procs:
                self._procs[proc.pid] = (proc, _role(proc, self.root.pid))
            cpu = self._cpu(self._procs[proc.pid][0])
            if cpu is None:
                continue
            if proc.pid not in self._start:
                self._start[proc.pid] = cpu if first else 0.0
            self._last[proc.pid] = cpu
            if self._procs[proc.pid][1] == "dask-worker":
                try:
                    self._wthreads[proc.pid] = {t.id: t.user_time + t.system_time
                                                for t in proc.threads()}
                except psutil.Error:
                    pass
        for th in threading.enumerate():
            if th.native_id is not None:
                self._names[th.native_id] = th.name
        target = self._threads0 if first else self._threads1
        try:
            for t in self.root.threads():
                target[t.id] = t.user_time + t.system_time
        except psutil.Error:
            pass

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sample()

    def __enter__(self) -> ProcessCPU:
        self._t0 = time.perf_counter()
        self._sys0 = _busy(psutil.cpu_times())
        self._sample(first=True)
        self._thread = threading.Thread(target=self._run, name="bench-cpu-sampler",
                                        daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()
        self.wall_s = time.perf_counter() - self._t0
        self.machine_busy_s = _busy(psutil.cpu_times()) - self._sys0

    def by_role(self) -> dict[str, float]:
        """CPU seconds per role over the block; each worker process separately
        (``dask-worker#1``...), plus ``other`` (the machine's busy time outside the tree)."""
        out: dict[str, float] = defaultdict(float)
        n = 0
        for pid, (_, role) in self._procs.items():
            if pid not in self._last:
                continue
            if role == "dask-worker":
                n += 1
                role = f"dask-worker#{n}"
            out[role] += self._last[pid] - self._start[pid]
        out["other"] = max(0.0, self.machine_busy_s - sum(out.values()))
        return dict(out)

    def parent_threads(self, top: int = 6) -> list[tuple[str, float]]:
        """The parent's busiest threads over the block: (Python thread name or tid, CPU s)."""
        grouped: dict[str, float] = defaultdict(float)
        for tid, cpu in self._threads1.items():
            name = self._names.get(tid, f"native-{tid}")
            grouped[re.sub(r"\d+", "", name)] += (
                cpu - self._threads0.get(tid, 0.0))
        return sorted(grouped.items(), key=lambda kv: -kv[1])[:top]

    def worker_threads(self) -> list[str]:
        """Per worker process: its CPU seconds by thread, busiest first (the first is the
        thread that ran the stage bodies, Dask's executor thread; the others are the event
        loop, Prefect's and native pools' threads)."""
        out = []
        for pid, threads in self._wthreads.items():
            secs = sorted(threads.values(), reverse=True)
            busy = [s for s in secs if s >= 0.05]
            out.append(f"pid {pid}: {len(threads)} threads, " + ", ".join(
                f"{s:.1f}" for s in busy[:8]) + f" s (others {sum(secs[len(busy[:8]):]):.1f} s)")
        return out

    def summary(self) -> str:
        """One line: wall, then CPU seconds and share of the wall per role."""
        parts = [f"{role} {s:.1f} s ({s / self.wall_s:.2f})"
                 for role, s in sorted(self.by_role().items(), key=lambda kv: -kv[1])]
        threads = ", ".join(f"{n} {s:.1f}" for n, s in self.parent_threads())
        return (f"wall {self.wall_s:.1f} s; CPU s (per wall s): " + ", ".join(parts)
                + f"; parent threads: {threads}")
