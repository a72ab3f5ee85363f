"""Stage 1: the object's pose on the turntable from one depth image.

Depth -> camera-frame cloud -> crop to the space over the platter (turntable
frame) -> FPFH + RANSAC with restarts -> coarse-to-fine point-to-plane ICP
against the mesh surface. Near-symmetric objects are reported, not hidden:
the best pose is turned about the mesh's principal axes and re-fitted, and a
distinct pose that explains the depth as well makes the result ``ambiguous``.
The method does not use the fact that the object rests on the platter beyond
the crop, so it also works for objects leaning on something.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.tasks.config import StageConfig
from graspcap.tasks.errors import StageError
from graspcap.tasks.geometry import inv_T
from graspcap.tasks.registration import (
    PlatterCrop,
    RegistrationConfig,
    crop_platter,
    distinct_from,
    prepare_model,
    prepare_scene,
    probe_symmetry,
    register,
    valid_depth,
)

STAGE_VERSION = "register_object/1"
STAGE = "register_object"


class RegisterObjectConfig(StageConfig):
    """Crop of the platter region and the registration settings."""

    crop: PlatterCrop = PlatterCrop()
    """Where the object is looked for."""
    min_points: int = 200
    """Fewer points over the platter than this means no object was found."""
    min_fitness: float = 0.5
    """Registration with a lower fitness (share of cropped points explained) fails the stage."""
    check_ambiguity: bool = True
    """Run the symmetry probes (ICP from the best pose turned about the principal axes)."""
    registration: RegistrationConfig = RegistrationConfig()
    """Global registration and ICP settings."""


PRESETS: dict[str, RegisterObjectConfig] = {
    "default": RegisterObjectConfig(),
    "fast": RegisterObjectConfig(
        check_ambiguity=False, registration=RegistrationConfig(n_restarts=2)
    ),
    "thorough": RegisterObjectConfig(
        registration=RegistrationConfig(
            n_restarts=8, probe_angles_deg=(45, 90, 135, 180, 225, 270, 315)
        )
    ),
}


@dataclass(frozen=True)
class ObjectRegistration:
    """Result of stage 1.

    Attributes
    ----------
    T_w_o : (4, 4) float
        Object pose in the colour camera frame (= world).
    fitness : float
        Share of the cropped points within ``eval_distance_m`` of the posed mesh.
    inlier_rmse_m : float
        RMSE of those inliers, metres.
    n_points : int
        Points over the platter that were registered.
    ambiguous : bool
        A pose at least ``ambiguity_min_deg`` away explains the depth about as well.
    ambiguity_deg : float
        Rotation between ``T_w_o`` and the runner-up (0 when there is none).
    T_w_o_runner_up : (4, 4) float or None
        Best pose distinct from ``T_w_o``.
    runner_up_fitness, runner_up_rmse_m : float
        Its fitness and inlier RMSE (0 when there is none).
    """

    T_w_o: np.ndarray
    fitness: float
    inlier_rmse_m: float
    n_points: int
    ambiguous: bool
    ambiguity_deg: float
    T_w_o_runner_up: np.ndarray | None
    runner_up_fitness: float
    runner_up_rmse_m: float


def register_object(
    depth_m: np.ndarray,
    K: np.ndarray,
    T_color_turntable: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    config: RegisterObjectConfig = PRESETS["default"],
) -> ObjectRegistration:
    """Register the object mesh in the stage-1 depth image.

    Parameters
    ----------
    depth_m : (h, w) float
        Depth aligned to the colour camera, metres; 0 = invalid.
    K : (3, 3) float
        Colour intrinsics.
    T_color_turntable : (4, 4) float
        Turntable frame (origin at the centre of the platter top, z up) in the colour frame.
    mesh_vertices : (n, 3) float
        Object mesh vertices, object frame, metres.
    mesh_faces : (m, 3) int
        Triangles.
    """
    cfg = config.registration
    if not valid_depth(depth_m, config.crop.max_range_m).any():
        raise StageError(STAGE, "depth image has no valid pixel (all zero, NaN or out of range)")
    points = crop_platter(depth_m, K, T_color_turntable, config.crop)
    if len(points) < config.min_points:
        raise StageError(
            STAGE,
            f"object not found on the platter: {len(points)} depth points over it "
            f"(need {config.min_points}); check the turntable calibration and the crop",
        )
    model = prepare_model(mesh_vertices, mesh_faces, cfg)
    scene, down, feats = prepare_scene(points, None, np.zeros(3), cfg)
    candidates = register(scene, down, feats, model, cfg)
    best = candidates[0]
    if best.fitness < config.min_fitness:
        raise StageError(
            STAGE,
            f"registration fitness {best.fitness:.2f} below {config.min_fitness:.2f}: the mesh "
            "does not explain the depth over the platter (wrong object or mesh units?)",
        )
    if config.check_ambiguity:
        candidates = probe_symmetry(scene, model, candidates, cfg)
    best = candidates[0]
    amb = distinct_from(best, candidates[1:], cfg)
    runner = amb.runner_up
    return ObjectRegistration(
        T_w_o=inv_T(best.T_o_s),
        fitness=best.fitness,
        inlier_rmse_m=best.inlier_rmse_m,
        n_points=len(points),
        ambiguous=amb.ambiguous,
        ambiguity_deg=amb.ambiguity_deg,
        T_w_o_runner_up=None if runner is None else inv_T(runner.T_o_s),
        runner_up_fitness=0.0 if runner is None else runner.fitness,
        runner_up_rmse_m=0.0 if runner is None else runner.inlier_rmse_m,
    )
