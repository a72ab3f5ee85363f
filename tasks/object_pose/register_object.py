"""The ``register_object`` stage (the paper's stage 1): the object's pose on the turntable
from one depth image.

Depth -> camera-frame cloud -> crop to the space over the platter (turntable
frame) -> FPFH + RANSAC with restarts -> coarse-to-fine point-to-plane ICP
against the mesh surface. Near-symmetric objects are reported, not hidden:
the best pose is turned about the mesh's principal axes and re-fitted, and a
distinct pose that explains the depth as well makes the result ``ambiguous``. So does a
rotation the depth leaves free (:mod:`free_rotation`): a bottle whose label faces away shows
a surface of revolution, every turn about its axis fits alike and noise picks one (held-out
bottle [9900, 10] 5.3 deg off about its axis, no probe pose distinct by 10 deg to compare).

Candidates are ranked by the share of cropped points the posed mesh explains
times the share of the mesh's rendered pixels the depth agrees with. The
nearest-neighbour fitness alone cannot see model surface where the depth shows
empty space: a mug (a surface of revolution but for its handle) turned so that
its handle hangs in the air explains nearly every observed point too.
The method does not use the fact that the object rests on the platter beyond
the crop, so it also works for objects leaning on something.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError, check_mesh
from graspcap.tasks.core.geometry import inv_T, transform_points
from graspcap.tasks.core.mesh_proxy import PROXY_FACES, mesh_proxy
from graspcap.tasks.object_pose.registration.depth_agreement import depth_agreement
from graspcap.tasks.object_pose.registration.engine import (
    Candidate,
    Model,
    RegistrationConfig,
    prepare_model,
    prepare_scene,
    refine,
    register,
    tls_cost,
)
from graspcap.tasks.object_pose.registration.free_rotation import FreeAxis, free_axis
from graspcap.tasks.object_pose.registration.grid_search import grid_candidates, rotation_grid
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded
from graspcap.tasks.object_pose.registration.point_clouds import (
    PlatterCrop,
    crop_platter,
    platter_depth,
    valid_depth,
)
from graspcap.tasks.object_pose.registration.symmetry import (
    Ambiguity,
    distinct_from,
    probe_symmetry,
)

# open3d, scipy: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "register_object/11"
STAGE = "register_object"


class RegisterObjectConfig(StageConfig):
    """Crop of the platter region and the registration settings."""

    crop: PlatterCrop = PlatterCrop(fit_platter=True)
    """Where the object is looked for: over the platter top as the depth shows it (a wild
    rig's depth, shifted against the colour camera, reads it millimetres off its calibrated
    height)."""
    min_points: int = 200
    """Fewer points over the platter than this means no object was found."""
    min_fitness: float = 0.5
    """Registration with a lower fitness (share of cropped points explained) fails the stage."""
    check_ambiguity: bool = True
    """Run the symmetry probes (ICP from the best pose turned about the principal axes)."""
    probe_grid: str = "I"
    """Symmetry probes: every rotation of this point group (scipy
    ``Rotation.create_group``: ``"I"`` 60 rotations, ``"O"`` 24) about the model's centroid
    and principal axes, applied to the best pose; ``""`` probes only about the principal
    axes by ``registration.probe_angles_deg``. Pose errors that are not a turn about one
    axis (a mug lying on its side, handle up, for one standing) need the grid."""
    grid_until: float = 0.97
    """The grid probes run only while the best pose's fitness times depth agreement is below
    this (a well-explained pose is not searched around; the axis probes still run), and stop
    at the first probe that reaches it (``grid_stops_early``)."""
    grid_stops_early: bool = True
    """End the grid at the first refined probe whose fitness times depth agreement reaches
    ``grid_until`` and beats the best before it (the search found what it looks for: a mug
    or bottle 60 probes of ~0.1 s each); off runs every probe."""
    probe_rounds: int = 2
    """Probe again from the new best pose while probing keeps finding a better one, at most
    this many rounds."""
    check_depth: bool = True
    """Rank candidates by fitness times depth agreement (rendered mesh against the depth
    image); off ranks by fitness and inlier RMSE alone."""
    agree_tol_m: float = 0.006
    """A pixel agrees with the posed mesh when its depth is within this of the rendered depth."""
    probe_gate_margin: float = 0.1
    """A probe runs its finer ICP levels only when, after the first, its fitness times depth
    agreement is at most this below the best's (a mug's handle in the air, or a bottle
    lying across its true axis, is not refined further)."""
    agree_stride_px: int = 2
    """The depth agreement judges every this-th pixel of every this-th row (a quarter of the
    rays at 2; a handle in empty space still costs a large share)."""
    depth_fitness_margin: float = 0.2
    """Only candidates whose fitness is within this of the best are rendered (the rest rank
    after them, by fitness and RMSE)."""
    polish_iterations: int = 50
    """When the result is ambiguous, the best pose is refined once more from the second ICP
    level with this many iterations per level (0: off) and kept if it scores better: turning
    about a near-symmetric object's axis (a bottle whose print and cap differ by 1-2 mm) moves
    point-to-plane ICP a few degrees per 20 iterations, and the finest level's short reach
    stops it there (the YCB fuze bottle stayed 20-39 deg off at depth agreement 0.986 where
    the truth has 1.0)."""
    refit_rounds: int = 2
    """After the probes, the best pose is refined again by the full ICP (every level, from its
    first) at most this many times while that ranks first (0: off). ICP's iteration cap stops
    it part-way along a near-symmetric object's axis: a realistic bottle (synth [7, 2]) came
    out 17.7 deg off about its long axis at fitness times depth agreement 0.983 (above
    ``grid_until``, so not searched around) where one more run reaches the truth's 0.999."""
    free_max_weakness: float = 0.003
    """The result is ``ambiguous`` when the least constrained rotation of the final pose
    (point-to-plane normal matrix of the mesh surface nearest the scene's points, eigenvalue
    over the largest: :func:`free_rotation.free_axis`) is weaker than this (0: off). Does not
    move the pose. On 24 realistic sessions (seeds 9000, 9900) the bottles and the mug 5-32 deg
    off about their axis were 0.0003-0.0006, every good pose >= 0.015 (bottles showing their
    label 0.015-0.017, spray bottles 0.024-0.034, the rest 0.10-0.15): a factor 5 either side."""
    proxy_faces: int = Field(PROXY_FACES, ge=1000)
    """A mesh with more faces is registered as a proxy of about this many
    (:mod:`mesh_proxy`): sampling, features and the depth rendering need its surface, not a
    scan's tenth-of-a-millimetre detail (a synthetic mug subdivided to 979200 faces: 34.7 s at
    fitness 0.970 on the mesh, 10.3 s at 0.998 on its 185628-face proxy)."""
    grid_group: str = "I"
    """Registration also starts ICP from every rotation of this point group (``""`` off),
    each placed on the cloud by the centroid of the model's camera-facing surface
    (:mod:`grid_search`): at 0.6-1.0 m a small object's FPFH features are noise. Only while
    the global step's best pose scores below ``grid_until``."""
    grid_keep: int = 4
    """Grid starts (the best by fitness times depth agreement) refined through every level."""
    registration: RegistrationConfig = RegistrationConfig(
        coarse_model_points=5000, ransac_max_iterations=10_000
    )
    """Global registration and ICP settings: a probe's first ICP level against a quarter of the
    model's points (4x cheaper); 10000 RANSAC iterations per restart instead of 20000 (on 14
    realistic sessions the same poses and the least CPU in all; with 5000 a carton
    needed all four restarts)."""


