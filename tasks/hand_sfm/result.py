"""The result of ``reconstruct_hand`` and its assembly from a finished solve.

The solves work in the frame of the initial pair's first camera and, before the scale,
in its units; the result is metric and in the frame of the first steady camera
(``T_w_c[0] = I``), with the initialisation and the reprojection-only solve carried along
in the same frame for the diagnostics (``crosscheck_sfm`` starts from the latter).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.hand_sfm.depth_links import DepthLink
from graspcap.tasks.hand_sfm.graph import BundleResult
from graspcap.tasks.hand_sfm.metric_scale import ScaleEstimate
from graspcap.tasks.hand_sfm.solve import NoiseScreen, fill_poses
from graspcap.tasks.hand_sfm.two_view_init import Initialisation


@dataclass(frozen=True)
class SfmDiagnostics:
    """How the solve went.

    pair_frames : video frame indices of the initial pair; parallax_deg its median angle.
    rounds : solves run; lm_iterations : iterations of the last; error_* : graph errors.
    scale_samples / scale_inliers / scale_spread : see ``hand_sfm.metric_scale.ScaleEstimate``.
    T_w_c_init : (m, 4, 4) and joints_w_init : (21, 3), the initialisation in the output frame.
    T_w_c_visual, joints_w_visual, inlier_visual : the reprojection-only solve (scaled, output
        frame) and its inliers, the problem ``crosscheck_sfm`` hands to pycolmap.
    depth_inlier : (m, 21) bool, observations whose depth reading fixed the scale.
    range_factor : (m, 21) bool, observations whose depth reading entered the final solve as a
        range factor (none with ``depth_use = scale``).
    depth_links : (k, 2) int solve-frame pairs whose dense depth registration entered the
        final solve (``depth_icp``).
    """

    pair_frames: tuple[int, int]
    parallax_deg: float
    rounds: int
    lm_iterations: int
    error_initial: float
    error_final: float
    scale_samples: int
    scale_inliers: int
    scale_spread: float
    T_w_c_init: np.ndarray
    joints_w_init: np.ndarray
    T_w_c_visual: np.ndarray
    joints_w_visual: np.ndarray
    inlier_visual: np.ndarray
    depth_inlier: np.ndarray
    range_factor: np.ndarray
    depth_links: np.ndarray
    restarted_after: str = ""
    """The reason the solve from the two-view start failed when the result comes from the
    depth restart, else empty."""
    frame_rejected: tuple[str, ...] = ()
    """Per solve frame, why it was rejected whole (``hand_sfm.frame_screen``), "" where
    accepted; empty without ``frame_rejection``."""
    swapped: np.ndarray | None = None
    """(m, 21) bool, detections of two fingers whose labels were found exchanged (not used)."""
    noise_sigma_px: float = float("nan")
    """Per-coordinate pixel noise measured on the accepted frames after the robust solve."""
    gate_px: float = float("nan")
    """The inlier gate of the final solve (pixels)."""
    hand_size_px: float = float("nan")
    """Median diagonal of the detections' bounding box (the scale of the gates)."""


@dataclass(frozen=True)
class HandReconstruction:
    """Virtual cameras and the static hand, metric, ``T_w_c[0] = I``.

    steady_from : first steady frame; frames : (m,) video frame indices.
    T_w_c : (m, 4, 4); pose_valid : (m,) bool, False where the pose is interpolated.
    joints_w : (21, 3) metres; joint_valid : (21,) bool, False (and NaN) if unreconstructed.
    residuals_px : (m, 21), NaN for missing detections; inlier : (m, 21) bool.
    reproj_rmse_px : RMS residual over inliers; inlier_ratio : inliers / detections.
    scale_m_per_unit : metres per unit of the up-to-scale solve.
    """

    steady_from: int
    frames: np.ndarray
    T_w_c: np.ndarray
    pose_valid: np.ndarray
    joints_w: np.ndarray
    joint_valid: np.ndarray
    residuals_px: np.ndarray
    inlier: np.ndarray
    reproj_rmse_px: float
    inlier_ratio: float
    scale_m_per_unit: float
    diagnostics: SfmDiagnostics

