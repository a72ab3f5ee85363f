"""T_adj: how the object moved during grasp adjustment (pipeline item 7, the paper's caveat).

The object in the first steady frame is registered against that frame's depth with the
hand's pixels masked out. Two paths, tried in order:

1. ``stage1_icp``: ICP initialised at register_object's pose, accepted when enough depth points
   around the posed object are explained (small motions).
2. ``near_hand_global``: the participant usually lifts the object 0.1-0.3 m and turns it
   tens of degrees, out of ICP's reach. The object touches the hand, so the depth is
   restricted to the space within one object diameter of the hand's 3D points, then FPFH +
   RANSAC + ICP as in register_object, register_object's pose one more start. Among poses
   that explain the depth equally well (a symmetric object) the one closest in rotation to
   register_object's wins.

One frame shows one side of the object, partly hidden by the hand: a mug's visible half fits its
own flipped twin as well as the truth (rig seed 11 #0: 163 deg off, fitness 0.98), and with its
handle hidden any turn about its body's axis. The global path's candidates include, when the
model's principal axes are ill-defined, half turns about its own near-symmetry axes and the best
pose turned about the rotation the depth leaves free, to the rotation nearest register_object's
(:mod:`free_rotation`; the search among these twins: :mod:`twin_search`). Other steady frames
(``other_views``) show it turned: when the first frame alone fits below ``views_below_fitness``
or is ambiguous, their points, carried into the first frame by ``reconstruct_hand``'s virtual
cameras, are registered together with it (the object's points near the hand found in each view
on its own), every pose is scored against all their depth images and the better pose is kept
(one frame alone is sharper when it is right). When the first frame alone fails (a 10-15 cm
object mostly inside the hand at 0.8-1.0 m: fewer than ``min_points`` depth points beside the
hand, or no pose), up to ``occluded_views`` steady frames are fused the same way and the object
is registered in them together, every frame's hand surface free space in the depth agreement.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.hand.image_masks import grow_mask
from graspcap.tasks.object_pose.adjustment_region import (
    near_hand,
    needed_pixels,
    region_per_view,
    surface_area_m2,
    within_reach,
)
from graspcap.tasks.object_pose.registration.depth_agreement import views_agreement
from graspcap.tasks.object_pose.registration.engine import (
    Model,
    RegistrationConfig,
    prepare_model,
    prepare_scene,
    rank,
    refine,
    register,
)
from graspcap.tasks.object_pose.registration.open3d_threads import single_threaded
from graspcap.tasks.object_pose.registration.point_clouds import (
    cloud_from_depth,
    drop_flying_pixels,
    to_pcd,
    valid_depth,
)
from graspcap.tasks.object_pose.registration.symmetry import moved_share
from graspcap.tasks.object_pose.registration.twin_search import search_twins
from graspcap.tasks.object_pose.track_object import ObjectTracking, TrackObjectConfig
from graspcap.tasks.object_pose.tracked_average import TrackedAverage, TrackedAverageConfig

STAGE_VERSION = "estimate_adjustment/25"
STAGE = "estimate_adjustment"


class AdjustmentPath(StrEnum):
    """How ``T_adj`` was found."""

    STAGE1_ICP = "stage1_icp"
    NEAR_HAND_GLOBAL = "near_hand_global"
    FRAME_CONSENSUS = "frame_consensus"
    """Found alone in several steady frames that agree (``adjustment_steady.frame_consensus``)."""


class Stage1Hypothesis(StrEnum):
    """Which register_object pose the adjustment started from."""

    BEST = "best"
    RUNNER_UP = "runner_up"


@dataclass(frozen=True)
class SteadyView:
    """Another steady frame: the same held object, seen turned.

    depth_m : (h, w) float metres, 0 = invalid; hand_mask : (h, w) bool, the hand's pixels.
    T_ref_c : (4, 4) this frame's camera into the frame of ``estimate_adjustment``'s depth
        (``inv(T_w_c[ref]) @ T_w_c[this]`` from ``reconstruct_hand``'s cameras).
    """

    depth_m: np.ndarray
    hand_mask: np.ndarray
    T_ref_c: np.ndarray


class EstimateAdjustmentConfig(StageConfig):
    """Masking, the region around the hand and acceptance thresholds."""

    max_range_m: float = 3.0
    """Depth beyond this is treated as invalid."""
    drop_flying: bool = True
    """Drop the pixels on no surface (:func:`point_clouds.drop_flying_pixels`): a Kinect v2's
    veil at depth edges joins the held object to everything behind it, and the clustering
    around the hand then finds no object-sized piece (wild [9700, 1], a can at 0.8 m: 15
    points kept of the 4100 on the can; 4333, 4046 on it, without the veil)."""
    frames_after_onset: int = 5
    """When the first steady frame fails or fits below ``accept_fitness``, the pipeline also
    registers the object in the frame this many later (the onset is often detected a few
    frames early, while the object still settles), carries that pose back with the frame's
    virtual camera and keeps the better fit."""
    mask_dilate_px: int = 3
    """The hand mask is grown by this many pixels before its pixels are dropped."""
    region_margin_m: float = 0.02
    """Slack on the object's size (its largest distance from its centroid) when judging
    which clusters around the hand may be pieces of it."""
    min_hand_points: int = 30
    """With fewer hand pixels with depth than this, the whole (unmasked) cloud is searched."""
    stage1_reach_m: float = 0.03
    """ICP from register_object's pose sees the points within the object's radius plus this."""
    stage1_coarse_min: float = 0.6
    """ICP from register_object's pose runs its finer levels only when the depth agrees with the
    first level's pose on at least this share (an object lifted away: ~0.3 s saved)."""
    cluster_voxel_m: float = 0.004
    """Voxel size of the Euclidean clustering of the region around the hand."""
    cluster_eps_m: float = 0.012
    """Clustering neighbour distance: pieces of the object closer than this stay together."""
    min_points: int = 150
    """Fewer judged pixels than this where the posed object is seen: the pose is not supported;
    for an object that covers few pixels (small, far) ``min_visible_share`` of them."""
    min_visible_share: float = 0.15
    """The least judged pixels a pose needs is this share of the pixels the object covers at
    that pose (its mean silhouette, a quarter of its surface area by Cauchy's formula, at its
    distance in every view, at ``agree_stride_px``) when that is below ``min_points``: a 7 cm
    ball at 0.8 m covers ~1800 pixels, 450 judged, and with two thirds of it inside the hand
    shows ~100 (wild [80625, 21]: 0.92 over 104 judged pixels was refused)."""
    min_points_floor: int = 40
    """...but never fewer than this many judged pixels."""
    agree_tol_m: float = 0.006
    """A pixel agrees with the posed object when its depth is within this of the rendered depth."""
    agree_stride_px: int = 2
    """The depth agreement judges every this-th pixel of every this-th row."""
    hand_free_space: bool = True
    """The hand's pixels count against a pose that puts the object in front of what they
    show (the space between the camera and the seen hand surface is empty): masked out
    alone, they let a pose through the hand or between it and the camera go unjudged."""
    accept_fitness: float = 0.85
    """ICP from register_object's pose is accepted at this fitness."""
    min_fitness: float = 0.5
    """A final fitness below this fails the stage..."""
    ambiguous_min_fitness: float = 0.85
    """...and an ``ambiguous`` one below this: poses far apart that explain only part of the
    depth equally well are a guess, not an object's symmetry (wild [82664, 20], a 6 cm box:
    149 deg off at 0.75, ambiguous; the ambiguous right poses measured 0.90-1.00)."""
    fused_min_fitness: float = 0.85
    """...and a pose found only in the fused steady frames (the first frame alone failed:
    ``occluded_views``) below this: the views' own objects found (the region per view), poses
    explaining half of them were wrong (tuning wild [78643, 18] 43 deg off at 0.54, [78643, 23]
    15 mm off at 0.55, real-detector [52033, 11] 77 mm off at 0.79; right fused poses 0.95-0.99,
    [78643, 6], [52033, 8])."""
    other_views: int = 6
    """Other steady frames (evenly spread) the pipeline offers as ``other_views`` (rig seed
    9000 #5, a mug from an onset 2 frames early: 3 views 4.7 deg, 6 views 0.9 deg)."""
    occluded_views: int = 12
    """Other steady frames fused when the first frame alone fails: fewer than ``min_points``
    depth points outside the hand mask or near the hand, or no pose found (a 10-15 cm object
    mostly inside the hand at 0.8-1.0 m: wild [9893, i] "only 9 depth points outside the hand
    mask"). Every view's depth points, carried into the first frame by ``reconstruct_hand``'s
    cameras, form one scene; each frame's hand is free space in the depth agreement."""
    consensus_views: int = 11
    """When every other way fails (the first frame, the frame ``frames_after_onset`` later and
    the fused views), the object is registered alone in the first steady frame and up to this
    many others (evenly spread), each needing only ``min_points_floor`` judged pixels, and a
    pose that ``consensus_min_frames`` of them find independently is kept (0: off). A small
    object inside the fist shows 50-120 judged pixels per frame, under ``min_points``, and
    the fused views' scene is dominated by what the views' camera errors smear (tuning wild
    ``[44199, 4]``, an 85 mm ball: alone 1.00 over 51 pixels, 1.7 mm off; fused 0.07)."""
    consensus_min_frames: int = 3
    """...frames, each fitting at least ``consensus_min_fitness``, whose poses carried into the
    first steady frame by ``reconstruct_hand``'s cameras lie within ``consensus_m`` of each
    other: one frame's few pixels can fit a wrong pose well (an 85 mm ball, fitness 0.98 over
    180 pixels, 109 mm off carried by its frame's camera); three seldom fit the same wrong one."""
    consensus_min_fitness: float = 0.85
    """See ``consensus_min_frames``."""
    consensus_m: float = 0.01
    """Two poses agree when the object's surface at one lies on average within this of its
    surface at the other (symmetric poses agree: a bulb's turn about its axis is 0): the
    right frames of the tuning sessions, carried by stage 2's cameras, lay 1-4 mm apart."""
    views_below_fitness: float = 0.97
    """The other views are used when the first frame's pose fits below this (measured on rig
    sessions: right poses 0.99-1.00; a flipped mug 0.92, a mug 7.5 deg off 0.64)..."""
    views_if_ambiguous: bool = True
    """...and when it is ``ambiguous`` (a mug, handle hidden: rig seed 11 #0 48.7 deg off
    alone, 0.7 with the views; a spray bottle whose half-turned twin fit one frame at 0.997
    against the truth's 0.983, wild [78643, 9]: 176 deg off alone, 1.4 with the views and the
    later frame). Ties that are the object's own symmetry (``symmetric_tie_share``) are alike
    in every view and ask for none."""
    symmetric_tie_share: float = 0.02
    """An ambiguous pose whose every twin moves at most this share of the model's surface more
    than ``symmetric_tie_moved_m`` off itself (:func:`symmetry.moved_share`) is the object's
    own symmetry: other views would see it alike and are not asked for. Half turns of the
    rig's objects: a can, a glass or a bulb about its axis, a remote, a ball 0.0; a small
    box's flap 0.06-0.09, a carton's spout 0.07-0.13, a bottle's cap 0.17, a mug's handle and
    a spray bottle's nozzle 0.25 and more."""
    symmetric_tie_moved_m: float = 0.003
    """See ``symmetric_tie_share``: a displacement the depth sees (twice a Kinect v2's noise at
    1 m)."""
    views_margin: float = 0.02
    """...and their pose is kept when the views agree with it by this much more (than with the
    first frame's; by any amount when that was ``ambiguous``)."""
    check_ambiguity: bool = True
    """Run the symmetry probes on the global path (finds the symmetric pose nearest
    register_object's)."""
    probe_rounds: int = 2
    """Further rounds of symmetry probes from the best pose while its fitness times depth
    agreement is below ``reprobe_below`` (realistic carton s9400 #5: its 180 deg twin at
    0.99 x 0.91 was kept; probed from it, the truth at 1.0)."""
    reprobe_below: float = 0.99
    """See ``probe_rounds``; the rounds stop at the first probe that reaches it."""
    tie_tol: float = 0.005
    """Among poses whose fitness times depth agreement is within this of the best, the one
    closest in rotation to register_object's is kept; poses within ``ambiguity_fitness_tol`` (0.02)
    make the result ``ambiguous`` (a lifted carton's 180 deg twin at 0.988 against the
    truth's 1.0 was kept for being nearer register_object's)."""
    flip_probes: bool = True
    """With ill-defined principal axes (``ill_defined_ratio``) the symmetry probes also turn
    the best pose half a turn about the model's two best self-matching axes
    (:func:`symmetry.self_flip_axes`, 0.15-0.4 s CPU per mesh)."""
    ill_defined_ratio: float = 0.9
    """Principal axes are ill-defined when two principal spreads are within this ratio
    (:func:`symmetry.axes_ill_defined`; mug, bottle 0.968; carton 0.78, spray 0.71, drill 0.65)."""
    free_turns: bool = True
    """With ``check_ambiguity`` and ill-defined axes: the best pose turned about the rotation
    the depth leaves least constrained to the rotation nearest register_object's, upright and
    flipped, are candidates too (:mod:`free_rotation`; a mug, handle hidden). Not gated by
    ``FreeAxis.weakness``: [9900, 4] from onset 26 needs them with its views at 0.07 (50.5 deg
    off without; other mugs 0.07-0.18)."""
    grid_group: str = "I"
    """The global path also starts ICP from every rotation of this point group (scipy
    ``Rotation.create_group``; ``""`` off), each placed on the region by the centroid of the
    model's camera-facing surface (:mod:`grid_search`): FPFH + RANSAC needs shape features a
    carton's faces, a can or a small object at 0.8 m do not have."""
    grid_keep: int = 4
    """Grid starts (the best by fitness times depth agreement) refined through every level.
    They run only while the global step's best of its first three scores below
    ``reprobe_below``."""
    registration: RegistrationConfig = RegistrationConfig(
        coarse_model_points=5000, round_spread=0.03
    )
    """Global registration and ICP settings (a probe's first ICP level against a quarter of
    the model's points). RANSAC keeps 20000 iterations per restart: with 5000 the realistic
    carton [9000, 0] came out 180 deg off (its symmetric twin never found, not flagged)."""
    tracking: TrackObjectConfig = TrackObjectConfig()
    """The object tracked in every steady frame's depth from the registered pose (the stage's
    glue, :mod:`track_object`); ``propagate_poses`` defines the tracked frames' cameras from
    it. ``enabled=False``: no tracking, stage 2's cameras as they are."""
    average: TrackedAverageConfig = TrackedAverageConfig()
    """``T_w_o`` as the robust mean over the frames whose depth registered the object
    (:mod:`tracked_average`)."""


PRESETS: dict[str, EstimateAdjustmentConfig] = {
    "default": EstimateAdjustmentConfig(),
    "fast": EstimateAdjustmentConfig(
        check_ambiguity=False,
        registration=RegistrationConfig(n_restarts=2, coarse_model_points=5000, round_spread=0.03),
    ),
    "always_global": EstimateAdjustmentConfig(accept_fitness=1.1),
}


@dataclass(frozen=True)
class Adjustment:
    """Result of :func:`estimate_adjustment`.

    Attributes
    ----------
    T_adj : (4, 4) float
        World-frame motion: the object at the first steady frame is ``T_adj @ T_w_o_stage1``.
    T_w_o : (4, 4) float
        That pose, ``T_adj @ T_w_o_stage1``.
    fitness : float
        Where the posed mesh is seen (hand masked): share of pixels whose depth agrees with it.
    inlier_rmse_m : float
        RMS depth difference of the agreeing pixels.
    n_points : int
        Pixels judged.
    path : AdjustmentPath
        Which path produced the pose.
    ambiguous : bool
        A pose at least ``ambiguity_min_deg`` away explains the depth as well.
    stage1_hypothesis : Stage1Hypothesis
        The register_object pose it started from (``runner_up`` only when one was passed and won).
    """

    T_adj: np.ndarray
    T_w_o: np.ndarray
    fitness: float
    inlier_rmse_m: float
    n_points: int
    path: AdjustmentPath
    ambiguous: bool
    stage1_hypothesis: Stage1Hypothesis = Stage1Hypothesis.BEST
    views: int = 1
    """Frames the pose was registered in and scored against (``fitness`` is over all)."""
    symmetric_tie: bool = False
    """``ambiguous`` only through poses the object's shape is symmetric under
    (``symmetric_tie_share``): other views cannot tell them apart."""
    tracking: ObjectTracking | None = None
    """The object tracked in every steady frame's depth (the stage's glue; None: not tracked).
    Its ``T_c_o`` where not tracked is the pose carried from ``T_w_o_first``."""
    T_w_o_first: np.ndarray | None = None
    """The pose registered in the first steady frame(s) when ``T_w_o`` is the mean over the
    registered frames (:mod:`tracked_average`); None when ``T_w_o`` is that pose."""
    average: TrackedAverage | None = None
    """The mean over the registered frames, or why there is none (None: not tried)."""


@single_threaded()
def estimate_adjustment(
    depth_m: np.ndarray,
    K: np.ndarray,
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    T_w_o_stage1: np.ndarray,
    hand_mask: np.ndarray,
    config: EstimateAdjustmentConfig = PRESETS["default"],
    T_w_o_stage1_alt: np.ndarray | None = None,
    other_views: Callable[[int], Sequence[SteadyView]] | None = None,
) -> Adjustment:
    """Estimate ``T_adj`` from the depth of the first steady frame.

    Parameters
    ----------
    depth_m : (h, w) float
        Depth of the first steady frame, aligned to colour, metres; 0 = invalid.
    K : (3, 3) float
        Colour intrinsics.
    mesh_vertices, mesh_faces : (n, 3) float, (m, 3) int
        Object mesh, object frame, metres.
    T_w_o_stage1 : (4, 4) float
        Object pose from ``register_object``.
    hand_mask : (h, w) bool
        Pixels of the hand (from the fitted hand or
        :func:`adjustment_region.hand_mask_from_keypoints`).
    T_w_o_stage1_alt : (4, 4) float, optional
        A second register_object hypothesis (``ObjectRegistration.T_w_o_runner_up`` when
        register_object was ``ambiguous``): the stage runs from both and keeps the pose whose
        rendering the depth agrees with more (ties: ``T_w_o_stage1``);
        ``Adjustment.stage1_hypothesis`` says which. ``T_adj`` stays relative to ``T_w_o_stage1``.
    other_views : ``count -> [SteadyView, ...]``, up to ``count`` other steady frames (same
        intrinsics ``K``), asked for only when the first frame alone fits below
        ``views_below_fitness`` or is ``ambiguous`` (``config.other_views`` of them), or fails
        (too few depth points beside the hand, no pose: ``config.occluded_views``).
    """
    cfg = config.registration
    depth = _depth(depth_m, K, config)
    if not depth.any():
        raise StageError(STAGE, "depth image has no valid pixel (all zero, NaN or out of range)")
    hand = np.asarray(hand_mask, bool)
    if hand.shape != depth.shape:
        raise StageError(STAGE, f"hand mask has shape {hand.shape}, depth {depth.shape}")
    views = [(depth, ~grow_mask(hand, config.mask_dilate_px), np.eye(4))]
    n = len(cloud_from_depth(depth, K, views[0][1]))
    short = n < config.min_points
    if short and (other_views is None or config.occluded_views <= 0):
        raise StageError(STAGE, f"only {n} depth points outside the hand mask")
    model = prepare_model(mesh_vertices, mesh_faces, cfg)
    mesh = (np.asarray(mesh_vertices, float), np.asarray(mesh_faces, np.int64))
    area = surface_area_m2(*mesh)
    T_w_o1 = np.asarray(T_w_o_stage1, float)
    hypotheses = [(Stage1Hypothesis.BEST, T_w_o1)]
    if T_w_o_stage1_alt is not None:
        hypotheses.append((Stage1Hypothesis.RUNNER_UP, np.asarray(T_w_o_stage1_alt, float)))
    hands = [hand]

    def solve(views: list) -> Adjustment:
        points = [cloud_from_depth(d, K, keep) @ T[:3, :3].T + T[:3, 3] for d, keep, T in views]
        hand_pts = [cloud_from_depth(d, K, m) @ T[:3, :3].T + T[:3, 3]
                    for (d, _, T), m in zip(views, hands, strict=True)]  # fmt: skip
        pts, hand_all = np.concatenate(points), np.concatenate(hand_pts)
        centres = [T[:3, :3] @ model.centroid + T[:3, 3] for _, T in hypotheses]
        ctx = _Context(views, K, within_reach(pts, hand_all, centres, model.radius_m, config),
                       hand_all, model, mesh, area)
        if len(views) > 1:
            ctx.cache["region"] = region_per_view(points, hand_pts, model.radius_m, config)
        results: list[Adjustment] = []
        errors: list[StageError] = []
        for which, T_start in hypotheses:
            try:
                results.append(_from_hypothesis(ctx, T_start, which, config))
            except StageError as e:
                errors.append(e)
        if not results:
            raise errors[0]
        best = max(results, key=lambda a: a.fitness)  # ties: register_object's best (listed first)
        # T_adj is relative to register_object's pose passed in, whichever hypothesis won, so that
        # T_adj @ T_w_o_stage1 is the object's pose in the steady frame.
        return replace(best, T_adj=best.T_w_o @ inv_T(T_w_o1), views=len(views))

    single: Adjustment | None = None
    failed = StageError(STAGE, f"only {n} depth points outside the hand mask")
    if not short:
        try:
            single = solve(views)
        except StageError as e:
            failed = e
    asks = config.views_if_ambiguous and single is not None and single.ambiguous
    sure = single is not None and not (asks and not single.symmetric_tie)
    if other_views is None or (sure and single.fitness >= config.views_below_fitness):
        if single is None:
            raise failed
        return single
    count = config.other_views if single is not None else config.occluded_views
    for v in other_views(count):  # carried into this frame by the virtual cameras
        hands.append(np.asarray(v.hand_mask, bool))
        d = _depth(v.depth_m, K, config)
        keep = ~grow_mask(hands[-1], config.mask_dilate_px)
        views.append((d, keep, np.asarray(v.T_ref_c, float)))
    if len(views) == 1:
        if single is None:
            raise failed
        return single
    try:
        multi = solve(views)
    except StageError as e:
        if single is None:
            raise StageError(STAGE, f"{failed.reason}; fused with {len(views) - 1} other steady "
                             f"frames: {e.reason}") from None
        return single
    if single is None and multi.fitness < config.fused_min_fitness:
        raise StageError(STAGE, f"{failed.reason}; fused with {len(views) - 1} other steady "
                         f"frames: the best pose explains {multi.fitness:.2f} of their depth "
                         f"(need {config.fused_min_fitness:.2f})")
    margin = config.views_margin if sure else 0.0  # an ambiguous frame is not sharper
    if single is None or multi.fitness > margin + _agreement(
        views, K, mesh, single.T_w_o, config
    )[0]:
        return multi
    return single


def _depth(depth_m: np.ndarray, K: np.ndarray, config: EstimateAdjustmentConfig) -> np.ndarray:
    """A view's depth as the stage uses it: valid within range, without flying pixels."""
    depth = valid_depth(depth_m, config.max_range_m)
    return drop_flying_pixels(depth, K) if config.drop_flying else depth


def _agreement(
    views: list, K: np.ndarray, mesh: tuple, T_w_o: np.ndarray, config: EstimateAdjustmentConfig
) -> tuple[float, float, int]:
    """:func:`views_agreement` with the stage's tolerance and pixel stride."""
    return views_agreement(views, K, mesh, T_w_o, config.agree_tol_m, config.agree_stride_px,
                           free_outside=config.hand_free_space)


@dataclass(frozen=True)
class _Context:
    """The steady frames, prepared once for every register_object hypothesis: the views
    ``(depth, keep, T_ref_c)`` and the points of all of them in the first one's frame."""

    views: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    K: np.ndarray
    points: np.ndarray
    hand_pts: np.ndarray
    model: Model
    mesh: tuple[np.ndarray, np.ndarray]
    area_m2: float
    """The mesh's surface area (:func:`adjustment_region.needed_pixels`)."""
    cache: dict = field(default_factory=dict)
    """What every hypothesis shares: the region around the hand, the global step's
    candidates, the grid's and the candidates' scores."""


def _from_hypothesis(
    ctx: _Context,
    T_w_o1: np.ndarray,
    which: Stage1Hypothesis,
    config: EstimateAdjustmentConfig,
) -> Adjustment:
    """Both paths from one register_object pose ``T_w_o1`` (4, 4); ``T_adj`` relative to it."""
    cfg = config.registration
    views, K, points, hand_pts, model, mesh = (
        ctx.views, ctx.K, ctx.points, ctx.hand_pts, ctx.model, ctx.mesh
    )  # fmt: skip

    # Path 1: ICP from register_object's pose, on the points it can reach.
    centre1 = T_w_o1[:3, :3] @ model.centroid + T_w_o1[:3, 3]
    reach1 = np.linalg.norm(points - centre1, axis=1) <= model.radius_m + config.stage1_reach_m
    scene_all = to_pcd(points[reach1])
    first = refine(
        scene_all, model, inv_T(T_w_o1), cfg, "stage1", stop=1, coarse_target=True,
        eval_points=cfg.probe_eval_points,
    )  # fmt: skip
    fit, rmse, n = _agreement(views, K, mesh, inv_T(first.T_o_s), config)
    if fit >= config.stage1_coarse_min:  # the finer levels only for a pose that may pass
        first = refine(scene_all, model, first.T_o_s, cfg, "stage1", first=1)
        fit, rmse, n = _agreement(views, K, mesh, inv_T(first.T_o_s), config)
    T_w_o = inv_T(first.T_o_s)
    needed = needed_pixels(views, K, model, ctx.area_m2, T_w_o, config)
    if n >= needed and fit >= config.accept_fitness:
        return Adjustment(
            T_w_o @ inv_T(T_w_o1), T_w_o, fit, rmse, n, AdjustmentPath.STAGE1_ICP, False, which
        )

    # Path 2: global registration on the depth around the hand. The region, the global
    # step's candidates and their scores do not depend on the hypothesis: found once per
    # context (a near-symmetric object's two hypotheses paid for two global searches).
    if "region" not in ctx.cache:
        ctx.cache["region"] = near_hand(points, hand_pts, model.radius_m, config)
    region = ctx.cache["region"]
    if len(region) < config.min_points:
        raise StageError(
            STAGE, f"only {len(region)} depth points near the hand: the object is not in view"
        )
    if "global" not in ctx.cache:
        scene, down, feats = prepare_scene(region, None, np.zeros(3), cfg)
        ctx.cache["global"] = (scene, down, register(scene, down, feats, model, cfg))
    scene, down, found = ctx.cache["global"]
    start = refine(scene, model, inv_T(T_w_o1), cfg, "stage1")
    candidates = rank([start, *found], cfg.eval_distance_m)
    chosen, twins = search_twins(
        scene, down, region, model, candidates, T_w_o1,
        lambda T: _agreement(views, K, mesh, T, config)[0], cfg, config, ctx.cache,
    )  # fmt: skip
    T_w_o = inv_T(chosen.T_o_s)
    ambiguous = bool(twins)
    symmetric = ambiguous and all(
        moved_share(model, chosen.T_o_s @ inv_T(t.T_o_s), config.symmetric_tie_moved_m)
        <= config.symmetric_tie_share
        for t in twins
    )
    fit, rmse, n = _agreement(views, K, mesh, T_w_o, config)
    needed = needed_pixels(views, K, model, ctx.area_m2, T_w_o, config)
    least = config.ambiguous_min_fitness if ambiguous else config.min_fitness
    if n < needed or fit < least:
        raise StageError(
            STAGE,
            f"object not found near the hand: fitness {fit:.2f} over {n} points "
            f"(need {least:.2f} over {needed}{', ambiguous' if ambiguous else ''})",
        )
    return Adjustment(
        T_w_o @ inv_T(T_w_o1), T_w_o, fit, rmse, n, AdjustmentPath.NEAR_HAND_GLOBAL, ambiguous,
        which, symmetric_tie=symmetric,
    )