PRESETS: dict[str, RegisterObjectConfig] = {
    "default": RegisterObjectConfig(),
    "fast": RegisterObjectConfig(
        probe_grid="O",
        probe_rounds=1,
        registration=RegistrationConfig(
            n_restarts=2, coarse_model_points=5000, ransac_max_iterations=10_000
        ),
    ),
    "thorough": RegisterObjectConfig(
        registration=RegistrationConfig(
            n_restarts=8, probe_angles_deg=(45, 90, 135, 180, 225, 270, 315),
        )
    ),
}


@dataclass(frozen=True)
class ObjectRegistration:
    """Result of ``register_object``.

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
    depth_agreement : float
        Share of the posed mesh's rendered pixels whose depth agrees (1 when not checked).
    ambiguous : bool
        A pose at least ``ambiguity_min_deg`` away explains the depth about as well (fitness
        times depth agreement within ``ambiguity_fitness_tol``), or the depth leaves a
        rotation nearly free (``free_weakness`` below ``free_max_weakness``).
    ambiguity_deg : float
        Rotation between ``T_w_o`` and the runner-up (0 when there is none).
    T_w_o_runner_up : (4, 4) float or None
        Best pose distinct from ``T_w_o``; None when there is none, and when the result is
        ambiguous by its free rotation alone (the pipeline hands the runner-up of an
        ambiguous result to the adjustment as a second hypothesis: one that did not fit as
        well is none).
    runner_up_fitness, runner_up_rmse_m, runner_up_depth_agreement : float
        Its fitness, inlier RMSE and depth agreement (0 when there is none).
    free_axis_o : (3,) float
        The least constrained rotation's axis direction at ``T_w_o``, object frame (zeros when
        not checked).
    free_point_o : (3,) float
        A point on that axis, object frame.
    free_weakness : float
        Its eigenvalue over the largest: 0 entirely free, ~0.1 as constrained as the rest
        (1 when not checked).
    notes : tuple of str
        What changes no verdict (a proxy registered for a very fine mesh).
    """

    T_w_o: np.ndarray
    fitness: float
    inlier_rmse_m: float
    n_points: int
    depth_agreement: float
    ambiguous: bool
    ambiguity_deg: float
    T_w_o_runner_up: np.ndarray | None
    runner_up_fitness: float
    runner_up_rmse_m: float
    runner_up_depth_agreement: float
    free_axis_o: np.ndarray
    free_point_o: np.ndarray
    free_weakness: float
    notes: tuple[str, ...] = ()

    @property
    def second_hypothesis(self) -> np.ndarray | None:
        """The pose ``estimate_adjustment`` tries beside ``T_w_o``: the runner-up (4, 4) of an
        ambiguous result (a near-symmetric object could be posed either way), else None."""
        return self.T_w_o_runner_up if self.ambiguous else None


