"""Seeded, repeatable RANSAC over FPFH correspondences (the global step of registration).

Open3D's ``registration_ransac_based_on_feature_matching`` runs its hypotheses on TBB
threads that share one random generator, so which hypotheses are drawn depends on thread
scheduling: even after ``o3d.utility.random.seed`` the same input gave a mug 10, 140 or
163 deg off from run to run (``OMP_NUM_THREADS`` does not reach TBB). On one thread, seeded
before every restart, the draws come in a fixed order.

(A numpy RANSAC drawn from ``numpy.random.default_rng`` was tried beside it: half the CPU
of a restart, but it missed the realistic mug [9000, 5] that Open3D's draws find, and a
restart is not where the registration stages spend their time; removed.)
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded

# open3d: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d
    from open3d.pipelines import registration as reg

_OPEN3D_LOCK = threading.Lock()
"""Open3D's RANSAC draws from one process-wide generator: seeding and drawing are serialised
between threads."""


def ransac_restarts(
    scene_down: o3d.geometry.PointCloud,
    scene_fpfh: reg.Feature,
    model_down: o3d.geometry.PointCloud,
    model_fpfh: reg.Feature,
    distance_m: float,
    seed: int,
    n_restarts: int,
    max_iterations: int,
    confidence: float,
) -> Iterator[np.ndarray]:
    """Scene-into-model transforms (4, 4) of restarts 0, 1, ... (seed ``seed + k``) of Open3D's
    FPFH + RANSAC, scene (source) against model (target), each on one thread."""
    import open3d as o3d
    from open3d.pipelines import registration as reg

    checkers = [
        reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        reg.CorrespondenceCheckerBasedOnDistance(distance_m),
    ]
    criteria = reg.RANSACConvergenceCriteria(max_iterations, confidence)
    for k in range(n_restarts):
        with _OPEN3D_LOCK, single_threaded():  # one thread: the draws in a fixed order
            o3d.utility.random.seed(seed + k)
            res = reg.registration_ransac_based_on_feature_matching(
                scene_down, model_down, scene_fpfh, model_fpfh, False, distance_m,
                reg.TransformationEstimationPointToPoint(False), 3, checkers, criteria,
            )  # fmt: skip
        yield np.asarray(res.transformation).copy()
