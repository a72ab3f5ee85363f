"""Set-up of the Dask workers of a build: their cluster's settings and a preload module.

``--dask local:N`` makes its ``LocalCluster`` with :func:`local_cluster` and preloads this
module into every worker; for an existing cluster start the workers with ``dask worker
ADDRESS --preload graspcap.flows.worker`` (and the settings of :data:`DASK_CONFIG` in their
environment, e.g. ``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False``).

The preload imports Prefect's task engine and the stage modules while the cluster starts (~3 s
and ~5 s of CPU a worker, measured under load), instead of in the first task, and bounds
Open3D's thread pool (TBB, which ``OMP_NUM_THREADS`` does not reach) to
``GRASPCAP_WORKER_THREADS`` when set: N single-threaded workers on N cores must not each fan
out over all of them (the stages' own threads read it too: ``graspcap.tasks.core.threads``).
Open3D's pool is the only native pool that runs beside a stage body here
(measured: OpenCV's pthreads pool and OpenBLAS took no CPU; Dask's nanny already sets
``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS`` and ``MKL_NUM_THREADS`` to 1).
"""

from __future__ import annotations

import os

from graspcap.tasks.core.threads import THREADS_ENV

DASK_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
}
"""Dask settings of a build's ``LocalCluster`` (scheduler, nannies and workers), each measured
in ``docs/architecture.md``: no statistical profiler sampling the running stage's stack every
10 ms; the event loops' watchdog tick every 1 s (was 20 ms), the system monitor every 5 s (was
0.5 s; it feeds the dashboard, which is off) and the nanny's memory poll every 1 s (was 0.1 s):
an idle cluster of 2 took 0.2 of the 2 cores before, 0.12 after; and glibc's own malloc
tuning kept in the workers (Dask sets ``MALLOC_TRIM_THRESHOLD_=65536``, which also fixes
glibc's mmap threshold, so every array above 128 KiB is a fresh ``mmap``: 12x the page faults
and +7 % stage-body CPU measured on the stages). A ``MALLOC_TRIM_THRESHOLD_`` the user put in
the environment still reaches the workers."""


def local_cluster(**kwargs):
    """A ``distributed.LocalCluster`` with :data:`DASK_CONFIG` (what ``--dask local:N``
    makes; the nannies read the settings when they are created and hand them to the worker
    processes)."""
    import dask
    from distributed import LocalCluster

    config = dict(DASK_CONFIG)
    trim = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"
    if "MALLOC_TRIM_THRESHOLD_" in os.environ:
        config.pop(trim)  # the user's own value reaches the workers
    with dask.config.set(config):
        return LocalCluster(**kwargs)


def dask_setup(worker=None) -> None:
    """Called by Dask in the worker process at start-up."""
    import prefect.task_engine  # noqa: F401

    import graspcap.flows.session  # noqa: F401
    import graspcap.tasks.pipeline  # noqa: F401

    threads = int(os.environ.get(THREADS_ENV) or 0)
    if threads > 0:
        import open3d as o3d

        o3d.utility.set_max_threads(threads)