@single_threaded()
def register_object(
    depth_m: np.ndarray,
    K: np.ndarray,
    T_color_turntable: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    config: RegisterObjectConfig = PRESETS["default"],
    *,
    depth_name: str = "the stage-1 depth image",
    mesh_name: str = "the object mesh",
) -> ObjectRegistration:
    """Register the object mesh in the ``stage1`` depth image.

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
    depth_name, mesh_name : str
        The depth file and the mesh file, for messages.
    """
    from scipy.spatial.transform import Rotation

    cfg = config.registration
    check_mesh(STAGE, mesh_vertices, mesh_faces, name=mesh_name)
    proxy = mesh_proxy(mesh_vertices, mesh_faces, config.proxy_faces)
    notes = () if proxy.is_original else (proxy.note(len(mesh_faces), "registered"),)
    mesh_vertices, mesh_faces = proxy.vertices, proxy.faces
    if np.ndim(depth_m) != 2:
        raise StageError(STAGE, f"{depth_name} has shape {np.shape(depth_m)}, expected (h, w)")
    if not valid_depth(depth_m, config.crop.max_range_m).any():
        raise StageError(STAGE, f"{depth_name} has no valid pixel (all zero, NaN or beyond "
                                f"{config.crop.max_range_m} m)")
    depth_m = platter_depth(depth_m, K, config.crop)  # what the agreement judges too
    points = crop_platter(depth_m, K, T_color_turntable, config.crop, prepared=True)
    if len(points) < config.min_points:
        raise StageError(
            STAGE,
            f"object not found on the platter: {len(points)} points of {depth_name} over it "
            f"(need {config.min_points}); check the turntable calibration and the crop",
        )
    model = prepare_model(mesh_vertices, mesh_faces, cfg)
    scene, down, feats = prepare_scene(points, None, np.zeros(3), cfg)
    candidates = register(scene, down, feats, model, cfg)
    mesh = (np.asarray(mesh_vertices, float), np.asarray(mesh_faces, np.int64))
    agreement: dict[Candidate, float] = {}

    def agree(c: Candidate) -> float:
        if c not in agreement:
            agreement[c] = depth_agreement(
                depth_m, K, mesh, inv_T(c.T_o_s), config.agree_tol_m,
                stride_px=config.agree_stride_px,
            )[0]  # fmt: skip
        return agreement[c]

    def ranked(cands: list[Candidate]) -> list[Candidate]:
        if not config.check_depth:
            return cands
        top = max(c.fitness for c in cands) - config.depth_fitness_margin
        for c in cands:
            if c.fitness >= top:
                agree(c)
        return sorted(
            cands,
            key=lambda c: (
                -c.fitness * agreement.get(c, 0.0),
                tls_cost(c, cfg.eval_distance_m),
                c.origin,
            ),
        )

    candidates = ranked(candidates)
    lead = candidates[0]
    if config.grid_group and lead.fitness * agreement.get(lead, 1.0) < config.grid_until:
        # starts without features (a small object at 0.6-1.0 m); a pose the depth already
        # explains is not searched around (a realistic spray bottle: 0.5 s, 2.5 s with them)
        extra = grid_candidates(
            scene, model, cfg, rotation_grid(config.grid_group), np.zeros(3), config.grid_keep,
            cfg.voxel_m, lambda c: c.fitness * agree(c),
        )  # fmt: skip
        candidates = [*candidates, *extra]
    candidates = ranked(candidates)
    # judged after the grid: on a ball at 0.8 m FPFH + RANSAC found nothing (fitness 0.00,
    # wild [82664, 19]) where a grid start explains 0.95 of the points
    fittest = max(candidates, key=lambda c: c.fitness)
    if fittest.fitness < config.min_fitness:
        raise StageError(
            STAGE,
            f"registration fitness {fittest.fitness:.2f} below {config.min_fitness:.2f} over "
            f"{len(points)} points: {mesh_name} does not explain {depth_name} over the platter "
            f"(wrong object or mesh units?)",
        )

    def gate(c: Candidate) -> bool:  # only probes as good as the best in depth go on
        if not config.check_depth:
            return True
        b = candidates[0]
        bar = b.fitness * agreement.get(b, 1.0) - config.probe_gate_margin
        return c.fitness * agree(c) >= bar

    if config.check_ambiguity:
        grid = None
        if config.probe_grid:
            group = Rotation.create_group(config.probe_grid)
            grid = group[group.magnitude() > 1e-6].as_matrix()  # the identity is the best
        candidates = ranked(probe_symmetry(scene, model, candidates, cfg, gate=gate))
        for _ in range(config.probe_rounds if grid is not None else 0):
            before = candidates[0]
            if before.fitness * agreement.get(before, 1.0) >= config.grid_until:
                break
            bar = max(config.grid_until, before.fitness * agreement.get(before, 1.0))

            def found(c: Candidate, bar: float = bar) -> bool:
                return c.fitness * (agree(c) if config.check_depth else 1.0) > bar

            stop = found if config.grid_stops_early else None
            candidates = ranked(
                probe_symmetry(scene, model, candidates, cfg, grid, stop, gate)
            )
            if candidates[0] is before:
                break
    for _ in range(config.refit_rounds):
        c = refine(scene, model, candidates[0].T_o_s, cfg, "refit")
        candidates = ranked([*candidates, c])
        if candidates[0] is not c:
            break
    amb, runner = _ambiguity(candidates, agreement, config)
    if amb.ambiguous and config.polish_iterations > 0:
        polish = cfg.model_copy(update={"icp_max_iterations": config.polish_iterations})
        first = min(1, len(cfg.icp_voxels_m) - 1)
        c = refine(scene, model, candidates[0].T_o_s, polish, "polish", first=first)
        candidates = ranked([*candidates, c])
        if candidates[0] is c:
            amb, runner = _ambiguity(candidates, agreement, config)
    best = candidates[0]
    free = None
    if config.check_ambiguity and config.free_max_weakness > 0:
        free = _free_rotation(np.asarray(down.points), model, best.T_o_s, cfg.eval_distance_m)
    loose = free is not None and free.weakness < config.free_max_weakness
    if loose and not amb.ambiguous:
        runner = None
    return ObjectRegistration(
        T_w_o=inv_T(best.T_o_s),
        fitness=best.fitness,
        inlier_rmse_m=best.inlier_rmse_m,
        n_points=len(points),
        depth_agreement=agreement.get(best, 1.0),
        ambiguous=amb.ambiguous or loose,
        ambiguity_deg=amb.ambiguity_deg,
        T_w_o_runner_up=None if runner is None else inv_T(runner.T_o_s),
        runner_up_fitness=0.0 if runner is None else runner.fitness,
        runner_up_rmse_m=0.0 if runner is None else runner.inlier_rmse_m,
        runner_up_depth_agreement=0.0 if runner is None else agreement.get(runner, 0.0),
        free_axis_o=np.zeros(3) if free is None else free.axis,
        free_point_o=np.zeros(3) if free is None else free.point,
        free_weakness=1.0 if free is None else free.weakness,
        notes=notes,
    )