def assemble(
    steady_from: int,
    T_c_w: np.ndarray,
    X: np.ndarray,
    res: np.ndarray,
    ok: np.ndarray,
    inlier: np.ndarray,
    *,
    init: Initialisation,
    s: float,
    T_vis: np.ndarray,
    X_vis: np.ndarray,
    inlier_vis: np.ndarray,
    rounds: int,
    ba: BundleResult,
    scale: ScaleEstimate,
    depth_inlier: np.ndarray,
    range_used: np.ndarray,
    links: Sequence[DepthLink],
    screen: NoiseScreen | None = None,
    hand_px: float = float("nan"),
) -> HandReconstruction:
    """The stage's result from a finished, checked solve.

    T_c_w : (m, 4, 4) metric poses (NaN rows unposed, interpolated here); X : (21, 3) metric
    joints; res : (m, 21) pixel residuals; ok, inlier : (m, 21) usable and inlier
    observations; init : the start (scaled by ``s`` here); T_vis, X_vis, inlier_vis : the
    scaled reprojection-only solve; ba : the last reprojection-only solve's statistics;
    screen : what the reprojection-only solve measured and rejected (the inlier ratio is then
    of the accepted frames' detections); hand_px : the hand's image size.
    """
    m = len(T_c_w)
    pair = init.pair
    T_c_w, pose_valid = fill_poses(T_c_w)
    T_0_w = T_c_w[0].copy()

    def to_output(T_c_w_any: np.ndarray, X_any: np.ndarray, factor: float = 1.0):
        """Into the frame of the final camera 0 (so T_w_c[0] = I), metres."""
        T_c_0 = T_c_w_any.copy()
        T_c_0[:, :3, 3] *= factor
        T_c_0 = T_c_0 @ inv_T(T_0_w)
        return np.stack([inv_T(T) for T in T_c_0]), (factor * X_any) @ T_0_w[:3, :3].T + T_0_w[
            :3, 3
        ]

    T_w_c, joints_w = to_output(T_c_w, X)
    T_w_c[0] = np.eye(4)
    T_w_c_init, joints_w_init = to_output(fill_poses(init.T_c_w)[0], init.points_w, s)
    T_w_c_vis, joints_w_vis = to_output(fill_poses(T_vis)[0], X_vis)

    residuals = np.where(ok, res, np.nan)
    residuals[~pose_valid] = np.nan
    inlier &= pose_valid[:, None]
    n_inl = int(inlier.sum())
    judged = ok if screen is None else ok & screen.accepted(m)[:, None]
    rejected = () if screen is None else tuple(screen.rejected.get(i, "") for i in range(m))
    return HandReconstruction(
        steady_from=int(steady_from),
        frames=np.arange(steady_from, steady_from + m),
        T_w_c=T_w_c,
        pose_valid=pose_valid,
        joints_w=joints_w,
        joint_valid=np.all(np.isfinite(joints_w), axis=1),
        residuals_px=residuals,
        inlier=inlier,
        reproj_rmse_px=float(np.sqrt(np.mean(res[inlier] ** 2))) if n_inl else float("nan"),
        inlier_ratio=n_inl / max(int(judged.sum()), 1),
        scale_m_per_unit=s,
        diagnostics=SfmDiagnostics(
            pair_frames=(steady_from + pair.a, steady_from + pair.b),
            parallax_deg=pair.parallax_deg,
            rounds=rounds,
            lm_iterations=ba.iterations,
            error_initial=ba.error_initial,
            error_final=ba.error_final,
            scale_samples=scale.n_samples,
            scale_inliers=scale.n_inliers,
            scale_spread=scale.spread,
            T_w_c_init=T_w_c_init,
            joints_w_init=joints_w_init,
            T_w_c_visual=T_w_c_vis,
            joints_w_visual=joints_w_vis,
            inlier_visual=inlier_vis,
            depth_inlier=depth_inlier,
            range_factor=range_used,
            depth_links=np.array([(k.a, k.b) for k in links], dtype=int).reshape(-1, 2),
            frame_rejected=rejected,
            swapped=None if screen is None else screen.swapped,
            noise_sigma_px=float("nan") if screen is None else screen.sigma_px,
            gate_px=float("nan") if screen is None else screen.gate_px,
            hand_size_px=float(hand_px),
        ),
    )
