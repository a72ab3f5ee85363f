"""The ``refine_grasp`` stage (the paper's stage 5): refine the fitted hand against the object
and its contact map (after ContactGrasp).

Brahmbhatt et al., ContactGrasp (IROS 2019), grasp optimisation: the nearest hand segment is
drawn to contacted object points, the hand surface is pushed away from points observed without
contact, and the hand may not penetrate the object. Here, in the object's frame (the object at
the first steady frame, ``T_w_o`` of estimate_adjustment), a bounded least squares moves the
palm by a small correction (turn about the wrist, shift; the scale stays) and the 20 angles
inside the joint limits (fit_hand's per-bone shape, ``bone_scale``, stays), minimising

- attraction: signed distance of each observed contacted vertex (``contact >= threshold``) to
  the hand surface, soft-L1, only for vertices within ``capture_radius_mm`` of the hand when a
  round starts (a wrong contact far away cannot drag the hand across the object);
- repulsion: observed vertices without contact (``contact < free_below``) closer than
  ``repel_margin_mm`` to the hand surface;
- penetration: the object's signed distance at hand probes (spheres along the bones, palm
  surface points) and object vertices near the hand that lie inside it;
- prior: joints (mm), angles and palm pose stay near fit_hand's fit.

Distances to the hand are the model's own (``hand.surface``); penetration and contact
agreement before and after are measured on the hand mesh. The refinement never penetrates
deeper than the fit: when the optimum does, the move from the fit is scaled back (bisection on
the share of the move kept) until its deepest hand vertex is no deeper than the fit's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, make_T, transform_points
from graspcap.tasks.hand.fit_hand import HandFit
from graspcap.tasks.hand.model import HandModel, HandSide
from graspcap.tasks.hand.surface import (
    HandSurface,
    contact_agreement,
    object_sdf_grid,
    penetration_mm,
)

# scipy: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "refine_grasp/3"
STAGE = "refine_grasp"
_N_POSE = 6


class RefineGraspConfig(StageConfig):
    """Weights, distances and bounds of the refinement, and its acceptance test."""

    contact_threshold: float = 0.4
    """A vertex with contact at or above this is contacted (attracts the hand)."""
    free_below: float = 0.05
    """An observed vertex with contact below this is free of contact (repels the hand)."""
    capture_radius_mm: float = 15.0
    """Contacted vertices farther than this from the hand when a round starts do not attract."""
    watch_radius_mm: float = 6.0
    """Other vertices (repelling, or checked for lying inside the hand) are those within this
    of the hand when a round starts."""
    attract_scale_mm: float = 3.0
    """Soft-L1 scale of the attraction: gaps beyond it pull with a bounded force."""
    repel_margin_mm: float = 1.0
    """Free vertices closer than this to the hand surface are pushed out to it."""
    attract_weight: float = 1.0
    """Weight of the RMS attraction gap (mm)."""
    repel_weight: float = 1.0
    """Weight of the repulsion, per free vertex, relative to one attracting vertex."""
    penetration_weight: float = 3.0
    """Weight of each penetration probe's depth (mm); not averaged, so every probe counts."""
    prior_joint_weight: float = 0.3
    """Weight of the RMS move of the 21 joints from fit_hand's fit (mm)."""
    prior_angle_weight_mm_per_rad: float = 2.0
    """An RMS angle change of 1 rad costs as much as this many mm of RMS attraction gap."""
    max_palm_shift_mm: float = 12.0
    """Largest move of the palm origin per axis from fit_hand's fit."""
    max_palm_turn_deg: float = 8.0
    """Largest turn of the palm per axis (palm frame) from fit_hand's fit."""
    max_angle_change_deg: float = 25.0
    """Largest change of any joint angle from fit_hand's fit (inside the joint limits too)."""
    rounds: int = 2
    """Optimisation rounds; each re-selects the vertices within the capture radius."""
    max_evaluations: int = 40
    """Cap on residual evaluations per round."""
    grid_step_mm: float = 3.0
    """Spacing of the object's signed-distance grid around the hand."""
    samples_per_bone: int = 5
    """Penetration probes (spheres) along each phalanx."""
    agreement_dist_mm: float = 3.0
    """Contact agreement: a vertex within this of the hand mesh is touched by the hand."""
    backtrack_steps: int = 8
    """Bisection steps on the share of the optimised move kept when the optimum penetrates
    deeper than the fit (8 steps: the share to within 0.4 %)."""


