"""How many threads a stage may run at once: what its config asks for, capped by the worker.

A stage that splits its work over threads (``reconstruct_hand``'s depth prefetch, its
initial PnP and its depth links) gives the same result on any number of them (tests), so the
count is a resource limit, not a parameter of the result, and not part of the cache key. On
a Dask cluster with as many single-threaded workers as cores, each worker's stages must not
fan out over the others' cores: ``GRASPCAP_WORKER_THREADS`` (set for the workers, see
``graspcap.flows.worker``) caps every stage's threads.
"""

from __future__ import annotations

import os

THREADS_ENV = "GRASPCAP_WORKER_THREADS"


def thread_budget(requested: int) -> int:
    """``requested`` threads (at least 1), at most ``GRASPCAP_WORKER_THREADS`` when it is set
    to a positive number."""
    cap = int(os.environ.get(THREADS_ENV) or 0)
    return max(1, min(requested, cap) if cap > 0 else requested)
