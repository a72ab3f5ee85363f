"""Registering a known object mesh into depth point clouds (Open3D).

Shared by :mod:`register_object`, :mod:`estimate_adjustment` and
:mod:`register_scan`. Registration always moves the *scene* cloud (source)
onto points sampled on the *model* (target, with the mesh's normals), so a
partial view is matched against the whole surface and the fitness is "the
share of observed points explained by the model". The transforms returned
here are therefore ``T_o_s`` (scene frame into object frame); stages invert
them into ``T_s_o``.

Pipeline pieces: FPFH features, RANSAC global registration with restarts and
coarse-to-fine point-to-plane ICP. The symmetry check (ICP from the best pose turned about
the model's principal axes) is in :mod:`symmetry`, clouds from depth and the platter crop
in :mod:`point_clouds`, the rendered-depth check in :mod:`depth_agreement`.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from pydantic import model_validator

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.geometry import rotation_error_deg, transform_points
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded
from graspcap.tasks.object_pose.registration.point_clouds import estimate_normals, to_pcd
from graspcap.tasks.object_pose.registration.ransac import ransac_restarts

# open3d, trimesh: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d
    from open3d.pipelines import registration as reg


class RegistrationConfig(StageConfig):
    """Global registration, ICP and ambiguity check, shared by the registration stages."""

    voxel_m: float = 0.005
    """Voxel size for the global (FPFH + RANSAC) step."""
    normal_radius_factor: float = 2.0
    """Normal estimation radius, in voxels."""
    feature_radius_factor: float = 5.0
    """FPFH radius, in voxels."""
    ransac_distance_factor: float = 1.5
    """RANSAC inlier distance, in voxels."""
    ransac_max_iterations: int = 20_000
    """RANSAC iteration cap per restart."""
    ransac_confidence: float = 0.999
    """RANSAC early-stop confidence."""
    n_restarts: int = 4
    """RANSAC restarts, each with its own seed; the best after ICP wins (fitness, then RMSE)."""
    seed: int = 0
    """Base seed of the RANSAC draws (restart k uses ``seed + k``) and of model sampling."""
    model_points: int = 20_000
    """Points sampled on the mesh surface (with face normals) as the ICP target."""
    icp_voxels_m: tuple[float, ...] = (0.005, 0.0025, 0.0015)
    """Scene voxel size per ICP level, coarse to fine; 0 keeps every point."""
    icp_max_distance_m: tuple[float, ...] = (0.015, 0.006, 0.003)
    """Correspondence distance per ICP level."""
    icp_max_iterations: int = 20
    """ICP iterations per level."""
    coarse_model_points: int = 0
    """At most this many of the model's points (an even stride) are the target of a symmetry
    probe's first ICP level; 0 uses them all. Its correspondence search gathers every model
    point within ``icp_max_distance_m[0]``, so its cost grows with the square of the sampling
    density. (The global step's starts keep every point: a realistic mug from RANSAC
    converged 9.5 deg off on 5000.)"""
    icp_max_points: int = 3000
    """At most this many scene points per ICP level (an even stride over the voxel grid's
    points): ICP's cost grows with the points, its accuracy stops improving long before."""
    eval_max_points: int = 10_000
    """At most this many scene points (even stride) when a candidate is scored."""
    good_fitness: float = 0.95
    """RANSAC restarts stop early once a refined candidate explains this share of the scene..."""
    agree_m: float = 0.005
    """...or once two restarts' refined poses agree within ``ambiguity_min_deg`` and this...
    """
    agree_min_fitness: float = 0.9
    """...and both explain at least this share of the scene (two restarts that agree on a
    poor pose, a realistic mug 109 deg off at 0.90, are no reason to stop drawing)."""
    eval_distance_m: float = 0.003
    """A scene point within this distance of the posed model counts as an inlier."""
    probe_angles_deg: tuple[float, ...] = (90.0, 180.0)
    """Ambiguity probes: turn the best pose about each principal axis by these, re-run ICP."""
    ambiguity_min_deg: float = 10.0
    """Two poses closer than this in rotation are the same solution."""
    ambiguity_fitness_tol: float = 0.02
    """A distinct pose is as good as the best when its fitness is at most this much lower..."""
    ambiguity_excess_rmse_m: float = 0.001
    """...and its residuals exceed the best's by at most this RMS (``sqrt(rmse_2^2 - rmse_1^2)``):
    a difference below depth-sensor noise is not evidence."""
    probe_levels: int = 1
    """ICP levels a probe runs before it is scored; only probes that come within twice the
    ambiguity tolerances of the best run the remaining levels."""
    probe_eval_points: int = 2000
    """At most this many scene points (even stride) score a probe after its first levels
    (the full score follows for the probes that go on)."""
    round_spread: float = 0.0
    """A model whose surface points' distances from its centroid vary by less than this share
    of their mean (RMS; the wild balls: 0.006) is refined by translation alone (:func:`refine`):
    its rotation is unobservable, and point-to-plane ICP's near-singular rotation steps threw
    a 62 mm ball from its true pose (scene fitness 0.70) 100 mm off to fitness 0 (wild
    [22921, 10]). 0: off."""

    @model_validator(mode="after")
    def _levels_match(self) -> RegistrationConfig:
        if len(self.icp_voxels_m) != len(self.icp_max_distance_m) or not self.icp_voxels_m:
            raise ValueError("icp_voxels_m and icp_max_distance_m need the same, non-zero length")
        return self


