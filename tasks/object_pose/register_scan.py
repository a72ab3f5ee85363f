"""The object's pose on the platter during the turntable scan (pipeline item 8).

The object was put back in a new pose, so register_object's pose is no help. Every view's
depth is cropped to the platter and brought into the turntable frame at angle
0 (``p_t0 = Rz(angle)^-1 @ T_color_turntable^-1 @ p_color``); the views are
fused (normals estimated per view, facing that view's camera) and the mesh is
registered against the fused cloud at once: FPFH + RANSAC with restarts, then
point-to-plane ICP, then the symmetry probes of register_object.

Candidates are ranked by their fitness times the share of the mesh's surface samples that
no view sees through (:mod:`scan_free_space`). The fitness alone cannot tell a mug from the
same mug upside down on its rim (registered 180 deg off, 100 mm up, at fitness 0.992
against the true pose's 0.998, and RANSAC found the flipped basin 7 times in 8): model
surface where the views saw empty space is what gives it away. While the best pose still
leaves more than ``grid_above`` of the mesh in seen-empty space, the probes also try every
rotation of a point group (the mug's flip axis lies between its principal axes).

Views at the same platter angle (a view captured twice) are all used: they are more data of
the same side. ``notes`` names them with each one's fitness under the final pose, so a view
whose ``angle_deg`` is wrong (it does not fit where its twin does) can be found.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError, check_mesh
from graspcap.tasks.core.geometry import inv_T, rot_z, transform_points
from graspcap.tasks.core.mesh_proxy import PROXY_FACES, mesh_proxy
from graspcap.tasks.object_pose.registration.engine import (
    Candidate,
    RegistrationConfig,
    evaluate,
    prepare_model,
    prepare_scene,
    register,
    strided,
    tls_cost,
)
from graspcap.tasks.object_pose.registration.grid_search import grid_candidates, rotation_grid
from graspcap.tasks.object_pose.registration.point_clouds import (
    PlatterCrop,
    crop_platter,
    estimate_normals,
    platter_depth,
    to_pcd,
)
from graspcap.tasks.object_pose.registration.symmetry import distinct_from, probe_symmetry
from graspcap.tasks.object_pose.scan_free_space import free_space_violation, prepare_views

# scipy: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "register_scan/6"
STAGE = "register_scan"


class RegisterScanConfig(StageConfig):
    """Crop, per-view acceptance and registration settings."""

    crop: PlatterCrop = PlatterCrop(fit_platter=True)
    """Where the object is looked for in every view: over the platter top as that view's
    depth shows it (as ``register_object``'s; wild [80625, 4]: fitness 0.48 over the
    calibrated platter, its raised top kept as the object)."""
    min_view_points: int = 100
    """A view with fewer points over the platter is skipped."""
    min_fitness: float = 0.5
    """A fused registration with a lower fitness fails the stage."""
    check_ambiguity: bool = True
    """Run the symmetry probes on the fused cloud."""
    check_free_space: bool = True
    """Rank candidates by fitness times (1 - free-space violation): the share of the posed
    mesh's surface samples that some view sees through counts against a pose. Off ranks by
    fitness and RMSE alone (``register_scan/2``)."""
    free_space_tol_m: float = 0.005
    """A view sees through a model point when its depth is this much further than the point."""
    free_space_window_px: int = 3
    """The depth is eroded to the nearest valid depth in this window (silhouette pixels)."""
    free_space_points: int = 3000
    """At most this many mesh surface samples (even stride) are projected into the views."""
    probe_grid: str = "O"
    """Extra probes: every rotation of this point group (scipy ``Rotation.create_group``,
    ``"O"`` 24, ``"I"`` 60) about the model's centroid and principal axes, applied to the best
    pose; ``""`` for none. They run only while the free space contradicts the best pose."""
    grid_above: float = 0.05
    """The grid probes run while the best pose's free-space violation is above this."""
    probe_rounds: int = 2
    """Passes over the grid (another pass starts from a new best pose)."""
    ambiguous_violation: float = 0.01
    """A distinct pose is as good only if its free-space violation exceeds the best's by at
    most this much (on top of the fitness and RMSE tolerances of ``registration``)."""
    grid_group: str = "I"
    """While the best pose scores (fitness times one minus its free-space violation) below
    ``grid_below``, ICP also starts from every rotation of this point group at the fused
    cloud's centroid (:mod:`grid_search`; ``""`` off)."""
    grid_below: float = 0.95
    """See ``grid_group``. A right realistic scan scores 0.96-0.98 (its free-space violation
    is ~0.02 by silhouette pixels alone); the realistic mug RANSAC missed scored 0.91."""
    grid_keep: int = 4
    """Grid starts (the best by that score) refined through every level."""
    proxy_faces: int = Field(PROXY_FACES, ge=1000)
    """A mesh with more faces is registered as a proxy of about this many (:mod:`mesh_proxy`)."""
    registration: RegistrationConfig = RegistrationConfig()
    """Global registration and ICP settings."""