PRESETS: dict[str, RefineGraspConfig] = {
    "default": RefineGraspConfig(),
    "fast": RefineGraspConfig(rounds=1, max_evaluations=20, grid_step_mm=3.5,
                              samples_per_bone=4),
}


@dataclass(frozen=True)
class GraspMetrics:
    """Penetration and contact agreement of one hand pose.

    Attributes
    ----------
    penetration_max_mm, penetration_mean_mm : float
        Deepest hand mesh vertex inside the object, and the mean depth over the vertices inside
        (0 when none is).
    contact_near_share : float
        Observed contacted vertices within ``agreement_dist_mm`` of the hand mesh (share; NaN
        when none is contacted).
    touch_contacted_share : float
        Observed vertices within ``agreement_dist_mm`` of the hand mesh that are contacted
        (share; NaN when the hand touches none).
    """

    penetration_max_mm: float
    penetration_mean_mm: float
    contact_near_share: float
    touch_contacted_share: float

    @property
    def contact_agreement(self) -> float:
        """Mean of the two agreement shares (the catalog's ``qa_contact_agreement``)."""
        return float(np.nanmean([self.contact_near_share, self.touch_contacted_share]))


@dataclass(frozen=True)
class GraspRefinement:
    """Result of :func:`refine_grasp`.

    Attributes
    ----------
    side : HandSide
    scale : float
        fit_hand's scale (unchanged).
    bone_scale : (20,) float
        fit_hand's shape (unchanged): per-bone length factors (``hand.shape``).
    T_w_p, T_o_p : (4, 4) float
        Refined palm pose in the world of the first steady frame and in the object frame.
    angles_rad : (20,) float
    joints_o, joints_w : (21, 3) float
        Posed joints in the object frame and in the world.
    hand_vertices_o : (n, 3) float
    hand_faces : (m, 3) int
        Refined hand mesh, object frame.
    before, after : GraspMetrics
        fit_hand's fit's and the returned hand's metrics.
    iterations : int
        Jacobian evaluations of the least squares, over all rounds.
    n_attract, n_repel : int
        Vertices attracting and repelling in the last round.
    kept_share : float
        Share of the optimised move (palm correction and angle changes) returned: 1 the
        optimum, less when it was scaled back so as to penetrate no deeper than the fit.
    accepted : bool
        The refinement is returned; False: fit_hand's fit is returned unchanged.
    reason : str
        Why it was not accepted (empty when it was).
    """

    side: HandSide
    scale: float
    bone_scale: np.ndarray
    T_w_p: np.ndarray
    T_o_p: np.ndarray
    angles_rad: np.ndarray
    joints_o: np.ndarray
    joints_w: np.ndarray
    hand_vertices_o: np.ndarray
    hand_faces: np.ndarray
    before: GraspMetrics
    after: GraspMetrics
    iterations: int
    n_attract: int
    n_repel: int
    kept_share: float
    accepted: bool
    reason: str


