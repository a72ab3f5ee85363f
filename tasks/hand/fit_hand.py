"""The ``fit_hand`` stage (the paper's stage 3): fit the 20-DoF hand model to the reconstructed
3D joints.

As in the paper: the palm pose ``T_w_p`` and the hand's scale come from the Umeyama
similarity between the model's six rigid palm points (0, 1, 5, 9, 13, 17) and their targets;
the 20 angles then come from inverse kinematics inside the joint limits. The IK starts from a
closed-form reading of each finger's angles (``hand.ik.closed_form_angles``) and is a bounded
least squares over the fingers' keypoints (fingers do not interact, so one solve holds five
independent blocks), with a weak pull towards the rest angles for DoFs the joints leave open.

In ``joint_refine`` mode (the default) a last bounded, robust least squares moves palm pose,
scale and angles together against all 21 joints, the palm by at most a few millimetres and
degrees: Umeyama sees only six noisy points, the refinement sees all of them. With
``estimate_shape`` (the default) it also estimates the hand's shape, 20 per-bone length
factors (``hand.shape``), under their anatomical prior: the prior's whitened residuals times
``shape_noise_mm`` (the SfM joints' assumed noise per coordinate) stand beside the joint
residuals, so a bone moves off the template's proportions only as far as the joints pay for
it (short bones, which noisy joints measure poorly, stay near the template). It runs after
the template's refinement, and only when that leaves at most ``max_shape_rmse_mm`` (a larger
residual is the joints' error, which a shape would absorb); the shape is kept only when it
explains significantly more of the joints than fitting 20 parameters to noise would
(``shape_test_p``), else the template's fit stands.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, make_T, transform_points, umeyama
from graspcap.tasks.hand.ik import MOVING, central_jacobian, closed_form_angles
from graspcap.tasks.hand.model import (
    RIGID_PALM_POINTS,
    TEMPLATE_BONE_LENGTHS_M,
    HandMesh,
    HandModel,
    HandSide,
)
from graspcap.tasks.hand.shape import MARGINAL_SD, ShapeCheck, check_shape, prior_residuals_log

# scipy: imported where used, so that importing the stage table stays cheap

STAGE_VERSION = "fit_hand/2"
STAGE = "fit_hand"
_RIGID = np.array(RIGID_PALM_POINTS)
_MOVING = np.array(MOVING).reshape(-1)  # the 15 keypoints the angles move


class FitMode(StrEnum):
    """What is optimised after the palm's Umeyama fit."""

    PALM_THEN_IK = "palm_then_ik"
    """The paper's two steps: Umeyama palm and scale, then IK of the angles with the palm fixed."""
    JOINT_REFINE = "joint_refine"
    """The two steps, then palm pose, scale and angles refined together (robust, bounded)."""


class RobustLoss(StrEnum):
    """``scipy.optimize.least_squares`` loss of the joint refinement."""

    LINEAR = "linear"
    SOFT_L1 = "soft_l1"
    HUBER = "huber"
    CAUCHY = "cauchy"