PRESETS: dict[str, RegisterScanConfig] = {
    "default": RegisterScanConfig(),
    "fast": RegisterScanConfig(
        check_ambiguity=False, probe_rounds=1, registration=RegistrationConfig(n_restarts=2)
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
    free_space_violation : float
        Share of the posed mesh's surface samples (over the views that judge them) that a view
        sees through; NaN when not checked.
    T_turntable_o_runner_up : (4, 4) float or None
        Best pose at least ``ambiguity_min_deg`` away from the result.
    runner_up_fitness, runner_up_free_space_violation : float
        Its fitness and free-space violation (NaN when there is none).
    note : str
        Why the pose may be wrong (ambiguous, or contradicted by the views); empty when none.
    notes : tuple of str
        What changes no verdict: views at the same platter angle, views skipped.
    """

    T_turntable_o_scan: np.ndarray
    fitness: float
    inlier_rmse_m: float
    n_points: int
    per_view_fitness: np.ndarray
    per_view_points: np.ndarray
    ambiguous: bool
    ambiguity_deg: float
    free_space_violation: float
    T_turntable_o_runner_up: np.ndarray | None
    runner_up_fitness: float
    runner_up_free_space_violation: float
    note: str
    notes: tuple[str, ...] = ()


def register_scan(
    views: list[tuple[np.ndarray, float]],
    K: np.ndarray,
    T_color_turntable: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    config: RegisterScanConfig = PRESETS["default"],
    *,
    view_names: Sequence[str] | None = None,
    mesh_name: str = "the object mesh",
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
    view_names, mesh_name : optional
        The views' depth files and the mesh file, for messages and notes.
    """
    cfg = config.registration
    names = [f"view {k}" for k in range(len(views))] if view_names is None else [
        f"view {k} ({n})" for k, n in enumerate(view_names)]
    if len(names) != len(views):
        raise ValueError(f"{len(names)} view names for {len(views)} views")
    check_mesh(STAGE, mesh_vertices, mesh_faces, name=mesh_name)
    proxy = mesh_proxy(mesh_vertices, mesh_faces, config.proxy_faces)
    proxy_notes = [] if proxy.is_original else [proxy.note(len(mesh_faces), "registered")]
    mesh_vertices, mesh_faces = proxy.vertices, proxy.faces
    for name, (depth_m, _) in zip(names, views, strict=True):
        if np.ndim(depth_m) != 2:
            raise StageError(STAGE, f"{name} depth has shape {np.shape(depth_m)}, expected (h, w)")
    T_turntable_color = inv_T(np.asarray(T_color_turntable, float))
    views = [(platter_depth(d, K, config.crop), a) for d, a in views]  # the free space's too
    per_view, counts, pts_all, nrm_all = [], [], [], []
    for depth_m, angle in views:
        pts_c = crop_platter(depth_m, K, T_color_turntable, config.crop, prepared=True)
        counts.append(len(pts_c))
        if len(pts_c) < config.min_view_points:
            per_view.append(None)
            continue
        pcd = to_pcd(pts_c)
        estimate_normals(pcd, cfg.normal_radius_factor * cfg.voxel_m, np.zeros(3))
        T_t0_c = rot_z(-angle) @ T_turntable_color
        pts_t0 = transform_points(T_t0_c, pts_c)
        per_view.append(pts_t0)
        pts_all.append(pts_t0)
        nrm_all.append(np.asarray(pcd.normals) @ T_t0_c[:3, :3].T)
    if not pts_all:
        raise StageError(
            STAGE,
            f"no valid view: none of the {len(views)} views has {config.min_view_points} depth "
            "points over the platter (empty platter, bad depth or turntable calibration; "
            f"points per view: {counts})",
        )
    model = prepare_model(mesh_vertices, mesh_faces, cfg)
    scene, down, feats = prepare_scene(
        np.concatenate(pts_all), np.concatenate(nrm_all), np.zeros(3), cfg
    )
    candidates = register(scene, down, feats, model, cfg)
    violation = _violation_of(views, K, T_turntable_color, model, config)
    candidates = _ranked(candidates, violation, cfg)
    if config.check_ambiguity:
        candidates = _ranked(probe_symmetry(scene, model, candidates, cfg), violation, cfg)
    lead = candidates[0]
    if config.grid_group and _score(lead, violation) < config.grid_below:
        # starts without features: RANSAC's draws can miss a pose the views all show (a
        # realistic mug [9400, 1] 89 deg off at fitness 0.93 after a few pixels changed)
        extra = grid_candidates(scene, model, cfg, rotation_grid(config.grid_group), None,
                                config.grid_keep, cfg.voxel_m, lambda c: _score(c, violation))
        candidates = _ranked([*candidates, *extra], violation, cfg)
        if config.check_ambiguity and candidates[0] is not lead:
            candidates = _ranked(probe_symmetry(scene, model, candidates, cfg), violation, cfg)
    if config.check_free_space and config.probe_grid:
        candidates = _grid_probes(scene, model, candidates, violation, config)
    best = candidates[0]
    if best.fitness < config.min_fitness:
        raise StageError(
            STAGE,
            f"registration fitness {best.fitness:.2f} below {config.min_fitness:.2f}: {mesh_name} "
            "does not explain the fused scan (wrong object, mesh units or turntable angles?)"
            + "".join(f"; {n}" for n in _view_notes(views, names, counts, None, config)),
        )
    amb = distinct_from(best, candidates[1:], cfg)
    runner = amb.runner_up
    ambiguous = amb.ambiguous
    if config.check_free_space and runner is not None:
        combined = [_combined(c, violation) for c in candidates]
        amb = distinct_from(combined[0], combined[1:], cfg)
        by_combined = dict(zip(combined, candidates, strict=True))
        runner = None if amb.runner_up is None else by_combined[amb.runner_up]
        ambiguous = amb.ambiguous and (
            violation(runner) <= violation(best) + config.ambiguous_violation
        )
    fits = [
        np.nan if p is None else evaluate(to_pcd(p), model, best.T_o_s, cfg.eval_distance_m)[0]
        for p in per_view
    ]
    v_best = violation(best) if config.check_free_space else np.nan
    v_runner = np.nan if runner is None or not config.check_free_space else violation(runner)
    return ScanRegistration(
        T_turntable_o_scan=inv_T(best.T_o_s),
        fitness=best.fitness,
        inlier_rmse_m=best.inlier_rmse_m,
        n_points=len(scene.points),
        per_view_fitness=np.asarray(fits, float),
        per_view_points=np.asarray(counts, int),
        ambiguous=ambiguous,
        ambiguity_deg=amb.ambiguity_deg,
        free_space_violation=v_best,
        T_turntable_o_runner_up=None if runner is None else inv_T(runner.T_o_s),
        runner_up_fitness=np.nan if runner is None else runner.fitness,
        runner_up_free_space_violation=v_runner,
        note=_note(ambiguous, amb.ambiguity_deg, v_best, config),
        notes=tuple(proxy_notes + _view_notes(views, names, counts, fits, config)),
    )


def _view_notes(views, names, counts, fits, config: RegisterScanConfig) -> list[str]:
    """Views skipped for too few points, and views that share a platter angle (with their
    fitness under the final pose when ``fits`` is given)."""
    notes = []
    skipped = [f"{n}: {c} points" for n, c in zip(names, counts, strict=True)
               if c < config.min_view_points]
    if skipped:
        notes.append(f"{len(skipped)} scan view(s) skipped, fewer than {config.min_view_points} "
                     f"depth points over the platter ({'; '.join(skipped)})")
    by_angle: dict[float, list[int]] = {}
    for k, (_, angle) in enumerate(views):
        key = round(float(np.degrees(angle)) % 360.0, 3) % 360.0
        by_angle.setdefault(key, []).append(k)
    for angle, ks in by_angle.items():
        if len(ks) < 2:
            continue
        fit = "" if fits is None else " (fitness under the final pose " + ", ".join(
            "skipped" if not np.isfinite(fits[k]) else f"{fits[k]:.2f}" for k in ks) + ")"
        notes.append(f"{len(ks)} scan views share angle_deg {angle:g}: "
                     f"{', '.join(names[k] for k in ks)}{fit}; all used (a view that fits much "
                     "worse than its twin has a wrong angle_deg)")
    return notes


def _violation_of(views, K, T_turntable_color, model, config: RegisterScanConfig):
    """``violation(candidate) -> float``, memoised per candidate; 0 when not checked."""
    if not config.check_free_space:
        return lambda c: 0.0
    crop = config.crop
    r = crop.radius_m + crop.margin_m
    corners = np.array(
        [[x, y, z] for x in (-r, r) for y in (-r, r) for z in (0.0, crop.max_height_m)]
    )
    fs = prepare_views(
        [(d, rot_z(-a) @ T_turntable_color) for d, a in views], K, config.free_space_window_px,
        corners,
    )
    pts_o = np.asarray(strided(model.dense, config.free_space_points).points)
    memo: dict[Candidate, float] = {}

    def violation(c: Candidate) -> float:
        if c not in memo:
            pts_t0 = transform_points(inv_T(c.T_o_s), pts_o)
            memo[c] = free_space_violation(fs, pts_t0, config.free_space_tol_m)
        return memo[c]

    return violation


def _grid_probes(scene, model, candidates, violation, config: RegisterScanConfig):
    """Probe the point group's rotations (:func:`_grid`) from the best pose while the free
    space contradicts it; a pass stops at the first refined probe that the free space does
    not contradict and that scores better; at most ``probe_rounds`` passes."""
    cfg = config.registration
    grid = _grid(config)
    for _ in range(config.probe_rounds):
        before = candidates[0]
        if violation(before) <= config.grid_above:
            break
        floor = _score(before, violation)

        def found(c: Candidate, floor: float = floor) -> bool:
            return violation(c) <= config.grid_above and _score(c, violation) > floor

        probes = probe_symmetry(scene, model, candidates, cfg, grid, stop_when=found)
        candidates = _ranked(probes, violation, cfg)
        if candidates[0] is before:
            break
    return candidates


def _score(c: Candidate, violation) -> float:
    """Fitness times (1 - free-space violation)."""
    return c.fitness * (1.0 - violation(c))


def _grid(config: RegisterScanConfig) -> np.ndarray:
    """The point group's rotations (k, 3, 3) but the identity, half turns first, without the
    turns about single principal axes that the symmetry probes already tried."""
    from scipy.spatial.transform import Rotation

    group = Rotation.create_group(config.probe_grid)
    angles = group.magnitude()
    keep = angles > 1e-6
    if config.check_ambiguity:
        rotvecs = group.as_rotvec()
        probed = np.radians(config.registration.probe_angles_deg)
        for i in range(3):
            for a in probed:
                keep &= np.linalg.norm(rotvecs - a * np.eye(3)[i], axis=1) > 1e-6
    order = np.argsort(-np.round(angles, 6), kind="stable")
    return group[order[keep[order]]].as_matrix()


def _combined(c: Candidate, violation) -> Candidate:
    """``c`` with its fitness times (1 - its free-space violation)."""
    return Candidate(c.T_o_s, _score(c, violation), c.inlier_rmse_m, c.origin)


def _ranked(cands: list[Candidate], violation, cfg: RegistrationConfig) -> list[Candidate]:
    """Best first by fitness times (1 - free-space violation), then TLS cost, then origin."""
    return sorted(
        cands,
        key=lambda c: (
            -_score(c, violation),
            tls_cost(c, cfg.eval_distance_m),
            c.origin,
        ),
    )


def _note(ambiguous: bool, angle_deg: float, v_best: float, config: RegisterScanConfig) -> str:
    """A sentence for QA on why the pose may be wrong; empty when there is no reason."""
    notes = []
    if ambiguous:
        notes.append(
            f"a pose {angle_deg:.0f} deg away explains the scan as well (symmetric object)"
        )
    if np.isfinite(v_best) and v_best > config.grid_above:
        notes.append(
            f"{100 * v_best:.0f} % of the posed mesh lies where the scan views see empty space"
        )
    return "; ".join(notes)
