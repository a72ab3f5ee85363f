"""The hand model inside structure from motion (the paper's Eq. 2) as a GTSAM factor graph.

Variables: one camera per frame ``C(i)`` (``gtsam.Pose3`` holding ``T_c_p``, the palm in that
camera: the static hand's palm frame is the solve's world, so there is no gauge to hold), the
20 joint angles ``A`` (vector), the log per-bone length factors ``B`` (vector (20,),
``SKELETON`` order, the ``bone_scale`` of ``HandModel.keypoints``) and the log global scale
``S`` (vector (1,)). ``J(Phi)`` are the model's 21 keypoints in the palm frame.

Factors (``gtsam.CustomFactor``, analytic Jacobians except the angles' derivative of ``J``,
which is a central difference of the model, computed once per linearisation point and
shared by every factor):

- one reprojection factor per detection, ``pi(K, T_c_p J_j(Phi)) - x_ij``, sigma from the
  detection's confidence, under a robust (Cauchy) loss: a swapped finger or a stray
  joint costs little and pulls little;
- one range factor per depth reading kept by the caller's gate, ``z_c(J_j) - (d_ij + s
  r_j)`` (the camera sees the skin ``r_j`` above the joint centre, ``r`` scaled with the
  hand), Huber: these fix the metric scale, as in ``reconstruct_hand``;
- the joint limits as one-sided priors on ``A``, a weak pull of ``A`` towards the rest pose
  (decides only what the pixels leave open), a Gaussian prior on ``B`` (the provisional
  shape prior: ``tasks/hand/shape.py`` will give the anatomical one) and a weak prior on
  ``S`` (holds the scale where no depth reading is kept).

GTSAM's Python wheel has no TBB, so the solve is single-threaded and deterministic.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from graspcap.tasks.hand.model import SKELETON, SURFACE_OFFSET_M, HandModel, HandSide
from graspcap.tasks.hand.shape import PRIOR_SQRT_INFORMATION
from graspcap.tasks.hand_sfm.graph import lm_params

# gtsam: imported where used, so that importing the stage table stays cheap
if TYPE_CHECKING:
    import gtsam

A_KEY, B_KEY, S_KEY = (ord(c) << 56 for c in "abs")  # gtsam.symbol(c, 0): c in the top byte
N_HAND = 41
"""Hand parameters: 20 angles, 20 log bone factors, 1 log scale."""


def camera_key(i: int) -> int:
    """Key of frame ``i``'s camera ``T_c_p``."""
    import gtsam

    return gtsam.symbol("c", int(i))


def _chain_matrix() -> np.ndarray:
    """(21, 20) 1 where bone k (``SKELETON`` order) lies between the wrist and keypoint j."""
    parent = {child: k for k, (_, child) in enumerate(SKELETON)}
    C = np.zeros((21, 20))
    for j in range(1, 21):
        k = j
        while k in parent:
            C[j, parent[k]] = 1.0
            k = SKELETON[parent[k]][0]
    return C


CHAIN = _chain_matrix()
_PARENT = np.array([p for p, _ in SKELETON])
_CHILD = np.array([c for _, c in SKELETON])


class HandKinematics:
    """``J(Phi)`` (21, 3) in the palm frame and its Jacobian (21, 3, 41) for one side.

    A keypoint is the sum of its chain's bone vectors, each its template vector at the angles
    times its length factor: ``J_j = s sum_k C_jk f_k v_k(angles)``, so the derivatives in the
    log factors and the log scale are exact; those in the angles are central differences of
    ``HandModel.keypoints_batch``. The last point's result is kept (every factor of one
    linearisation asks for the same point)."""

    def __init__(self, side: HandSide, step_rad: float = 1e-6):
        self.model = HandModel(side)
        self.step = step_rad
        self._last: tuple[bytes, tuple[np.ndarray, np.ndarray]] | None = None

    def bones(self, angles: np.ndarray) -> np.ndarray:
        """Template bone vectors (b, 20, 3) at angles (b, 20), unit scale and factors."""
        kp = self.model.keypoints_batch(np.asarray(angles, float))
        return kp[:, _CHILD] - kp[:, _PARENT]

    def keypoints(self, angles: np.ndarray, log_bone: np.ndarray, log_scale: float
                  ) -> np.ndarray:
        """(21, 3) palm-frame keypoints."""
        v = self.bones(np.asarray(angles, float)[None])[0]
        return np.exp(log_scale) * CHAIN @ (np.exp(log_bone)[:, None] * v)

    def evaluate(self, angles: np.ndarray, log_bone: np.ndarray, log_scale: float
                 ) -> tuple[np.ndarray, np.ndarray]:
        """(J (21, 3), dJ/d[angles, log_bone, log_scale] (21, 3, 41))."""
        key = np.concatenate([angles, log_bone, [log_scale]]).tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        h = self.step
        steps = np.concatenate([np.eye(20) * h, -np.eye(20) * h])
        v_all = self.bones(np.concatenate([angles[None], angles[None] + steps]))
        s, f = np.exp(log_scale), np.exp(log_bone)
        fv = f[None, :, None] * v_all  # (41, 20, 3)
        J = s * CHAIN @ fv[0]
        d_angles = s * np.einsum("jk,bkc->bjc", CHAIN, fv[1:21] - fv[21:]) / (2 * h)
        d_bone = s * CHAIN[:, :, None] * fv[0][None]  # (21, 20, 3)
        dJ = np.concatenate(
            [d_angles.transpose(1, 2, 0), d_bone.transpose(0, 2, 1), J[:, :, None]], axis=2
        )
        self._last = (key, (J, dJ))
        return J, dJ