class FitHandConfig(StageConfig):
    """Input checks, the IK regulariser and the joint refinement's bounds."""

    mode: FitMode = FitMode.JOINT_REFINE
    """Paper two-step fit, or two steps then a joint refinement."""
    min_scale: float = 0.6
    """Smallest plausible hand scale (model at 1 is an adult mean); below fails the stage."""
    max_scale: float = 1.5
    """Largest plausible hand scale; above fails the stage."""
    min_palm_spread_mm: float = 10.0
    """RMS distance of the rigid palm targets from their centroid below this: coincident."""
    min_palm_aspect: float = 0.1
    """Second over first singular value of the centred rigid targets below this: collinear."""
    prior_weight_mm_per_rad: float = 0.2
    """Pull of every angle towards the rest pose: 1 rad away costs as much as this many mm of
    joint error. Small: it only decides DoFs the joints leave (nearly) open."""
    max_palm_shift_mm: float = 10.0
    """Joint refinement: largest move of the palm origin per axis from the Umeyama fit."""
    max_palm_turn_deg: float = 10.0
    """Joint refinement: largest turn of the palm per axis (palm frame) from the Umeyama fit."""
    max_scale_change: float = 0.05
    """Joint refinement: largest relative change of the scale from the Umeyama fit."""
    loss: RobustLoss = RobustLoss.SOFT_L1
    """Joint refinement loss on the per-coordinate joint residuals."""
    robust_scale_mm: float = 5.0
    """Residual (mm) where the robust loss starts to flatten."""
    at_limit_tol_deg: float = 0.5
    """An angle within this of a joint limit is reported as at the limit."""
    max_evaluations: int = 200
    """Cap on residual evaluations of each least squares."""
    estimate_shape: bool = True
    """Joint refinement: estimate the 20 per-bone length factors (``hand.shape``) under their
    prior; False keeps the template's proportions (one global scale)."""
    shape_noise_mm: float = 2.0
    """Assumed SD (mm, per coordinate) of the target joints: a bone factor one prior SD off
    the template costs as much as a joint coordinate this far off. Larger: the shape stays
    nearer the template."""
    max_shape_sd: float = 4.0
    """Bound of each bone's log length factor, in the prior's marginal SDs."""
    shape_test_p: float = 0.001
    """The shape is kept only when it explains more of the joints than 20 parameters fitted to
    noise of ``shape_noise_mm`` would with this probability: the drop of the joints' squared
    residual, in units of ``shape_noise_mm`` squared, above the chi-square quantile (20 degrees
    of freedom; a likelihood-ratio test against the template's proportions). 1: always kept."""
    max_shape_rmse_mm: float = 10.0
    """The shape is estimated only when the template's proportions leave at most this RMS
    joint residual: other hands' proportions leave 4.6-9.4 mm (``bench/wild_hand_misfit.py``,
    the wild rig's +-15 % bones); beyond that the joints' own errors dominate, and a shape
    fitted to them would absorb them."""


PRESETS: dict[str, FitHandConfig] = {
    "default": FitHandConfig(),
    "paper": FitHandConfig(mode=FitMode.PALM_THEN_IK),
    "noisy": FitHandConfig(robust_scale_mm=3.0, loss=RobustLoss.CAUCHY, max_palm_shift_mm=15.0,
                           shape_noise_mm=3.0),
}


@dataclass(frozen=True)
class HandFit:
    """Result of ``fit_hand`` (small: the mesh is rebuilt on demand by :meth:`mesh`).

    Attributes
    ----------
    side : HandSide
    T_w_p : (4, 4) float
        Palm frame in the world (origin at the wrist, +y to the middle MCP, +z palmar).
    scale : float
        Multiplies every model length.
    angles_rad : (20,) float
        Joint angles in ``hand.model.ANGLE_NAMES`` order, inside the limits.
    joints_fit_w : (21, 3) float
        The posed model's keypoints, metres.
    residual_mm : (21,) float
        Distance from each fitted joint to its target (NaN where the target is not finite).
    rmse_mm : float
        RMS of ``residual_mm`` over the joints with positive weight.
    palm_rmse_mm : float
        RMS residual of the rigid palm points right after the Umeyama fit.
    at_limit : (20,) bool
        Angles within ``at_limit_tol_deg`` of a joint limit.
    bone_scale : (20,) float
        The hand's shape: per-bone length factors on top of ``scale`` (``hand.shape``; ones,
        the default, when not estimated).
    shape_note : str
        Why the shape was not estimated though ``estimate_shape`` asked because the joints are
        too far off for it (empty otherwise; QA notes it).
    shape_chi2 : float
        The shape's likelihood-ratio statistic against the template's proportions (drop of the
        joints' squared residual over ``shape_noise_mm`` squared; NaN when not estimated); the
        shape is kept when it is above the ``shape_test_p`` quantile.
    """

    side: HandSide
    T_w_p: np.ndarray
    scale: float
    angles_rad: np.ndarray
    joints_fit_w: np.ndarray
    residual_mm: np.ndarray
    rmse_mm: float
    palm_rmse_mm: float
    at_limit: np.ndarray
    bone_scale: np.ndarray = field(default_factory=lambda: np.ones(20))
    shape_note: str = ""
    shape_chi2: float = float("nan")

    @property
    def shape_check(self) -> ShapeCheck:
        """The shape against the anatomical prior (``hand.shape.check_shape``)."""
        return check_shape(self.bone_scale)

    @property
    def bone_lengths_m(self) -> np.ndarray:
        """(20,) the fitted hand's bone lengths, metres, ``SKELETON`` order (the catalog's
        ``hand_shape``)."""
        return self.scale * self.bone_scale * TEMPLATE_BONE_LENGTHS_M

    def mesh(self) -> HandMesh:
        """The posed hand surface in the world (``HandModel.mesh``)."""
        return HandModel(self.side).mesh(self.angles_rad, self.T_w_p, self.scale,
                                         self.bone_scale)


