"""Open3D on one thread while a registration runs: the same input gives the same pose.

Open3D runs ICP, normals, FPFH and clustering on TBB threads; ICP sums its normal
equations in whatever order the threads finish, so the same start gave poses 1e-4 apart
from run to run, and on a mug whose probes compete closely that became 15 deg against
32 deg (build bench seed 11 #0). ``OMP_NUM_THREADS`` does not reach TBB;
``open3d.utility.set_max_threads`` does, process-wide. :func:`single_threaded` sets it
to 1 while any caller is inside (counted, so nested and concurrent callers are safe) and
restores the previous limit when the last one leaves.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

# open3d: imported where used, so that importing the stage table stays cheap

_lock = threading.Lock()
_inside = 0
_saved = 0


@contextmanager
def single_threaded() -> Iterator[None]:
    """Limit Open3D to one thread for the duration of the ``with`` block."""
    import open3d as o3d

    global _inside, _saved
    with _lock:
        if _inside == 0:
            _saved = o3d.utility.get_max_threads()
            o3d.utility.set_max_threads(1)
        _inside += 1
    try:
        yield
    finally:
        with _lock:
            _inside -= 1
            if _inside == 0:
                o3d.utility.set_max_threads(_saved)
