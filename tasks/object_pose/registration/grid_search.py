"""Starts for registration that need no features: a grid of rotations, each placed so that
the part of the model facing the camera sits on the scene.

FPFH + RANSAC needs distinctive local shape. A carton shows two or three flat faces, a can a
cylinder, and a small object at 0.6-1.0 m a few hundred points whose features are noise: the
global step then returns a face-to-face match turned 90 or 180 deg and displaced along a face
by centimetres (wild [9700, 0], a carton held at 0.36 m: RANSAC 90 and 180 deg off, 11 cm
away; the true pose, refined, fits better). Turning that candidate about the model's
centroid (the symmetry probes) keeps the displacement, which the first ICP level (15 mm
reach) cannot undo. Here every rotation of a grid is a start on its own: its translation
puts the centroid of the model's camera-facing surface at the scene's centroid, one coarse
ICP level refines it on a voxel grid of the scene, and the best few go on through every
level.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.geometry import inv_T, make_T, rotation_error_deg
from graspcap.tasks.object_pose.registration.engine import (
    Candidate,
    Model,
    RegistrationConfig,
    downsampled,
    rank,
    refine,
    strided,
)
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded

# open3d, scipy: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d


def rotation_grid(group: str, turns: int = 1) -> np.ndarray:
    """(k, 3, 3) rotations: scipy's point ``group`` (``"I"`` 60, ``"O"`` 24), and with
    ``turns`` > 1 each of them also composed with ``turns - 1`` further turns about the
    group's 5-fold (or 4-fold) axis by fractions of the spacing, so that the grid is denser
    than the group (``"I"`` alone leaves a rotation up to ~37 deg from its nearest member)."""
    from scipy.spatial.transform import Rotation

    base = Rotation.create_group(group)
    if turns <= 1:
        return base.as_matrix()
    axis = np.array([0.0, 0.0, 1.0])
    step = 2 * np.pi / (5 if group == "I" else 4) / turns
    extra = [Rotation.from_rotvec(axis * step * k) for k in range(turns)]
    return np.concatenate([(base * e).as_matrix() for e in extra])


def facing_centroids(model: Model, rotations: np.ndarray, view_o: np.ndarray) -> np.ndarray:
    """(k, 3) object-frame centroid of the model's samples whose normal faces the camera
    when the model is turned by each of ``rotations`` (k, 3, 3) (object into scene) and
    seen along ``view_o`` (3,) (unit, scene frame: camera towards the scene)."""
    P = np.asarray(model.coarse.points)
    N = np.asarray(model.coarse.normals)
    out = np.empty((len(rotations), 3))
    for i, R in enumerate(rotations):
        facing = N @ (R.T @ view_o) < 0
        out[i] = P[facing].mean(0) if facing.sum() >= 10 else model.centroid
    return out


@single_threaded()
def grid_candidates(
    scene: o3d.geometry.PointCloud,
    model: Model,
    cfg: RegistrationConfig,
    rotations: np.ndarray,
    viewpoint: np.ndarray | None,
    keep: int,
    voxel_m: float,
    score: Callable[[Candidate], float] | None = None,
    reach_share: float = 0.5,
    max_points: int = 800,
) -> list[Candidate]:
    """Every rotation of ``rotations`` (k, 3, 3) (object into scene) as a start, translated
    so that the model's camera-facing centroid (seen from ``viewpoint`` (3,), scene frame;
    the whole model's centroid when None) is at the scene's centroid; refined against the
    coarse model on the scene voxelised at ``voxel_m`` (at most ``max_points`` of it, an even
    stride) by ICP reaching ``reach_share`` of
    the model's radius (the centroids of a partly hidden object and of its facing surface
    are centimetres apart), then by the first ICP level. Of the distinct results
    (``ambiguity_min_deg`` or ``agree_m`` apart) the ``keep`` best by fitness and RMSE, or,
    given ``score`` (higher is better: the depth agreement, which tells a carton from its
    twin slid along a face at equal fitness), the ``keep`` best by it among twice as many,
    run every level on the whole scene. Returns those, best first."""
    pts = np.asarray(scene.points)
    if len(pts) == 0 or keep <= 0:
        return []
    centre = pts.mean(0)
    if viewpoint is None:  # seen from all round (a fused turntable scan): the whole model
        centroids = np.repeat(model.centroid[None], len(rotations), axis=0)
    else:
        view = centre - np.asarray(viewpoint, float)
        centroids = facing_centroids(model, rotations, view / max(np.linalg.norm(view), 1e-9))
    coarse = strided(downsampled(scene, voxel_m) if voxel_m > 0 else scene, max_points)
    reach = max(cfg.icp_max_distance_m[0], reach_share * model.radius_m)
    levels = [cfg.model_copy(update={"icp_voxels_m": (0.0,), "icp_max_distance_m": (d,)})
              for d in (reach, cfg.icp_max_distance_m[0])]
    found = []
    for j, (R, c_o) in enumerate(zip(rotations, centroids, strict=True)):
        T_o_s = inv_T(make_T(R, centre - R @ c_o))
        for level in levels:  # against the coarse model: a wide reach on the dense one is slow
            c = refine(coarse, model, T_o_s, level, f"grid:{j}",
                       eval_points=cfg.probe_eval_points, coarse_target=True)
            T_o_s = c.T_o_s
        found.append(c)
    distinct: list[Candidate] = []
    for c in rank(found, cfg.eval_distance_m):
        if not any(rotation_error_deg(c.T_o_s, d.T_o_s) < cfg.ambiguity_min_deg
                   and np.linalg.norm(inv_T(c.T_o_s)[:3, 3] - inv_T(d.T_o_s)[:3, 3]) <= cfg.agree_m
                   for d in distinct):
            distinct.append(c)
    if score is None:
        best = distinct[:keep]
    else:
        best = sorted(distinct[: 2 * keep], key=lambda c: -score(c))[:keep]
    out = [refine(scene, model, c.T_o_s, cfg, c.origin, first=1) if len(cfg.icp_voxels_m) > 1
           else c for c in best]
    return rank(out, cfg.eval_distance_m)
