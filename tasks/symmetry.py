"""The symmetry check of registration: is another pose as good as the best?

The best pose is turned about the model's principal axes (or by every rotation of a point
group) about its centroid and re-fitted by ICP (:func:`probe_symmetry`); a distinct pose that
explains the scene about as well makes the result ambiguous (:func:`distinct_from`). Shared
by :mod:`register_object`, :mod:`estimate_adjustment` and :mod:`register_scan`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import trimesh

from graspcap.tasks.geometry import inv_T, make_T, rotation_error_deg
from graspcap.tasks.open3d_threads import single_threaded
from graspcap.tasks.registration import Candidate, Model, RegistrationConfig, rank, refine


def about_axis(model: Model, axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Object-frame rotation (4, 4) by ``angle_rad`` about ``axis`` through the model centroid."""
    R = trimesh.transformations.rotation_matrix(angle_rad, axis)[:3, :3]
    return make_T(R, model.centroid - R @ model.centroid)


@dataclass(frozen=True)
class Ambiguity:
    """Outcome of the symmetry check.

    Attributes
    ----------
    ambiguous : bool
        A pose at least ``ambiguity_min_deg`` away explains the data about as well.
    ambiguity_deg : float
        Rotation between the best pose and the runner-up (0 when there is none).
    runner_up : Candidate or None
        Best candidate distinct from the winner.
    """

    ambiguous: bool
    ambiguity_deg: float
    runner_up: Candidate | None


def as_good_as(c: Candidate, best: Candidate, cfg: RegistrationConfig) -> bool:
    """``c`` explains the scene as well as ``best`` within the ambiguity tolerances."""
    excess_sq = max(c.inlier_rmse_m**2 - best.inlier_rmse_m**2, 0.0)
    return (
        c.fitness >= best.fitness - cfg.ambiguity_fitness_tol
        and excess_sq <= cfg.ambiguity_excess_rmse_m**2
    )


def distinct_from(best: Candidate, others: list[Candidate], cfg: RegistrationConfig) -> Ambiguity:
    """Compare ``best`` with the best of ``others`` that is a distinct rotation."""
    distinct = [
        c for c in others if rotation_error_deg(c.T_o_s, best.T_o_s) >= cfg.ambiguity_min_deg
    ]
    if not distinct:
        return Ambiguity(False, 0.0, None)
    runner = rank(distinct, cfg.eval_distance_m)[0]
    angle = rotation_error_deg(runner.T_o_s, best.T_o_s)
    return Ambiguity(as_good_as(runner, best, cfg), angle, runner)


@single_threaded()
def probe_symmetry(
    scene: o3d.geometry.PointCloud,
    model: Model,
    candidates: list[Candidate],
    cfg: RegistrationConfig,
    rotations: np.ndarray | None = None,
    stop_when: Callable[[Candidate], bool] | None = None,
    gate: Callable[[Candidate], bool] | None = None,
) -> list[Candidate]:
    """Re-run ICP from the best of ``candidates`` (ranked) turned about each principal axis
    of the model by ``cfg.probe_angles_deg``, or, when ``rotations`` (k, 3, 3) are given, by
    each of them (expressed in the principal-axes frame, turned about the centroid); returns
    every candidate, the probes included, best first (a probe may beat the global step).
    ``stop_when``, when given, is asked about every fully refined probe in turn: True ends the
    probing (a search for a better pose that found one). A probe runs the ICP levels after
    ``cfg.probe_levels`` when its fitness comes within twice the ambiguity tolerance of the
    best's and ``gate`` (when given) passes it too. Pass the result to :func:`distinct_from`."""
    best = candidates[0]
    probes = list(candidates)
    starts: list[tuple[str, np.ndarray]] = []
    if rotations is None:
        for i in range(3):
            for angle in cfg.probe_angles_deg:
                T_probe = about_axis(model, model.axes[:, i], np.radians(angle))
                starts.append((f"probe:{i}:{angle:g}", T_probe))
    else:
        A = model.axes
        for j, R in enumerate(np.asarray(rotations, float)):
            R_o = A @ R @ A.T
            starts.append((f"probe:grid:{j}", make_T(R_o, model.centroid - R_o @ model.centroid)))
    for origin, T_probe in starts:
        start = inv_T(T_probe) @ best.T_o_s
        c = refine(
            scene, model, start, cfg, origin, stop=cfg.probe_levels,
            eval_points=cfg.probe_eval_points, coarse_target=True,
        )  # fmt: skip
        goes_on = c.fitness >= best.fitness - 2 * cfg.ambiguity_fitness_tol
        goes_on = goes_on and (gate is None or gate(c))
        if goes_on:
            c = refine(scene, model, c.T_o_s, cfg, origin, first=cfg.probe_levels)
        probes.append(c)
        if goes_on and stop_when is not None and stop_when(c):
            break
    return rank(probes, cfg.eval_distance_m)
