"""The object's pose on the platter during the turntable scan (pipeline item 8).

The object was put back in a new pose, so stage 1 is no help. Every view's
depth is cropped to the platter and brought into the turntable frame at angle
0 (``p_t0 = Rz(angle)^-1 @ T_color_turntable^-1 @ p_color``); the views are
fused (normals estimated per view, facing that view's camera) and the mesh is
registered against the fused cloud at once: FPFH + RANSAC with restarts, then
point-to-plane ICP, then the symmetry probes of stage 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.tasks.config import StageConfig
from graspcap.tasks.errors import StageError
from graspcap.tasks.geometry import inv_T, rot_z, transform_points
from graspcap.tasks.registration import (
    PlatterCrop,
    RegistrationConfig,
    crop_platter,
    distinct_from,
    estimate_normals,
    evaluate,
    prepare_model,
    prepare_scene,
    probe_symmetry,
    register,
    to_pcd,
)

STAGE_VERSION = "register_scan/2"
STAGE = "register_scan"


class RegisterScanConfig(StageConfig):
    """Crop, per-view acceptance and registration settings."""

    crop: PlatterCrop = PlatterCrop()
    """Where the object is looked for in every view."""
    min_view_points: int = 100
    """A view with fewer points over the platter is skipped."""
    min_fitness: float = 0.5
    """A fused registration with a lower fitness fails the stage."""
    check_ambiguity: bool = True
    """Run the symmetry probes on the fused cloud."""
    registration: RegistrationConfig = RegistrationConfig()
    """Global registration and ICP settings."""


PRESETS: dict[str, RegisterScanConfig] = {
    "default": RegisterScanConfig(),
    "fast": RegisterScanConfig(
        check_ambiguity=False, registration=RegistrationConfig(n_restarts=2)
    ),
}


@dataclass(frozen=True)
class ScanRegistration:
    """Result of :func:`register_scan`.

    Attributes
    ----------
    T_turntable_o_scan : (4, 4) float
        Object pose in the turntable frame at angle 0.
    fitness, inlier_rmse_m : float
        Over the fused cloud: share of points within ``eval_distance_m`` of the mesh, their RMSE.
    n_points : int
        Points in the fused cloud (after the finest ICP voxel).
    per_view_fitness : (n_views,) float
        Fitness of each view's own points under the final pose; NaN for skipped views.
    per_view_points : (n_views,) int
        Points over the platter in each view.
    ambiguous : bool
        A distinct pose explains the fused cloud as well (symmetric object).
    ambiguity_deg : float
        Rotation to that runner-up (0 when there is none).
    """

    T_turntable_o_scan: np.ndarray
    fitness: float
    inlier_rmse_m: float
    n_points: int
    per_view_fitness: np.ndarray
    per_view_points: np.ndarray
    ambiguous: bool
    ambiguity_deg: float


def register_scan(
    views: list[tuple[np.ndarray, float]],
    K: np.ndarray,
    T_color_turntable: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    config: RegisterScanConfig = PRESETS["default"],
) -> ScanRegistration:
    """Register the mesh against all scan views fused in the turntable frame.

    Parameters
    ----------
    views : list of (depth_m (h, w) float, angle_rad float)
        Depth of each view and the platter's rotation about its z axis.
    K : (3, 3) float
        Depth (= colour) intrinsics.
    T_color_turntable : (4, 4) float
        Turntable frame in the colour frame.
    mesh_vertices, mesh_faces : (n, 3) float, (m, 3) int
        Object mesh, object frame, metres.
    """
    cfg = config.registration
    T_t_c = inv_T(np.asarray(T_color_turntable, float))
    per_view, counts, pts_all, nrm_all = [], [], [], []
    for depth_m, angle in views:
        pts_c = crop_platter(depth_m, K, T_color_turntable, config.crop)
        counts.append(len(pts_c))
        if len(pts_c) < config.min_view_points:
            per_view.append(None)
            continue
        pcd = to_pcd(pts_c)
        estimate_normals(pcd, cfg.normal_radius_factor * cfg.voxel_m, np.zeros(3))
        T_t0_c = rot_z(-angle) @ T_t_c
        pts_t0 = transform_points(T_t0_c, pts_c)
        per_view.append(pts_t0)
        pts_all.append(pts_t0)
        nrm_all.append(np.asarray(pcd.normals) @ T_t0_c[:3, :3].T)
    if not pts_all:
        raise StageError(
            STAGE,
            f"no valid view: none of the {len(views)} views has {config.min_view_points} depth "
            "points over the platter (empty platter, bad depth or turntable calibration)",
        )
    model = prepare_model(mesh_vertices, mesh_faces, cfg)
    scene, down, feats = prepare_scene(
        np.concatenate(pts_all), np.concatenate(nrm_all), np.zeros(3), cfg
    )
    candidates = register(scene, down, feats, model, cfg)
    if config.check_ambiguity:
        candidates = probe_symmetry(scene, model, candidates, cfg)
    best = candidates[0]
    if best.fitness < config.min_fitness:
        raise StageError(
            STAGE,
            f"registration fitness {best.fitness:.2f} below {config.min_fitness:.2f}: the mesh "
            "does not explain the fused scan (wrong object, mesh units or turntable angles?)",
        )
    amb = distinct_from(best, candidates[1:], cfg)
    fits = [
        np.nan if p is None else evaluate(to_pcd(p), model, best.T_o_s, cfg.eval_distance_m)[0]
        for p in per_view
    ]
    return ScanRegistration(
        T_turntable_o_scan=inv_T(best.T_o_s),
        fitness=best.fitness,
        inlier_rmse_m=best.inlier_rmse_m,
        n_points=len(scene.points),
        per_view_fitness=np.asarray(fits, float),
        per_view_points=np.asarray(counts, int),
        ambiguous=amb.ambiguous,
        ambiguity_deg=amb.ambiguity_deg,
    )