def _free_rotation(
    points_s: np.ndarray, model: Model, T_o_s: np.ndarray, distance_m: float
) -> FreeAxis | None:
    """The least constrained rotation (object frame) of the mesh surface nearest the scene
    ``points_s`` (n, 3) moved by ``T_o_s`` (those within ``distance_m`` of it, with the mesh's
    own normals: the depth's noisy normals blur a label's millimetres); None with fewer than
    six such points."""
    import open3d as o3d

    p_o = transform_points(T_o_s, points_s)
    closest = model.surface.compute_closest_points(o3d.core.Tensor(p_o.astype(np.float32)))
    q = closest["points"].numpy().astype(float)
    n = closest["primitive_normals"].numpy().astype(float)
    near = np.linalg.norm(q - p_o, axis=1) <= distance_m
    if near.sum() < 6:
        return None
    return free_axis(q[near], n[near])


def _ambiguity(
    candidates: list[Candidate], agreement: dict[Candidate, float], config: RegisterObjectConfig
) -> tuple[Ambiguity, Candidate | None]:
    """The symmetry verdict on ranked ``candidates`` and the runner-up candidate itself."""
    cfg = config.registration
    best = candidates[0]
    if config.check_depth:  # ambiguity judged on the combined score
        combined = {
            c: Candidate(c.T_o_s, c.fitness * agreement.get(c, 0.0), c.inlier_rmse_m, c.origin)
            for c in candidates
        }
        amb = distinct_from(combined[best], [combined[c] for c in candidates[1:]], cfg)
        by_combined = {combined[c]: c for c in candidates}
        runner = None if amb.runner_up is None else by_combined[amb.runner_up]
    else:
        amb = distinct_from(best, candidates[1:], cfg)
        runner = amb.runner_up
    return amb, runner