def _check(fit, side, T_w_o, V, F, contact, observed):
    if HandSide(side) != fit.side:
        raise StageError(STAGE, f"side {side!r} differs from the fitted hand's {fit.side.value!r}")
    T = np.asarray(T_w_o, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise StageError(STAGE, f"T_w_o must be a finite (4, 4) pose, got shape {T.shape}")
    V = np.asarray(V, dtype=float)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 4 or not np.all(np.isfinite(V)):
        raise StageError(STAGE, f"object_vertices must be finite (n, 3), got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) < 4 or F.min() < 0 or F.max() >= len(V):
        raise StageError(STAGE, f"object_faces must be (m, 3) indices into the {len(V)} "
                         f"vertices, got shape {F.shape}")
    c = np.asarray(contact, dtype=float).reshape(-1)
    o = np.asarray(observed).reshape(-1)
    for name, a in (("contact", c), ("observed", o)):
        if len(a) != len(V):
            raise StageError(STAGE, f"{name} has {len(a)} values for {len(V)} object vertices")
    if not np.all(np.isfinite(c[o.astype(bool)])):
        raise StageError(STAGE, "contact is not finite (NaN or inf) at observed vertices")
    hand = [fit.T_w_p, fit.angles_rad, fit.scale, fit.bone_scale]
    if not all(np.all(np.isfinite(np.asarray(h, dtype=float))) for h in hand):
        raise StageError(STAGE, "the fitted hand (T_w_p, angles_rad, scale, bone_scale) is "
                         "not finite")
    return T, V, F.astype(np.int64), np.where(o.astype(bool), c, 0.0), o.astype(bool)


class _Problem:
    """Residuals of the refinement for parameters x = (turn (3) rad, shift (3) mm, angles)."""

    def __init__(self, model, surface, sdf, T0, angles0, V, contact, observed, config,
                 bone_scale):
        self.model, self.surface, self.sdf, self.cfg = model, surface, sdf, config
        self.bone_scale = bone_scale
        self.R0, self.t0 = T0[:3, :3], T0[:3, 3]
        self.angles0 = angles0
        self.V, self.contact, self.observed = V, contact, observed
        self.kp0 = self.pose(self.x0[None])[0][0]
        self.select(self.x0)

    @property
    def x0(self) -> np.ndarray:
        return np.concatenate([np.zeros(_N_POSE), self.angles0])

    def pose(self, X: np.ndarray):
        from scipy.spatial.transform import Rotation

        R = self.R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix()
        t = self.t0 + 1e-3 * X[:, 3:6]
        kp_p = self.model.keypoints_batch(X[:, _N_POSE:], bone_scale=self.bone_scale)
        kp = self.surface.scale * np.einsum("bij,bkj->bki", R, kp_p) + t[:, None]
        return kp, R, t

    def select(self, x: np.ndarray) -> None:
        """Vertices near the hand at ``x``: attracting, repelling, and all (for penetration)."""
        kp, R, t = self.pose(x[None])
        d_mm = 1e3 * self.surface.distance(self.V, kp, R, t)[0]
        cfg = self.cfg
        contacted = self.observed & (self.contact >= cfg.contact_threshold)
        watch = d_mm < cfg.watch_radius_mm
        self.attract = np.flatnonzero(contacted & (d_mm < cfg.capture_radius_mm))
        self.repel = np.flatnonzero(watch & self.observed & (self.contact < cfg.free_below))
        self.near = np.union1d(self.attract, np.flatnonzero(watch))
        self.norm = 1.0 / np.sqrt(max(len(self.attract), 1))

    def residuals(self, X: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        kp, R, t = self.pose(X)
        d_mm = 1e3 * self.surface.distance(self.V[self.near], kp, R, t)  # (b, near)
        pos = np.searchsorted(self.near, self.attract)
        f = cfg.attract_scale_mm
        gap = d_mm[:, pos]
        att = np.sign(gap) * f * np.sqrt(2.0 * (np.sqrt(1.0 + (gap / f) ** 2) - 1.0))
        rep = np.maximum(cfg.repel_margin_mm - d_mm[:, np.searchsorted(self.near, self.repel)], 0)
        inside = np.maximum(-d_mm, 0.0)
        centres, radii, palm = self.surface.samples(kp, R, t)
        pen_b = np.maximum(1e3 * (radii - self.sdf(centres)), 0.0)
        pen_p = np.maximum(-1e3 * self.sdf(palm), 0.0)
        joints = 1e3 * (kp - self.kp0).reshape(len(X), -1) / np.sqrt(21.0)
        turn_mm = X[:, :3] * 100.0  # 1 rad at the wrist ~ 100 mm at the knuckles
        angles = (X[:, _N_POSE:] - self.angles0) / np.sqrt(20.0)
        return np.concatenate([
            cfg.attract_weight * self.norm * att,
            cfg.repel_weight * self.norm * rep,
            cfg.penetration_weight * np.concatenate([inside, pen_b, pen_p], axis=1),
            cfg.prior_joint_weight * np.concatenate([joints, turn_mm / np.sqrt(21.0)], axis=1),
            cfg.prior_angle_weight_mm_per_rad * angles,
        ], axis=1)  # fmt: skip


def _forward_jacobian(fun, x: np.ndarray, step: np.ndarray, lo, hi) -> np.ndarray:
    """Jacobian by one-sided differences (stepping away from a bound), one batched call."""
    n = len(x)
    h = np.where(x + step <= hi, step, -step)
    X = np.repeat(x[None], n + 1, axis=0)
    X[np.arange(1, n + 1), np.arange(n)] += h
    R = fun(X)
    return (R[1:] - R[0]).T / h


def _metrics(V, F, contact, observed, hand_v, hand_f, surface_d_m, config) -> GraspMetrics:
    """Penetration of the hand mesh into the object and contact agreement with it, by
    ``hand.surface.contact_agreement`` (the one definition, also qa_metrics'); the model's own
    distance ``surface_d_m`` only pre-selects the vertices that may be touched."""
    pen_max_mm, pen_mean_mm = penetration_mm(V, F, hand_v)
    near_share, touch_share = contact_agreement(
        V, contact, observed, hand_v, hand_f, near_mm=config.agreement_dist_mm,
        contact_threshold=config.contact_threshold,
        candidates=surface_d_m < 1e-3 * config.agreement_dist_mm + 0.005,
    )
    return GraspMetrics(
        penetration_max_mm=pen_max_mm,
        penetration_mean_mm=pen_mean_mm,
        contact_near_share=near_share,
        touch_contacted_share=touch_share,
    )


def refine_grasp(
    fit: HandFit,
    side: HandSide,
    T_w_o: np.ndarray,
    object_vertices: np.ndarray,
    object_faces: np.ndarray,
    contact: np.ndarray,
    observed: np.ndarray,
    config: RefineGraspConfig = PRESETS["default"],
) -> GraspRefinement:
    """Refine fit_hand's hand against the object's contact map, in the object frame.

    Parameters
    ----------
    fit : HandFit
        ``fit_hand``'s result (palm pose in the world of the first steady frame, scale, angles).
    side : HandSide
        The session's hand (must be the fit's).
    T_w_o : (4, 4) float
        Object pose at the first steady frame (estimate_adjustment's ``T_w_o``).
    object_vertices : (n, 3) float
    object_faces : (m, 3) int
        The object mesh in its own frame (closed), file vertex order.
    contact : (n,) float
        Contact in [0, 1] per vertex (``build_contactmap``).
    observed : (n,) bool
        Vertices the thermal scan saw; unobserved vertices neither attract nor repel.
    config : RefineGraspConfig

    Raises
    ------
    StageError
        Inconsistent inputs: lengths of ``contact``/``observed`` other than the vertex count,
        non-finite values, another side than the fit's, faces out of range.
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    T_w_o, V, F, contact, observed = _check(fit, side, T_w_o, object_vertices, object_faces,
                                            contact, observed)
    model = HandModel(fit.side)
    shape = np.asarray(fit.bone_scale, dtype=float)
    surface = HandSurface(fit.side, fit.scale, config.samples_per_bone, shape)
    T_o_w = inv_T(T_w_o)
    T0 = T_o_w @ np.asarray(fit.T_w_p, dtype=float)
    angles0 = model.clip(fit.angles_rad)

    def result(T_o_p, angles, before, after, iterations, n_att, n_rep, reason, kept=0.0):
        mesh = model.mesh(angles, T_o_p, fit.scale, shape)
        joints_o = model.keypoints(angles, T_o_p, fit.scale, shape)
        return GraspRefinement(
            side=fit.side, scale=float(fit.scale), bone_scale=shape, T_w_p=T_w_o @ T_o_p,
            T_o_p=T_o_p,
            angles_rad=angles, joints_o=joints_o, joints_w=transform_points(T_w_o, joints_o),
            hand_vertices_o=mesh.vertices, hand_faces=np.asarray(mesh.faces, np.int64),
            before=before, after=after, iterations=iterations, n_attract=n_att, n_repel=n_rep,
            kept_share=float(kept), accepted=not reason, reason=reason,
        )  # fmt: skip

    def measure(T_o_p, angles):
        kp = model.keypoints(angles, T_o_p, fit.scale, shape)[None]
        d = surface.distance(V, kp, T_o_p[None, :3, :3], T_o_p[None, :3, 3])[0]
        mesh = model.mesh(angles, T_o_p, fit.scale, shape)
        return _metrics(V, F, contact, observed, mesh.vertices, mesh.faces, d, config)

    before = measure(T0, angles0)
    if not np.any(observed & (contact >= config.contact_threshold)):
        reason = "no observed vertex has contact; the stage-3 fit is kept"
        return result(T0, angles0, before, before, 0, 0, 0, reason)

    hand_v = model.mesh(angles0, T0, fit.scale, shape).vertices
    reach_m = 1e-3 * config.max_palm_shift_mm + 0.03  # fingers move too
    probe_m = 0.02  # beyond this from the object every probe is outside it
    sdf = object_sdf_grid(
        V, F, np.maximum(hand_v.min(0) - reach_m, V.min(0) - probe_m),
        np.minimum(hand_v.max(0) + reach_m, V.max(0) + probe_m), 1e-3 * config.grid_step_mm,
        band_m=probe_m,
    )  # fmt: skip
    prob = _Problem(model, surface, sdf, T0, angles0, V, contact, observed, config, shape)
    turn, shift = np.radians(config.max_palm_turn_deg), config.max_palm_shift_mm
    dA = np.radians(config.max_angle_change_deg)
    lo = np.concatenate([[-turn] * 3, [-shift] * 3, np.maximum(model.lower_rad, angles0 - dA)])
    hi = np.concatenate([[turn] * 3, [shift] * 3, np.minimum(model.upper_rad, angles0 + dA)])
    step = np.concatenate([[2e-4] * 3, [0.02] * 3, [2e-4] * 20])
    x, iterations = prob.x0, 0
    for r in range(config.rounds):
        if r:
            prob.select(x)
        if len(prob.attract) == 0:
            break
        sol = least_squares(
            lambda z: prob.residuals(z[None])[0], x, bounds=(lo, hi), method="trf",
            jac=lambda z: _forward_jacobian(prob.residuals, z, step, lo, hi),
            x_scale=np.concatenate([[0.02] * 3, [2.0] * 3, [0.1] * 20]),
            max_nfev=config.max_evaluations,
        )  # fmt: skip
        x, iterations = np.clip(sol.x, lo, hi), iterations + int(sol.njev)
    n_att, n_rep = len(prob.attract), len(prob.repel)
    if n_att == 0:
        reason = (f"no observed contacted vertex within {config.capture_radius_mm} mm of the "
                  "fitted hand; the stage-3 fit is kept")
        return result(T0, angles0, before, before, iterations, 0, n_rep, reason)

    def hand_at(share: float):
        z = prob.x0 + share * (x - prob.x0)
        T = make_T(prob.R0 @ Rotation.from_rotvec(z[:3]).as_matrix(), prob.t0 + 1e-3 * z[3:6])
        return T, model.clip(z[_N_POSE:])

    def depth_mm(share: float) -> float:
        T, angles = hand_at(share)
        return penetration_mm(V, F, model.mesh(angles, T, fit.scale, shape).vertices)[0]

    kept = 1.0
    if depth_mm(1.0) > before.penetration_max_mm:
        good, bad = 0.0, 1.0  # the fit (share 0) is no deeper than itself
        for _ in range(config.backtrack_steps):
            mid = 0.5 * (good + bad)
            good, bad = (mid, bad) if depth_mm(mid) <= before.penetration_max_mm else (good, mid)
        kept = good
    if kept == 0.0:
        reason = (f"the refinement penetrates deeper than the fit's "
                  f"{before.penetration_max_mm:.2f} mm even scaled back to "
                  f"1/{2 ** config.backtrack_steps} of its move; the stage-3 fit is kept")
        return result(T0, angles0, before, before, iterations, n_att, n_rep, reason)
    T, angles = hand_at(kept)
    return result(T, angles, before, measure(T, angles), iterations, n_att, n_rep, "", kept)


__all__ = [
    "PRESETS", "STAGE_VERSION", "GraspMetrics", "GraspRefinement", "RefineGraspConfig",
    "refine_grasp",
]  # fmt: skip