def _check_inputs(joints_w, weights) -> tuple[np.ndarray, np.ndarray]:
    joints = np.asarray(joints_w, dtype=float)
    if joints.shape != (21, 3):
        raise StageError(STAGE, f"joints_w must be (21, 3), got {joints.shape}")
    w = np.ones(21) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (21,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise StageError(STAGE, f"weights must be 21 finite values >= 0, got shape {w.shape}")
    bad = np.nonzero((w > 0) & ~np.all(np.isfinite(joints), axis=1))[0]
    if len(bad):
        raise StageError(
            STAGE, f"joints {bad.tolist()} are not finite (NaN or inf); give them weight 0 "
            "to fit without them",
        )  # fmt: skip
    return joints, w


def _palm_similarity(
    model: HandModel, joints: np.ndarray, used: np.ndarray, config: FitHandConfig
) -> tuple[np.ndarray, float, float]:
    """(T_w_p, scale, palm RMSE mm) by Umeyama on the usable rigid points; raises if degenerate."""
    rigid = _RIGID[used[_RIGID]]
    if len(rigid) < 3:
        raise StageError(
            STAGE, f"only {len(rigid)} rigid palm points (0, 1, 5, 9, 13, 17) have weight > 0; "
            "need 3 to place the palm",
        )  # fmt: skip
    dst = joints[rigid]
    centred = dst - dst.mean(axis=0)
    spread_mm = 1e3 * np.sqrt(np.mean(np.sum(centred**2, axis=1)))
    if spread_mm < config.min_palm_spread_mm:
        raise StageError(
            STAGE, f"rigid palm points are (nearly) coincident: RMS spread {spread_mm:.2f} mm "
            f"< {config.min_palm_spread_mm} mm; the 3D joints are degenerate",
        )  # fmt: skip
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[1] < config.min_palm_aspect * sv[0]:
        raise StageError(
            STAGE, f"rigid palm points are (nearly) collinear (singular values "
            f"{np.round(sv, 4).tolist()}); the 3D joints are degenerate",
        )  # fmt: skip
    src = model.keypoints(model.rest_angles())[rigid]
    T_w_p, scale = umeyama(src, dst)
    if not config.min_scale <= scale <= config.max_scale:
        raise StageError(
            STAGE, f"hand scale {scale:.3f} outside [{config.min_scale}, {config.max_scale}] "
            "(model at 1 is an adult hand); are the joints in metres and of one hand?",
        )  # fmt: skip
    fitted = transform_points(T_w_p, scale * src)
    palm_rmse_mm = 1e3 * float(np.sqrt(np.mean(np.sum((fitted - dst) ** 2, axis=1))))
    return T_w_p, float(scale), palm_rmse_mm


def _solve_angles(
    model: HandModel, targets_p: np.ndarray, w: np.ndarray, scale: float, config: FitHandConfig
) -> np.ndarray:
    """IK with the palm fixed: angles (20,) in the limits for palm-frame targets at scale 1."""
    from scipy.optimize import least_squares

    lo, hi = model.lower_rad, model.upper_rad
    prior = model.rest_angles()
    usable = w > 0
    x0 = np.clip(closed_form_angles(model.side, targets_p, usable, prior), lo, hi)
    sw = 1e3 * scale * np.sqrt(w[_MOVING])[None, :, None]  # residuals in world mm
    target = np.where(usable[_MOVING, None], targets_p[_MOVING], 0.0)
    lam = config.prior_weight_mm_per_rad

    def batch(X: np.ndarray) -> np.ndarray:
        kp = model.keypoints_batch(X)[:, _MOVING]
        return np.concatenate([(sw * (kp - target)).reshape(len(X), -1), lam * (X - prior)], 1)

    step = np.full(20, 1e-6)
    sol = least_squares(
        lambda x: batch(x[None])[0], x0, jac=lambda x: central_jacobian(batch, x, step),
        bounds=(lo, hi), method="trf", x_scale=1.0, max_nfev=config.max_evaluations,
    )  # fmt: skip
    return np.clip(sol.x, lo, hi)


def _robust(res: np.ndarray, loss: RobustLoss, f: float) -> np.ndarray:
    """Residuals whose squares are ``least_squares``' robust cost of ``res`` (so that other
    residuals beside them stay quadratic): ``sign(r) f sqrt(rho((r / f)^2))``."""
    z = (res / f) ** 2
    if loss == RobustLoss.LINEAR:
        return res
    if loss == RobustLoss.SOFT_L1:
        rho = 2.0 * (np.sqrt(1.0 + z) - 1.0)
    elif loss == RobustLoss.HUBER:
        rho = np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0)
    else:
        rho = np.log1p(z)
    return np.sign(res) * f * np.sqrt(rho)


