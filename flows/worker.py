"""Set-up of a Dask worker process for builds: a Dask preload module.

``--dask local:N`` preloads it into every worker of its ``LocalCluster``; for an existing
cluster start the workers with ``dask worker ADDRESS --preload graspcap.flows.worker``.
It imports Prefect's task engine and the stage modules while the cluster starts (~3 s and ~5 s
of CPU a worker, measured under load), instead of in the first task, and bounds Open3D's
thread pool (TBB, which ``OMP_NUM_THREADS`` does not reach) to ``GRASPCAP_WORKER_THREADS``
when set: N single-threaded workers on N cores must not each fan out over all of them.
"""

from __future__ import annotations

import os

THREADS_ENV = "GRASPCAP_WORKER_THREADS"


def dask_setup(worker=None) -> None:
    """Called by Dask in the worker process at start-up."""
    import prefect.task_engine  # noqa: F401

    import graspcap.flows.session  # noqa: F401
    import graspcap.tasks.pipeline  # noqa: F401

    threads = int(os.environ.get(THREADS_ENV) or 0)
    if threads > 0:
        import open3d as o3d

        o3d.utility.set_max_threads(threads)
