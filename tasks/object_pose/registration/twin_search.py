"""The pose among a global registration's candidates and their twins (estimate_adjustment's
global path): grid starts, symmetry probes, free turns, and the choice among equals.

One frame shows one side of the object, partly hidden by the hand, so the global step's best
candidate is often a twin of the truth: turned half a turn, or about an axis the depth leaves
free. :func:`search_twins` scores candidates by fitness times depth agreement (``agree``),
adds feature-free grid starts (:mod:`grid_search`) while the best agrees poorly, probes the
object's symmetries (:mod:`symmetry`) from the best, in rounds, and with ill-defined
principal axes turns the best about its free rotation (:mod:`free_rotation`). Among the poses
that explain the depth equally well, the one nearest in rotation to a reference pose
(register_object's) is chosen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING, Protocol

import numpy as np

from graspcap.tasks.core.geometry import inv_T, rotation_error_deg
from graspcap.tasks.object_pose.registration.engine import (
    Candidate,
    Model,
    RegistrationConfig,
    rank,
    refine,
    tls_cost,
)
from graspcap.tasks.object_pose.registration.free_rotation import free_axis, free_starts
from graspcap.tasks.object_pose.registration.grid_search import grid_candidates, rotation_grid
from graspcap.tasks.object_pose.registration.symmetry import (
    as_good_as,
    axes_ill_defined,
    probe_symmetry,
    self_flip_axes,
)

# open3d: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import open3d as o3d


class TwinSearchConfig(Protocol):
    """The settings :func:`search_twins` reads (``EstimateAdjustmentConfig``'s, documented
    there)."""

    grid_group: str
    grid_keep: int
    reprobe_below: float
    check_ambiguity: bool
    ill_defined_ratio: float
    flip_probes: bool
    probe_rounds: int
    free_turns: bool
    tie_tol: float


def search_twins(
    scene: o3d.geometry.PointCloud,
    down: o3d.geometry.PointCloud,
    region: np.ndarray,
    model: Model,
    candidates: list[Candidate],
    T_w_o1: np.ndarray,
    agree: Callable[[np.ndarray], float],
    cfg: RegistrationConfig,
    config: TwinSearchConfig,
    cache: dict,
) -> tuple[Candidate, list[Candidate]]:
    """(the chosen candidate, its twins) among ``candidates`` (ranked: the global step's and
    ICP from ``T_w_o1``) and the twins found from them. ``scene``, ``down``: the region's
    clouds (``engine.prepare_scene``), ``region`` (n, 3) its points; ``T_w_o1`` (4, 4): the
    reference pose (ties go to the rotation nearest it); ``agree``: a pose ``T_w_o``'s depth
    agreement in [0, 1]. ``cache``: shared by every call on the same region (the grid's
    candidates, the scores), whatever ``T_w_o1``. The twins: the poses at least
    ``cfg.ambiguity_min_deg`` away that explain the depth as well (none: not ambiguous)."""
    # near-equal candidates are compared on fitness times depth agreement (a carton's twin:
    # 0.99 x 0.91, the truth 1.0 x 1.0); while the best agrees poorly, probes run from it
    scores: dict[Candidate, Candidate] = cache.setdefault("scores", {})

    def score(c: Candidate) -> float:
        if c not in scores:
            scores[c] = replace(c, fitness=c.fitness * agree(inv_T(c.T_o_s)))
        return scores[c].fitness

    def combined(cands: list[Candidate]) -> list[Candidate]:
        top = cands[0].fitness - 2 * cfg.ambiguity_fitness_tol
        for c in cands:
            if c.fitness >= top:
                score(c)
        kept = [scores[c] for c in cands if c in scores]
        return sorted(kept, key=lambda c: (tls_cost(c, cfg.eval_distance_m), c.origin))

    def lead_of(scored: list[Candidate]) -> Candidate:
        return next(c for c in candidates if scores.get(c) is scored[0])

    lead = max(candidates[:3], key=score)
    if config.grid_group and ("grid" in cache or score(lead) < config.reprobe_below):
        # starts without features (a carton's faces, a small far object), unless the global
        # step found a pose the depth already explains
        if "grid" not in cache:
            cache["grid"] = grid_candidates(
                scene, model, cfg, rotation_grid(config.grid_group), np.zeros(3),
                config.grid_keep, cfg.voxel_m, score,
            )  # fmt: skip
        candidates = rank([*candidates, *cache["grid"]], cfg.eval_distance_m)
    centre = candidates[0]  # the pose the symmetry probes turn
    # the model's own near-symmetries are probed too: a mug's principal axes are arbitrary
    # (held-out mug [9900, 7]: its handle-axis twin at agreement 0.71, the truth at 1.0)
    mixed = config.check_ambiguity and axes_ill_defined(model, config.ill_defined_ratio)
    flips = mixed and config.flip_probes
    probe = partial(probe_symmetry, flip_axes=self_flip_axes(model) if flips else None)
    if config.check_ambiguity:
        candidates = probe(scene, model, candidates, cfg)
        if centre is not lead and lead in candidates:
            # the grid displaced the global step's best: its twins are probed too (lifted mug
            # seed 2, 120 deg: a grid pose 9 deg off at 0.97 led, the truth at 0.998 is a
            # turn of the global step's pose; which one led hung on a handful of depth pixels)
            rest = [c for c in candidates if c is not lead]
            candidates = probe(scene, model, [lead, *rest], cfg)
    scored = combined(candidates)
    for _ in range(config.probe_rounds if config.check_ambiguity else 0):
        if scored[0].fitness >= config.reprobe_below:
            break
        centre = lead_of(scored)
        rest = [c for c in candidates if c is not centre]
        candidates = probe(
            scene, model, [centre, *rest], cfg, None, lambda c: score(c) >= config.reprobe_below
        )
        before, scored = scored[0], combined(candidates)
        if scored[0] is before:
            break
    if config.check_ambiguity and lead_of(scored) is not centre:
        # a probe beat the pose the probes turned: only probes turning the new best find
        # its own twins (realistic carton [9000, 0]: the truth was never a candidate)
        centre = lead_of(scored)
        rest = [c for c in candidates if c is not centre]
        candidates = probe(scene, model, [centre, *rest], cfg)
        scored = combined(candidates)
    if mixed and config.free_turns:
        # held-out mug [9900, 4], handle hidden: the truth never a candidate, its twin kept
        free = free_axis(np.asarray(down.points), np.asarray(down.normals))
        starts = free_starts(inv_T(lead_of(scored).T_o_s), free, T_w_o1[:3, :3], region.mean(0))
        turns = [refine(scene, model, inv_T(T), cfg, origin) for origin, T in starts]
        scored = combined(rank([*candidates, *turns], cfg.eval_distance_m))
    candidates = scored
    best = candidates[0]
    equal = [c for c in candidates if as_good_as(c, best, cfg)]
    tied = [c for c in equal if c.fitness >= best.fitness - config.tie_tol]
    nearest: Candidate = min(
        tied, key=lambda c: rotation_error_deg(inv_T(c.T_o_s)[:3, :3], T_w_o1[:3, :3])
    )
    # poses closer than ambiguity_min_deg are one solution: its best-scoring one (a probe
    # can slide along a flat face, same rotation, 30 mm off, scoring a little lower)
    chosen = next(
        c for c in tied if rotation_error_deg(c.T_o_s, nearest.T_o_s) < cfg.ambiguity_min_deg
    )
    twins = [c for c in equal if rotation_error_deg(c.T_o_s, chosen.T_o_s) >= cfg.ambiguity_min_deg]
    return chosen, twins