def _batch_keypoints(model: HandModel, angles: np.ndarray, log_shape: np.ndarray | None
                     ) -> np.ndarray:
    """Palm-frame keypoints (b, 21, 3) at scale 1 for angles (b, 20) and per-row log bone
    factors (b, 20) (None: the template)."""
    return model.keypoints_batch(angles, bone_scale=None if log_shape is None
                                 else np.exp(log_shape))


def _refine(
    model: HandModel,
    joints: np.ndarray,
    w: np.ndarray,
    T0: np.ndarray,
    scale0: float,
    angles0: np.ndarray,
    config: FitHandConfig,
    shape: bool,
) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
    """Palm turn (3, rad), shift (3, mm), log scale, angles and (with ``estimate_shape``) the
    20 log bone factors together; bounded and robust. Returns (T_w_p, scale, angles,
    bone_scale)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    R0, t0 = T0[:3, :3], T0[:3, 3]
    used = w > 0
    target = np.where(used[:, None], joints, 0.0)
    sw = 1e3 * np.sqrt(w)[None, :, None]
    prior = model.rest_angles()
    lam = config.prior_weight_mm_per_rad
    n = 27 + (20 if shape else 0)

    def batch(X: np.ndarray) -> np.ndarray:
        R = R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix()  # (b, 3, 3)
        t = t0 + 1e-3 * X[:, 3:6]
        s = scale0 * np.exp(X[:, 6])
        kp_p = _batch_keypoints(model, X[:, 7:27], X[:, 27:] if shape else None)
        kp_w = s[:, None, None] * np.einsum("bij,bkj->bki", R, kp_p) + t[:, None]
        res = (sw * (kp_w - target)).reshape(len(X), -1)
        angle_prior = lam * (X[:, 7:27] - prior)
        if not shape:
            return np.concatenate([res, angle_prior], axis=1)
        res = _robust(res, config.loss, config.robust_scale_mm)
        shape_prior = config.shape_noise_mm * prior_residuals_log(X[:, 27:])
        return np.concatenate([res, angle_prior, shape_prior], axis=1)

    turn = np.radians(config.max_palm_turn_deg)
    shift = config.max_palm_shift_mm
    ls_lo = max(np.log1p(-config.max_scale_change), np.log(config.min_scale / scale0))
    ls_hi = min(np.log1p(config.max_scale_change), np.log(config.max_scale / scale0))
    lo = np.concatenate([[-turn] * 3, [-shift] * 3, [min(ls_lo, 0.0)], model.lower_rad])
    hi = np.concatenate([[turn] * 3, [shift] * 3, [max(ls_hi, 0.0)], model.upper_rad])
    step = np.concatenate([[1e-6] * 3, [1e-3] * 3, [1e-6], [1e-6] * 20])
    if shape:
        lo = np.concatenate([lo, -config.max_shape_sd * MARGINAL_SD])
        hi = np.concatenate([hi, config.max_shape_sd * MARGINAL_SD])
        step = np.concatenate([step, [1e-6] * 20])
    x0 = np.concatenate([np.zeros(7), angles0, np.zeros(n - 27)])
    sol = least_squares(
        lambda x: batch(x[None])[0], x0, jac=lambda x: central_jacobian(batch, x, step),
        bounds=(lo, hi), method="trf", max_nfev=config.max_evaluations,
        **({} if shape else {"loss": config.loss.value, "f_scale": config.robust_scale_mm}),
    )  # fmt: skip
    x = sol.x
    T = make_T(R0 @ Rotation.from_rotvec(x[:3]).as_matrix(), t0 + 1e-3 * x[3:6])
    angles = np.clip(x[7:27], model.lower_rad, model.upper_rad)
    bone_scale = np.exp(np.clip(x[27:], lo[27:], hi[27:])) if shape else np.ones(20)
    return T, float(scale0 * np.exp(x[6])), angles, bone_scale


def fit_hand(
    joints_w: np.ndarray,
    side: HandSide,
    config: FitHandConfig = PRESETS["default"],
    weights: np.ndarray | None = None,
) -> HandFit:
    """Fit palm pose, scale, the 20 angles and (``estimate_shape``, joint refinement only) the
    per-bone shape of the ``side`` hand model to 3D joints.

    Parameters
    ----------
    joints_w : (21, 3) float
        Target joints in the world, metres, 21-keypoint order (e.g. ``reconstruct_hand``'s
        ``joints_w``).
    side : HandSide
        Which hand (from the session manifest).
    config : FitHandConfig
    weights : (21,) float, optional
        Non-negative weight per joint (e.g. from ``reconstruct_hand``'s inlier counts); joints
        with weight 0 are ignored and may be NaN. Default: all 1.

    Raises
    ------
    StageError
        Non-finite joints with positive weight, fewer than 3 usable rigid palm points,
        coincident or collinear palm points, or a scale outside [min_scale, max_scale].
    """
    from scipy.stats import chi2

    model = HandModel(side)
    joints, w = _check_inputs(joints_w, weights)
    used = w > 0
    T_w_p, scale, palm_rmse_mm = _palm_similarity(model, joints, used, config)
    targets_p = transform_points(inv_T(T_w_p), np.where(used[:, None], joints, 0.0)) / scale
    angles = _solve_angles(model, targets_p, w, scale, config)
    bone_scale, note, chi2_stat = np.ones(20), "", float("nan")
    if config.mode == FitMode.JOINT_REFINE:
        T_w_p, scale, angles, _ = _refine(model, joints, w, T_w_p, scale, angles, config, False)
        if config.estimate_shape:
            target = np.where(used[:, None], joints, 0.0)

            def rss_mm2(T, s, a, b=None) -> float:
                d2 = np.sum((model.keypoints(a, T, s, b) - target) ** 2, axis=1)
                return 1e6 * float(np.sum(w[used] * d2[used]))

            rss0 = rss_mm2(T_w_p, scale, angles)
            rmse_mm = float(np.sqrt(rss0 / np.sum(w[used])))
            if rmse_mm <= config.max_shape_rmse_mm:
                shaped = _refine(model, joints, w, T_w_p, scale, angles, config, True)
                chi2_stat = (rss0 - rss_mm2(*shaped)) / config.shape_noise_mm**2
                if chi2_stat > chi2.ppf(1.0 - config.shape_test_p, 20):
                    T_w_p, scale, angles, bone_scale = shaped
            else:
                note = (f"the template's fit leaves {rmse_mm:.1f} mm RMS > "
                        f"{config.max_shape_rmse_mm} mm: the joints' errors, not the hand's "
                        "proportions; the template's proportions kept")
    fit_w = model.keypoints(angles, T_w_p, scale, bone_scale)
    residual_mm = 1e3 * np.linalg.norm(fit_w - joints, axis=1)
    tol = np.radians(config.at_limit_tol_deg)
    at_limit = (angles <= model.lower_rad + tol) | (angles >= model.upper_rad - tol)
    return HandFit(
        side=HandSide(side),
        T_w_p=T_w_p,
        scale=scale,
        angles_rad=angles,
        joints_fit_w=fit_w,
        residual_mm=residual_mm,
        rmse_mm=float(np.sqrt(np.mean(residual_mm[used] ** 2))),
        palm_rmse_mm=palm_rmse_mm,
        at_limit=at_limit,
        bone_scale=bone_scale,
        shape_note=note,
        shape_chi2=chi2_stat,
    )


__all__ = [
    "PRESETS", "STAGE_VERSION", "FitHandConfig", "FitMode", "HandFit", "RobustLoss", "fit_hand",
]  # fmt: skip