@dataclass(frozen=True, eq=False)
class Candidate:
    """One registration hypothesis; equal and hashed by identity (the stages key scores by
    the candidate).

    Attributes
    ----------
    T_o_s : (4, 4) float
        Scene frame into object frame.
    fitness : float
        Share of scene points within ``eval_distance_m`` of the model.
    inlier_rmse_m : float
        RMSE of those inliers.
    origin : str
        How it was found (``"ransac:3"``, ``"probe:1:180"``, ``"init"``...).
    """

    T_o_s: np.ndarray
    fitness: float
    inlier_rmse_m: float
    origin: str


@dataclass(frozen=True)
class Model:
    """A mesh prepared for registration.

    Attributes
    ----------
    dense : o3d.geometry.PointCloud
        Surface samples with face normals (ICP target).
    coarse : o3d.geometry.PointCloud
        At most ``coarse_model_points`` of them (a probe's first ICP level's target).
    down, fpfh
        Voxel-downsampled samples and their FPFH features (global step).
    centroid : (3,) float
        Centroid of the samples, object frame.
    axes : (3, 3) float
        Principal axes as columns, largest variance first.
    radius_m : float
        Largest distance from the centroid to a sample.
    surface : o3d.t.geometry.RaycastingScene
        The mesh itself, for exact point-to-surface distances.
    """

    dense: o3d.geometry.PointCloud
    coarse: o3d.geometry.PointCloud
    down: o3d.geometry.PointCloud
    fpfh: o3d.pipelines.registration.Feature
    centroid: np.ndarray
    axes: np.ndarray
    radius_m: float
    surface: o3d.t.geometry.RaycastingScene


def fpfh(pcd: o3d.geometry.PointCloud, cfg: RegistrationConfig) -> reg.Feature:
    """FPFH features of a cloud that already has normals."""
    import open3d as o3d
    from open3d.pipelines import registration as reg

    radius = cfg.feature_radius_factor * cfg.voxel_m
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=100)
    return reg.compute_fpfh_feature(pcd, search)


_MODELS = threading.local()
"""This thread's recently prepared models (a per-thread cache: Open3D's raycasting scene
builds itself on its first query, which two threads must not race)."""
MODELS_KEPT = 4
"""Prepared models each thread keeps (a session's registration stages share one mesh)."""


