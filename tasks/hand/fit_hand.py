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
degrees: Umeyama sees only six noisy points, the refinement sees all of them.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, make_T, transform_points, umeyama
from graspcap.tasks.hand.ik import MOVING, central_jacobian, closed_form_angles
from graspcap.tasks.hand.model import RIGID_PALM_POINTS, HandMesh, HandModel, HandSide

STAGE_VERSION = "fit_hand/1"
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


PRESETS: dict[str, FitHandConfig] = {
    "default": FitHandConfig(),
    "paper": FitHandConfig(mode=FitMode.PALM_THEN_IK),
    "noisy": FitHandConfig(robust_scale_mm=3.0, loss=RobustLoss.CAUCHY, max_palm_shift_mm=15.0),
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

    def mesh(self) -> HandMesh:
        """The posed hand surface in the world (``HandModel.mesh``)."""
        return HandModel(self.side).mesh(self.angles_rad, self.T_w_p, self.scale)


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


def _refine(
    model: HandModel,
    joints: np.ndarray,
    w: np.ndarray,
    T0: np.ndarray,
    scale0: float,
    angles0: np.ndarray,
    config: FitHandConfig,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Palm turn (3, rad), shift (3, mm), log scale and angles together; bounded and robust."""
    R0, t0 = T0[:3, :3], T0[:3, 3]
    used = w > 0
    target = np.where(used[:, None], joints, 0.0)
    sw = 1e3 * np.sqrt(w)[None, :, None]
    prior = model.rest_angles()
    lam = config.prior_weight_mm_per_rad

    def batch(X: np.ndarray) -> np.ndarray:
        R = R0 @ Rotation.from_rotvec(X[:, :3]).as_matrix()  # (b, 3, 3)
        t = t0 + 1e-3 * X[:, 3:6]
        s = scale0 * np.exp(X[:, 6])
        kp_p = model.keypoints_batch(X[:, 7:])  # palm frame, scale 1
        kp_w = s[:, None, None] * np.einsum("bij,bkj->bki", R, kp_p) + t[:, None]
        res = (sw * (kp_w - target)).reshape(len(X), -1)
        return np.concatenate([res, lam * (X[:, 7:] - prior)], axis=1)

    turn = np.radians(config.max_palm_turn_deg)
    shift = config.max_palm_shift_mm
    ls_lo = max(np.log1p(-config.max_scale_change), np.log(config.min_scale / scale0))
    ls_hi = min(np.log1p(config.max_scale_change), np.log(config.max_scale / scale0))
    lo = np.concatenate([[-turn] * 3, [-shift] * 3, [min(ls_lo, 0.0)], model.lower_rad])
    hi = np.concatenate([[turn] * 3, [shift] * 3, [max(ls_hi, 0.0)], model.upper_rad])
    x0 = np.concatenate([np.zeros(7), angles0])
    step = np.concatenate([[1e-6] * 3, [1e-3] * 3, [1e-6], [1e-6] * 20])
    sol = least_squares(
        lambda x: batch(x[None])[0], x0, jac=lambda x: central_jacobian(batch, x, step),
        bounds=(lo, hi), method="trf", loss=config.loss.value, f_scale=config.robust_scale_mm,
        max_nfev=config.max_evaluations,
    )  # fmt: skip
    x = sol.x
    T = make_T(R0 @ Rotation.from_rotvec(x[:3]).as_matrix(), t0 + 1e-3 * x[3:6])
    return T, float(scale0 * np.exp(x[6])), np.clip(x[7:], model.lower_rad, model.upper_rad)


def fit_hand(
    joints_w: np.ndarray,
    side: HandSide,
    config: FitHandConfig = PRESETS["default"],
    weights: np.ndarray | None = None,
) -> HandFit:
    """Fit palm pose, scale and the 20 angles of the ``side`` hand model to 3D joints.

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
    model = HandModel(side)
    joints, w = _check_inputs(joints_w, weights)
    used = w > 0
    T_w_p, scale, palm_rmse_mm = _palm_similarity(model, joints, used, config)
    targets_p = transform_points(inv_T(T_w_p), np.where(used[:, None], joints, 0.0)) / scale
    angles = _solve_angles(model, targets_p, w, scale, config)
    if config.mode == FitMode.JOINT_REFINE:
        T_w_p, scale, angles = _refine(model, joints, w, T_w_p, scale, angles, config)
    fit_w = model.keypoints(angles, T_w_p, scale)
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
    )


__all__ = [
    "PRESETS", "STAGE_VERSION", "FitHandConfig", "FitMode", "HandFit", "RobustLoss", "fit_hand",
]  # fmt: skip
