"""Seeded, repeatable RANSAC over FPFH correspondences (the global step of registration).

Two ways, both repeatable (:class:`GlobalMethod`): Open3D's RANSAC on one thread (the
default), or :func:`ransac` below.

Open3D's ``registration_ransac_based_on_feature_matching`` runs its hypotheses on TBB
threads that share one random generator, so which hypotheses are drawn depends on thread
scheduling: even after ``o3d.utility.random.seed`` the same input gave a mug 10, 140 or
163 deg off from run to run (``OMP_NUM_THREADS`` does not reach TBB). On one thread the
draws come in a fixed order. :func:`ransac` is the same algorithm in numpy, drawn from
``numpy.random.default_rng(seed)`` in batches (half the CPU time, but it missed the
realistic mug [9000, 5] that Open3D's draws find).

Per hypothesis, as Open3D does: three correspondences drawn at random, rejected unless
every edge between them has about the same length in both clouds (``edge_ratio``), the
rigid fit (Kabsch) of the three, rejected unless each maps within ``distance_m`` of its
partner; then the share of all correspondences it explains (the inlier ratio) and the
share of a subsample of the scene points with a model point within ``distance_m``; for the
best few of each batch by the latter, the same share over all scene points (the fitness,
which ranks, then the RMSE). The iteration count shrinks as the best inlier ratio grows, to
reach ``confidence``.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from graspcap.tasks.open3d_threads import single_threaded

reg = o3d.pipelines.registration


class GlobalMethod(StrEnum):
    """The RANSAC of the global step."""

    OPEN3D = "open3d"
    """Open3D's ``registration_ransac_based_on_feature_matching``, run on one thread (on
    several, its TBB threads share one generator and the draws depend on scheduling)."""
    NUMPY = "numpy"
    """:func:`ransac` below: the same algorithm in numpy, 2x less CPU; it fails more often on the
    synthetic mug (seed [9000, 5]: every restart and probe 109 deg off)."""


BATCH = 1024
"""Hypotheses drawn and tested together (a fixed size keeps the draws repeatable)."""
PROBE_POINTS = 256
"""Every hypothesis that passes the checks is scored on this many scene points (an even
stride): the fitness on them ranks the hypotheses of a batch as the full one does."""
VALIDATE_PER_BATCH = 4
"""The hypotheses of a batch that score best on those points get the full check."""


@dataclass(frozen=True)
class Matches:
    """FPFH correspondences of a scene against a model, computed once for every restart.

    scene_pts : (n, 3) float; model_pts : (m, 3) float; pairs : (k, 2) int (scene, model)
    indices; model_tree : KD-tree of ``model_pts``.
    """

    scene_pts: np.ndarray
    model_pts: np.ndarray
    pairs: np.ndarray
    model_tree: cKDTree


def match_features(
    scene_pts: np.ndarray, scene_fpfh: np.ndarray, model_pts: np.ndarray, model_fpfh: np.ndarray
) -> Matches:
    """Each scene point paired with the model point whose feature is nearest.

    Parameters
    ----------
    scene_pts : (n, 3) float
    scene_fpfh : (33, n) float
        Open3D's layout (``Feature.data``).
    model_pts : (m, 3) float
    model_fpfh : (33, m) float
    """
    scene_pts = np.asarray(scene_pts, float)
    model_pts = np.asarray(model_pts, float)
    nearest = cKDTree(np.asarray(model_fpfh, float).T).query(np.asarray(scene_fpfh, float).T)[1]
    pairs = np.stack([np.arange(len(scene_pts)), nearest], axis=1).astype(np.int64)
    return Matches(scene_pts, model_pts, pairs, cKDTree(model_pts))


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid fits ``dst ~ R @ src + t`` of point sets ``src``, ``dst`` (b, k, 3):
    (R (b, 3, 3), t (b, 3))."""
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("bki,bkj->bij", src - cs[:, None], dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", Vt, U)))
    D = np.ones((len(src), 3))
    D[:, 2] = np.where(d == 0, 1.0, d)
    R = np.einsum("bji,bj,bkj->bik", Vt, D, U)
    return R, cd - np.einsum("bij,bj->bi", R, cs)


def _edges_agree(src: np.ndarray, dst: np.ndarray, ratio: float) -> np.ndarray:
    """(b,) bool: every edge of the triangles ``src``, ``dst`` (b, 3, 3) has about the same
    length in both (neither shorter than ``ratio`` times the other)."""
    ok = np.ones(len(src), bool)
    for a, b in ((0, 1), (0, 2), (1, 2)):
        ls = np.linalg.norm(src[:, a] - src[:, b], axis=1)
        lt = np.linalg.norm(dst[:, a] - dst[:, b], axis=1)
        ok &= (ls >= ratio * lt) & (lt >= ratio * ls)
    return ok


def fitness(m: Matches, T: np.ndarray, distance_m: float) -> tuple[float, float]:
    """(share of scene points within ``distance_m`` of a model point, RMSE of those) at
    ``T`` (4, 4), scene into model."""
    d = m.model_tree.query(m.scene_pts @ T[:3, :3].T + T[:3, 3], distance_upper_bound=distance_m)[0]
    inl = np.isfinite(d)
    if not inl.any():
        return 0.0, 0.0
    return float(inl.mean()), float(np.sqrt(np.mean(d[inl] ** 2)))


def ransac(
    m: Matches,
    distance_m: float,
    seed: int,
    max_iterations: int = 20_000,
    confidence: float = 0.999,
    edge_ratio: float = 0.9,
) -> np.ndarray:
    """The best rigid transform (4, 4), scene into model, of RANSAC over ``m.pairs`` with
    the random generator ``default_rng(seed)``; the identity when no hypothesis passes."""
    rng = np.random.default_rng(seed)
    k = len(m.pairs)
    best_T, best_key = np.eye(4), (0.0, 0.0)
    if k < 3:
        return best_T
    S, M = m.scene_pts[m.pairs[:, 0]], m.model_pts[m.pairs[:, 1]]
    probe_pts = m.scene_pts[:: -(-len(m.scene_pts) // PROBE_POINTS)]
    budget, done = max_iterations, 0
    log_miss = np.log(1.0 - confidence) if confidence < 1.0 else -np.inf
    while done < budget:
        idx = rng.integers(0, k, size=(BATCH, 3))
        done += BATCH
        src, dst = S[idx], M[idx]
        ok = np.flatnonzero(_edges_agree(src, dst, edge_ratio))
        if len(ok) == 0:
            continue
        R, t = kabsch(src[ok], dst[ok])
        moved = np.einsum("bij,bkj->bki", R, src[ok]) + t[:, None]
        close = np.all(np.linalg.norm(moved - dst[ok], axis=2) <= distance_m, axis=1)
        R, t = R[close], t[close]
        if len(R) == 0:
            continue
        resid = np.einsum("bij,kj->bki", R, S) + t[:, None] - M
        inliers = (np.einsum("bki,bki->bk", resid, resid) <= distance_m**2).sum(axis=1)
        probe = np.einsum("bij,kj->bki", R, probe_pts) + t[:, None]
        near = m.model_tree.query(probe.reshape(-1, 3), distance_upper_bound=distance_m)[0]
        score = np.isfinite(near).reshape(len(R), -1).sum(axis=1)
        for j in np.lexsort((-inliers, -score))[:VALIDATE_PER_BATCH]:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R[j], t[j]
            fit, rmse = fitness(m, T, distance_m)
            key = (fit, -rmse)
            if key > best_key:
                best_T, best_key = T, key
                w = inliers[j] / k
                if 0 < w < 1 and np.isfinite(log_miss):
                    needed = log_miss / np.log(1.0 - w**3)
                    budget = min(budget, int(np.ceil(needed)))
                elif w >= 1:
                    budget = done
    return best_T


_OPEN3D_LOCK = threading.Lock()
"""Open3D's RANSAC draws from one process-wide generator: seeding and drawing are serialised
between threads."""


def ransac_restarts(
    method: GlobalMethod,
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
    """Scene-into-model transforms (4, 4) of restarts 0, 1, ... (seed ``seed + k``) of
    FPFH + RANSAC, scene (source) against model (target), drawn as ``method`` says."""
    if method is GlobalMethod.NUMPY:
        matches = match_features(
            np.asarray(scene_down.points), scene_fpfh.data, np.asarray(model_down.points),
            model_fpfh.data,
        )  # fmt: skip
        for k in range(n_restarts):
            yield ransac(matches, distance_m, seed + k, max_iterations, confidence)
        return
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