def prepare_model(vertices: np.ndarray, faces: np.ndarray, cfg: RegistrationConfig) -> Model:
    """Sample the mesh (vertices (n, 3), faces (m, 3)) and compute its global features.

    The same mesh with the same sampling and feature settings, prepared again on the same
    thread, is the model prepared before (its model FPFH alone costs ~0.1 s; nothing
    modifies a model)."""
    V = np.ascontiguousarray(vertices, dtype=float)
    F = np.ascontiguousarray(faces, dtype=np.int64)
    key = (
        V.shape, F.shape, hashlib.sha1(V.tobytes()).hexdigest(),
        hashlib.sha1(F.tobytes()).hexdigest(), cfg.model_points, cfg.seed, cfg.voxel_m,
        cfg.normal_radius_factor, cfg.feature_radius_factor, cfg.coarse_model_points,
    )  # fmt: skip
    kept: OrderedDict = _MODELS.__dict__.setdefault("kept", OrderedDict())
    if key in kept:
        kept.move_to_end(key)
        return kept[key]
    model = _prepare_model(V, F, cfg)
    kept[key] = model
    while len(kept) > MODELS_KEPT:
        kept.popitem(last=False)
    return model


def _prepare_model(vertices: np.ndarray, faces: np.ndarray, cfg: RegistrationConfig) -> Model:
    import open3d as o3d
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    good = mesh.area_faces > 0
    if not good.any():
        raise ValueError("the object mesh has no face with non-zero area")
    mesh.update_faces(good)
    pts, face_idx = trimesh.sample.sample_surface(mesh, cfg.model_points, seed=cfg.seed)
    normals = mesh.face_normals[face_idx]
    dense = to_pcd(pts, normals)
    down = dense.voxel_down_sample(cfg.voxel_m)
    mesh_normals = np.asarray(down.normals).copy()
    radius = cfg.normal_radius_factor * cfg.voxel_m
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    est = np.asarray(down.normals)
    flip = (est * mesh_normals).sum(1) < 0
    est[flip] *= -1
    down.normals = o3d.utility.Vector3dVector(est)
    centroid = pts.mean(0)
    _, _, Vt = np.linalg.svd(pts - centroid, full_matrices=False)
    radius = float(np.linalg.norm(pts - centroid, axis=1).max())
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    coarse = strided(dense, cfg.coarse_model_points)
    return Model(dense, coarse, down, fpfh(down, cfg), centroid, Vt.T, radius, surface)


def prepare_scene(
    points: np.ndarray, normals: np.ndarray | None, viewpoint: np.ndarray, cfg: RegistrationConfig
) -> tuple[o3d.geometry.PointCloud, o3d.geometry.PointCloud, reg.Feature]:
    """Scene ``points`` (n, 3) -> (cloud at the finest ICP voxel, downsampled cloud, its FPFH).

    ``normals`` (n, 3), when given, are kept (already oriented); otherwise they are
    estimated and turned towards ``viewpoint`` (3,).
    """
    import open3d as o3d

    full = to_pcd(points, normals)
    finest = min(cfg.icp_voxels_m)
    if finest > 0:  # every ICP level and every score works at or above this resolution
        full = full.voxel_down_sample(finest)
    down = full.voxel_down_sample(cfg.voxel_m)
    old = np.asarray(down.normals).copy() if normals is not None else None
    estimate_normals(down, cfg.normal_radius_factor * cfg.voxel_m, viewpoint)
    if old is not None:
        est = np.asarray(down.normals)
        est[(est * old).sum(1) < 0] *= -1
        down.normals = o3d.utility.Vector3dVector(est)
    return full, down, fpfh(down, cfg)


def surface_distance(model: Model, points_o: np.ndarray) -> np.ndarray:
    """Distance (n,) from object-frame ``points_o`` (n, 3) to the mesh surface."""
    import open3d as o3d

    q = o3d.core.Tensor(np.asarray(points_o, dtype=np.float32))
    return model.surface.compute_distance(q).numpy().astype(float)


_DOWNSAMPLED = threading.local()
"""This thread's recent voxel-downsampled clouds, by content (:func:`downsampled`)."""
DOWNSAMPLED_KEPT = 8
"""Downsampled clouds each thread keeps (one per ICP level of a few scenes)."""