def _hand_params(values: gtsam.Values) -> tuple[np.ndarray, np.ndarray, float]:
    return values.atVector(A_KEY), values.atVector(B_KEY), float(values.atVector(S_KEY)[0])


def _camera_point(T: gtsam.Pose3, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """p_c, d p_c / d xi (3, 6) for GTSAM's right perturbation ``T Exp(xi)``, and R."""
    R = T.rotation().matrix()
    pc = R @ p + T.translation()
    skew = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    return pc, np.concatenate([-R @ skew, R], axis=1), R


def reprojection_factor(kin: HandKinematics, K: np.ndarray, i: int, j: int, uv: np.ndarray,
                        noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """Pixel residual (2,) of keypoint ``j`` seen at ``uv`` in frame ``i``."""
    import gtsam

    fx, fy, skew, cx, cy = K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2]
    uv = np.asarray(uv, float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        T = values.atPose3(this.keys()[0])
        J, dJ = kin.evaluate(*_hand_params(values))
        pc, dpc_dxi, R = _camera_point(T, J[j])
        x, y, z = pc
        z = z if abs(z) > 1e-9 else 1e-9
        proj = np.array([fx * x / z + skew * y / z + cx, fy * y / z + cy])
        if H is not None:
            dproj = np.array([[fx / z, skew / z, -(fx * x + skew * y) / (z * z)],
                              [0.0, fy / z, -fy * y / (z * z)]])
            dh = dproj @ R @ dJ[j]  # (2, 41)
            H[0] = dproj @ dpc_dxi
            H[1], H[2], H[3] = dh[:, :20], dh[:, 20:40], dh[:, 40:]
        return proj - uv

    return gtsam.CustomFactor(noise, [camera_key(i), A_KEY, B_KEY, S_KEY], error)


def range_factor(kin: HandKinematics, i: int, j: int, depth_m: float, offset_m: float,
                 noise: gtsam.noiseModel.Base, front_weight: float = 1.0) -> gtsam.CustomFactor:
    """Depth residual (1,): the joint's camera z minus the reading plus the skin offset
    (``offset_m`` at unit scale, scaled with the hand), times ``front_weight`` where the
    reading lies in front of the skin: a reading is the first surface on the pixel's ray, the
    hand's skin or something before it (the held object, another finger), never behind it."""

    import gtsam

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        T = values.atPose3(this.keys()[0])
        angles, log_bone, log_scale = _hand_params(values)
        J, dJ = kin.evaluate(angles, log_bone, log_scale)
        pc, dpc_dxi, R = _camera_point(T, J[j])
        s_off = np.exp(log_scale) * offset_m
        r = pc[2] - depth_m - s_off
        w = front_weight if r > 0.0 else 1.0
        if H is not None:
            dh = R[2:3] @ dJ[j]  # (1, 41)
            H[0] = w * dpc_dxi[2:3]
            H[1], H[2] = w * dh[:, :20], w * dh[:, 20:40]
            H[3] = w * (dh[:, 40:] - s_off)
        return np.array([w * r])

    return gtsam.CustomFactor(noise, [camera_key(i), A_KEY, B_KEY, S_KEY], error)


def limit_factor(lower: np.ndarray, upper: np.ndarray, sigma_rad: float) -> gtsam.CustomFactor:
    """One-sided priors (20,) keeping the angles inside the joint limits: zero inside."""
    import gtsam

    lo, hi = np.asarray(lower, float), np.asarray(upper, float)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        a = values.atVector(A_KEY)
        below, above = a < lo, a > hi
        if H is not None:
            H[0] = np.diag((below | above).astype(float))
        return np.where(below, a - lo, np.where(above, a - hi, 0.0))

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(20, sigma_rad), [A_KEY], error)


def _pose_residual(residual: Callable[..., np.ndarray], poses: list, H: list | None,
                   step: float) -> np.ndarray:
    """``residual(*poses)``; with ``H``, each pose's (6, 6) Jacobian by central differences
    along its retraction, written into ``H`` (a ``CustomFactor`` error function's job)."""
    if H is not None:
        for n, pose in enumerate(poses):
            cols = []
            for d in range(6):
                e = np.zeros(6)
                e[d] = step
                plus, minus = list(poses), list(poses)
                plus[n], minus[n] = pose.retract(e), pose.retract(-e)
                cols.append((residual(*plus) - residual(*minus)) / (2 * step))
            H[n] = np.stack(cols, axis=1)
    return residual(*poses)


def motion_factor(a: int, b: int, c: int, noise: gtsam.noiseModel.Base,
                  step: float = 1e-6) -> gtsam.CustomFactor:
    """Constant velocity of the virtual camera over frames a < b < c (6,): the per-frame
    relative motion ``Log(T_a T_b^-1) / (b - a)`` minus ``Log(T_b T_c^-1) / (c - b)`` (the
    hand turns smoothly in front of the camera; a turn-around costs little under a robust
    loss). Jacobians by central differences along each camera's retraction."""
    import gtsam

    ga, gb = float(b - a), float(c - b)

    def residual(Ta: gtsam.Pose3, Tb: gtsam.Pose3, Tc: gtsam.Pose3) -> np.ndarray:
        return (gtsam.Pose3.Logmap(Ta.compose(Tb.inverse())) / ga
                - gtsam.Pose3.Logmap(Tb.compose(Tc.inverse())) / gb)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        return _pose_residual(residual, [values.atPose3(k) for k in this.keys()], H, step)

    return gtsam.CustomFactor(noise, [camera_key(a), camera_key(b), camera_key(c)], error)


def link_factor(a: int, b: int, T_a_b: np.ndarray, noise: gtsam.noiseModel.Base,
                step: float = 1e-6) -> gtsam.CustomFactor:
    """A dense depth link (``hand_sfm.depth_links``): camera b in camera a measured as
    ``T_a_b``; residual (6,) ``Log(T_a_b^-1 T_ca_p T_cb_p^-1)``, the error of GTSAM's
    ``BetweenFactorPose3`` on camera poses, so the link's information applies as it is.
    Jacobians by central differences along each camera's retraction."""
    import gtsam

    meas_inv = gtsam.Pose3(np.asarray(T_a_b, float)).inverse()

    def residual(Ta: gtsam.Pose3, Tb: gtsam.Pose3) -> np.ndarray:
        return gtsam.Pose3.Logmap(meas_inv.compose(Ta.compose(Tb.inverse())))

    def error(this: gtsam.CustomFactor, values: gtsam.Values, H: list | None) -> np.ndarray:
        return _pose_residual(residual, [values.atPose3(k) for k in this.keys()], H, step)

    return gtsam.CustomFactor(noise, [camera_key(a), camera_key(b)], error)


@dataclass(frozen=True)
class HandPriors:
    """Sigmas of the priors on the hand parameters."""

    limit_sigma_rad: float
    rest_sigma_rad: float
    scale_sigma: float
    """Sigma of the log scale around its start."""


@dataclass(frozen=True)
class GraphSolve:
    """A solved graph: T_c_p (m, 4, 4) (NaN for frames left out), angles (20,), log_bone
    (20,), log_scale, LM iterations and the final graph error."""

    T_c_p: np.ndarray
    angles: np.ndarray
    log_bone: np.ndarray
    log_scale: float
    iterations: int
    error: float


def solve_graph(
    kin: HandKinematics,
    K: np.ndarray,
    uv: np.ndarray,
    use: np.ndarray,
    sigma_px: np.ndarray,
    T_c_p: np.ndarray,
    angles: np.ndarray,
    log_bone: np.ndarray,
    log_scale: float,
    priors: HandPriors,
    *,
    robust: Callable[[], gtsam.noiseModel.mEstimator.Base] | None,
    depth_m: np.ndarray | None = None,
    depth_sigma_m: float = 0.003,
    range_front_weight: float = 1.0,
    motion_sigmas: tuple[float, float] | None = None,
    links: Sequence = (),
    link_huber_k: float = 3.0,
    max_iterations: int = 100,
    relative_tol: float = 1e-6,
) -> GraphSolve:
    """Levenberg-Marquardt over the frames with a used detection.

    uv : (m, 21, 2) pixels; use : (m, 21) detections that get a factor; sigma_px (m, 21);
    T_c_p : (m, 4, 4) start cameras (frames with a use need a finite one); depth_m : (m, 21)
    readings that get a range factor (NaN: none); robust : the reprojections' m-estimator
    (None: plain least squares); motion_sigmas : (rad, m) per frame squared of the constant
    velocity priors between consecutive solved frames (None: none); links : dense depth links
    (``hand_sfm.depth_links.DepthLink``, frames of ``uv``) under a Huber loss.
    """
    import gtsam

    m = len(uv)
    frames = np.flatnonzero(use.any(1))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for i in frames:
        values.insert(camera_key(i), gtsam.Pose3(T_c_p[i]))
    values.insert(A_KEY, np.asarray(angles, float).copy())
    values.insert(B_KEY, np.asarray(log_bone, float).copy())
    values.insert(S_KEY, np.array([float(log_scale)]))
    for i, j in zip(*np.nonzero(use), strict=True):
        base = gtsam.noiseModel.Isotropic.Sigma(2, float(sigma_px[i, j]))
        noise = gtsam.noiseModel.Robust.Create(robust(), base) if robust else base
        graph.add(reprojection_factor(kin, K, int(i), int(j), uv[i, j], noise))
    if depth_m is not None:
        range_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(2.0),
            gtsam.noiseModel.Isotropic.Sigma(1, depth_sigma_m),
        )
        for i, j in zip(*np.nonzero(np.isfinite(depth_m) & use), strict=True):
            graph.add(range_factor(kin, int(i), int(j), float(depth_m[i, j]),
                                   float(SURFACE_OFFSET_M[j]), range_noise, range_front_weight))
    huber_link = gtsam.noiseModel.mEstimator.Huber.Create(link_huber_k)
    framed = set(frames.tolist())
    for link in links:
        if link.a in framed and link.b in framed:
            graph.add(link_factor(int(link.a), int(link.b), link.T_a_b, gtsam.noiseModel.Robust
                                  .Create(huber_link,
                                          gtsam.noiseModel.Gaussian.Information(link.information))))
    if motion_sigmas is not None and len(frames) >= 3:
        sig = np.repeat(np.asarray(motion_sigmas, float), 3)
        motion_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(2.0), gtsam.noiseModel.Diagonal.Sigmas(sig))
        for a, b, c in zip(frames[:-2], frames[1:-1], frames[2:], strict=True):
            graph.add(motion_factor(int(a), int(b), int(c), motion_noise))
    model = kin.model
    graph.add(limit_factor(model.lower_rad, model.upper_rad, priors.limit_sigma_rad))
    graph.add(gtsam.PriorFactorVector(A_KEY, model.rest_angles(),
                                      gtsam.noiseModel.Isotropic.Sigma(20, priors.rest_sigma_rad)))
    # the anatomical shape prior (``hand.shape``): Gaussian in the log factors around the template
    graph.add(gtsam.PriorFactorVector(
        B_KEY, np.zeros(20), gtsam.noiseModel.Gaussian.SqrtInformation(PRIOR_SQRT_INFORMATION)))
    graph.add(gtsam.PriorFactorVector(S_KEY, np.array([float(log_scale)]),
                                      gtsam.noiseModel.Isotropic.Sigma(1, priors.scale_sigma)))
    optimizer = gtsam.LevenbergMarquardtOptimizer(
        graph, values, lm_params(max_iterations, relative_tol)
    )
    result = optimizer.optimize()
    T_out = np.full((m, 4, 4), np.nan)
    for i in frames:
        T_out[i] = result.atPose3(camera_key(i)).matrix()
    a, b, s = _hand_params(result)
    return GraphSolve(T_out, a, b, s, int(optimizer.iterations()), float(graph.error(result)))


def project_hand(K: np.ndarray, T_c_p: np.ndarray, J: np.ndarray) -> np.ndarray:
    """Pixels (m, 21, 2) of palm-frame keypoints J (21, 3) in cameras T_c_p (m, 4, 4);
    NaN for NaN cameras or points behind the camera."""
    pc = np.einsum("mab,jb->mja", T_c_p[:, :3, :3], J) + T_c_p[:, None, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = np.einsum("ab,mjb->mja", K, pc)
        uv = uv[..., :2] / uv[..., 2:]
        uv[pc[..., 2] <= 0] = np.nan
    return uv


__all__ = [
    "A_KEY", "B_KEY", "CHAIN", "N_HAND", "S_KEY", "GraphSolve", "HandKinematics", "HandPriors",
    "camera_key", "limit_factor", "link_factor", "motion_factor", "project_hand", "range_factor",
    "reprojection_factor", "solve_graph",
]  # fmt: skip
