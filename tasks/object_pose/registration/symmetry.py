"""The symmetry check of registration: is another pose as good as the best?

The best pose is turned about the model's principal axes (or by every rotation of a point
group) about its centroid and re-fitted by ICP (:func:`probe_symmetry`); a distinct pose that
explains the scene about as well makes the result ambiguous (:func:`distinct_from`). Shared
by :mod:`register_object`, :mod:`estimate_adjustment` and :mod:`register_scan`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.core.geometry import inv_T, make_T, rotation_error_deg, transform_points
from graspcap.tasks.object_pose.registration.engine import (
    Candidate,
    Model,
    RegistrationConfig,
    rank,
    refine,
    strided,
    surface_distance,
)
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded

# open3d, trimesh: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d


def about_axis(model: Model, axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Object-frame rotation (4, 4) by ``angle_rad`` about ``axis`` through the model centroid."""
    import trimesh

    R = trimesh.transformations.rotation_matrix(angle_rad, axis)[:3, :3]
    return make_T(R, model.centroid - R @ model.centroid)


def _hemisphere(n: int) -> np.ndarray:
    """``n`` (n, 3) unit directions spread evenly over the upper hemisphere (Fibonacci)."""
    i = np.arange(n) + 0.5
    z = i / n
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def axes_ill_defined(model: Model, ratio: float) -> bool:
    """Two of the model's principal spreads (RMS extents along its principal axes) are within
    ``ratio`` of each other, so those axes are mixed arbitrarily within their plane (the mug
    0.968: 54 deg off its handle's axis; a bottle 0.968; carton 0.78, spray bottle 0.71,
    drill 0.65) and half turns about them may miss the object's own near-symmetries."""
    pts = np.asarray(model.dense.points)
    s = np.linalg.svd(pts - model.centroid, compute_uv=False)  # largest first
    return bool(np.any(s[1:] >= ratio * s[:-1]))


def revolution_axis(model: Model, tolerance_m: float, points: int = 800) -> np.ndarray | None:
    """The model's axis of (near) revolution (3,), object frame, through its centroid, or None:
    the principal axis about which turns of 30, 60, ... 330 deg move none of ``points``
    surface samples further than ``tolerance_m`` from the surface (the evaluation's test,
    ``graspcap.synth.symmetry``, on the principal axes alone: a can with its tab, a bulb, a
    ball; not a bottle with its cap off the axis, a mug, a box)."""
    pts = np.asarray(strided(model.dense, points).points)
    for k in range(3):
        axis = model.axes[:, k]
        moved = np.concatenate([transform_points(about_axis(model, axis, np.radians(a)), pts)
                                for a in range(30, 360, 30)])
        if float(surface_distance(model, moved).max()) <= tolerance_m:
            return axis / np.linalg.norm(axis)
    return None


def moved_share(model: Model, T_o_o: np.ndarray, moved_m: float, points: int = 500) -> float:
    """The share of the model's surface an object-frame motion ``T_o_o`` (4, 4) moves more than
    ``moved_m`` off the surface (``points`` samples). 0 for a motion the shape is symmetric
    under; a mug's half turn about its handle's axis moves a quarter of it more than 3 mm, a
    carton's about its long axis the spout and ridge, 7 %."""
    pts = np.asarray(strided(model.coarse, points).points)
    return float((surface_distance(model, transform_points(T_o_o, pts)) > moved_m).mean())


_FLIPS: dict[int, tuple[Model, np.ndarray]] = {}
"""Recent :func:`self_flip_axes` results by model (the model kept alive beside them)."""


def self_flip_axes(
    model: Model, count: int = 2, samples: int = 100, points: int = 500, cap_m: float = 0.02
) -> np.ndarray:
    """The model's own near-symmetries: the ``count`` axes (k, 3), object frame, at least
    30 deg apart, about which a half turn through the centroid maps its surface onto itself
    best (least mean distance of ``points`` samples to the mesh, each capped at ``cap_m``:
    a part that misses counts fully), among the principal axes and ``samples`` axes over a
    hemisphere, each refined by a hill climb (4, 2, 1 deg steps). Unlike the principal axes
    they do not depend on the spreads being distinct: a mug's two largest spreads are within
    3 %, its principal axes 54 deg away from its handle's axis, the half turn about which
    maps it onto itself (3.0 mm; about its principal axes 5.1-7.1 mm)."""
    key = hash((id(model), count, samples, points, cap_m))
    if key in _FLIPS and _FLIPS[key][0] is model:
        return _FLIPS[key][1]
    pts = np.asarray(strided(model.coarse, points).points)

    def cost(axes: np.ndarray) -> np.ndarray:
        moved = np.concatenate([transform_points(about_axis(model, a, np.pi), pts) for a in axes])
        return np.minimum(surface_distance(model, moved), cap_m).reshape(len(axes), -1).mean(1)

    def climb(a: np.ndarray, c: float) -> np.ndarray:
        for step in np.tan(np.radians([4.0, 2.0, 1.0])):
            for _ in range(8):
                u = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
                u /= np.linalg.norm(u)
                near = a + step * np.array([u, -u, np.cross(a, u), -np.cross(a, u)])
                near /= np.linalg.norm(near, axis=1, keepdims=True)
                costs = cost(near)
                if costs.min() >= c:
                    break
                a, c = near[int(np.argmin(costs))], float(costs.min())
        return a

    axes = np.vstack([model.axes.T, _hemisphere(samples)])
    costs = cost(axes)
    kept: list[np.ndarray] = []
    for i in np.argsort(costs, kind="stable"):
        if len(kept) == count:
            break
        if all(abs(axes[i] @ b) < np.cos(np.radians(30.0)) for b in kept):
            kept.append(climb(axes[i], float(costs[i])))
    result = np.array(kept)
    if len(_FLIPS) >= 8:
        _FLIPS.pop(next(iter(_FLIPS)))
    _FLIPS[key] = (model, result)
    return result


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
    flip_axes: np.ndarray | None = None,
) -> list[Candidate]:
    """Re-run ICP from the best of ``candidates`` (ranked) turned about each principal axis
    of the model by ``cfg.probe_angles_deg``, or, when ``rotations`` (k, 3, 3) are given, by
    each of them (expressed in the principal-axes frame, turned about the centroid); returns
    every candidate, the probes included, best first (a probe may beat the global step).
    ``stop_when``, when given, is asked about every fully refined probe in turn: True ends the
    probing (a search for a better pose that found one). A probe runs the ICP levels after
    ``cfg.probe_levels`` when its fitness comes within twice the ambiguity tolerance of the
    best's and ``gate`` (when given) passes it too. ``flip_axes`` (k, 3), object frame: half
    turns about them are probes too, after the others (:func:`self_flip_axes`). Pass the
    result to :func:`distinct_from`."""
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
    for j, axis in enumerate(() if flip_axes is None else flip_axes):
        # a half turn about a principal axis is probed already
        if rotations is None and 180.0 in cfg.probe_angles_deg and np.abs(
            axis @ model.axes).max() >= np.cos(np.radians(5.0)):  # fmt: skip
            continue
        starts.append((f"probe:flip:{j}", about_axis(model, axis, np.pi)))
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