def downsampled(pcd: o3d.geometry.PointCloud, voxel_m: float) -> o3d.geometry.PointCloud:
    """``pcd.voxel_down_sample(voxel_m)``, the cloud made before when a cloud with the same
    points and normals was downsampled at the same voxel on this thread (the result is the
    same; nothing modifies it). A global search refines hundreds of starts and probes on one
    scene, every ICP level downsampling it again: wild [9700, 2] spent 64 of 148 CPU s so."""
    pts = np.asarray(pcd.points)
    nrm = np.asarray(pcd.normals) if pcd.has_normals() else np.zeros(0)
    key = (pts.shape, hashlib.sha1(pts.tobytes()).hexdigest(), nrm.shape,
           hashlib.sha1(nrm.tobytes()).hexdigest(), float(voxel_m))  # fmt: skip
    kept: OrderedDict = _DOWNSAMPLED.__dict__.setdefault("kept", OrderedDict())
    if key in kept:
        kept.move_to_end(key)
        return kept[key]
    out = pcd.voxel_down_sample(voxel_m)
    kept[key] = out
    while len(kept) > DOWNSAMPLED_KEPT:
        kept.popitem(last=False)
    return out


def strided(pcd: o3d.geometry.PointCloud, max_points: int) -> o3d.geometry.PointCloud:
    """``pcd`` itself, or every k-th of its points so that at most ``max_points`` remain."""
    n = len(pcd.points)
    if max_points <= 0 or n <= max_points:
        return pcd
    return pcd.select_by_index(np.arange(0, n, -(-n // max_points)).tolist())


def evaluate(
    scene: o3d.geometry.PointCloud,
    model: Model,
    T_o_s: np.ndarray,
    distance_m: float,
    max_points: int = 0,
) -> tuple[float, float]:
    """(fitness, inlier RMSE) of the scene moved by ``T_o_s``, measured to the mesh surface:
    the share of scene points within ``distance_m`` and their RMSE (over an even stride of
    at most ``max_points`` points when it is positive)."""
    pts = np.asarray(strided(scene, max_points).points)
    d = surface_distance(model, transform_points(T_o_s, pts))
    inl = d <= distance_m
    if not inl.any():
        return 0.0, 0.0
    return float(inl.mean()), float(np.sqrt(np.mean(d[inl] ** 2)))


@single_threaded()
def refine(
    scene: o3d.geometry.PointCloud,
    model: Model,
    T_o_s: np.ndarray,
    cfg: RegistrationConfig,
    origin: str,
    first: int = 0,
    stop: int | None = None,
    eval_points: int | None = None,
    coarse_target: bool = False,
) -> Candidate:
    """Coarse-to-fine point-to-plane ICP from ``T_o_s`` (4, 4) over the configured levels
    ``first`` to ``stop`` (all by default), scored on at most ``eval_points`` scene points
    (``cfg.eval_max_points`` by default); the first level against ``model.coarse`` when
    ``coarse_target``."""
    from open3d.pipelines import registration as reg

    T = np.asarray(T_o_s, dtype=float)
    criteria = reg.ICPConvergenceCriteria(1e-7, 1e-7, cfg.icp_max_iterations)
    levels = list(enumerate(zip(cfg.icp_voxels_m, cfg.icp_max_distance_m, strict=True)))
    round_model = cfg.round_spread > 0 and is_round(model, cfg.round_spread)
    for level, (voxel, dist) in levels[first:stop]:
        src = strided(downsampled(scene, voxel) if voxel > 0 else scene, cfg.icp_max_points)
        if round_model:
            T = translate_only(src, model, T, dist, cfg.icp_max_iterations)
            continue
        est = reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=dist))
        target = model.coarse if level == 0 and coarse_target else model.dense
        T = reg.registration_icp(src, target, dist, T, est, criteria).transformation
    n_eval = cfg.eval_max_points if eval_points is None else eval_points
    fit, rmse = evaluate(scene, model, T, cfg.eval_distance_m, n_eval)
    return Candidate(np.asarray(T).copy(), fit, rmse, origin)


def is_round(model: Model, spread: float) -> bool:
    """The model's surface points lie within ``spread`` (RMS, a share of their mean) of one
    distance from its centroid: a ball, whose rotation no depth can show."""
    r = np.linalg.norm(np.asarray(model.dense.points) - model.centroid, axis=1)
    return bool(r.std() < spread * r.mean())


def translate_only(
    src: o3d.geometry.PointCloud, model: Model, T_o_s: np.ndarray, dist_m: float, iterations: int
) -> np.ndarray:
    """Point-to-plane ICP of ``src`` onto the mesh from ``T_o_s`` (4, 4) that moves it by
    translation alone (Tukey weights at ``dist_m``, correspondences the closest surface points
    within it); the rotation is kept. Returns the new ``T_o_s``."""
    import open3d as o3d

    T = np.array(T_o_s, float)
    pts = np.asarray(src.points)
    if len(pts) == 0:
        return T
    for _ in range(iterations):
        p = pts @ T[:3, :3].T + T[:3, 3]
        hit = model.surface.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        q = hit["points"].numpy().astype(float)
        n = hit["primitive_normals"].numpy().astype(float)
        e = ((q - p) * n).sum(1)
        w = np.where(np.abs(e) < dist_m, (1 - (e / dist_m) ** 2) ** 2, 0.0)
        w *= np.linalg.norm(q - p, axis=1) <= dist_m
        if w.sum() < 3:
            break
        A = (n * w[:, None]).T @ n + 1e-9 * np.eye(3)
        step = np.linalg.solve(A, (n * (w * e)[:, None]).sum(0))
        T[:3, 3] += step
        if np.linalg.norm(step) < 1e-7:
            break
    return T


def global_starts(
    scene_down: o3d.geometry.PointCloud,
    scene_fpfh: reg.Feature,
    model: Model,
    cfg: RegistrationConfig,
) -> Iterator[np.ndarray]:
    """``T_o_s`` (4, 4) of RANSAC restart 0, 1, ... (seed ``cfg.seed + k``), repeatable."""
    return ransac_restarts(
        scene_down, scene_fpfh, model.down, model.fpfh,
        cfg.ransac_distance_factor * cfg.voxel_m, cfg.seed, cfg.n_restarts,
        cfg.ransac_max_iterations, cfg.ransac_confidence,
    )  # fmt: skip


def _settled(refined: list[Candidate], cfg: RegistrationConfig) -> bool:
    """A refined candidate is clearly good, or two agree (independent RANSAC runs)."""
    if any(c.fitness >= cfg.good_fitness for c in refined):
        return True
    return any(
        rotation_error_deg(a.T_o_s, b.T_o_s) < cfg.ambiguity_min_deg
        and np.linalg.norm(a.T_o_s[:3, 3] - b.T_o_s[:3, 3]) <= cfg.agree_m
        and min(a.fitness, b.fitness) >= cfg.agree_min_fitness
        for i, a in enumerate(refined)
        for b in refined[i + 1 :]
    )


def tls_cost(c: Candidate, distance_m: float) -> float:
    """Truncated least squares over all scene points, in metres squared: inliers count their
    squared distance, outliers ``distance_m`` squared. Fitness first, then RMSE, in one number."""
    return (1.0 - c.fitness) * distance_m**2 + c.fitness * c.inlier_rmse_m**2


def rank(candidates: list[Candidate], distance_m: float) -> list[Candidate]:
    """Best first by :func:`tls_cost` at ``distance_m``, then origin (a stable order)."""
    return sorted(candidates, key=lambda c: (tls_cost(c, distance_m), c.origin))



@single_threaded()
def register(
    scene: o3d.geometry.PointCloud,
    scene_down: o3d.geometry.PointCloud,
    scene_fpfh: reg.Feature,
    model: Model,
    cfg: RegistrationConfig,
    extra_starts: Sequence[tuple[str, np.ndarray]] = (),
) -> list[Candidate]:
    """``extra_starts`` [(origin, T_o_s)] and global registration, each refined by ICP; returns
    all candidates, best first. RANSAC restarts (at most ``n_restarts``) stop early once the
    candidates have settled (:func:`_settled`)."""
    refined = [refine(scene, model, T, cfg, origin) for origin, T in extra_starts]
    for k, T in enumerate(global_starts(scene_down, scene_fpfh, model, cfg)):
        refined.append(refine(scene, model, T, cfg, f"ransac:{k}"))
        if _settled(refined, cfg):
            break
    return rank(refined, cfg.eval_distance_m)
