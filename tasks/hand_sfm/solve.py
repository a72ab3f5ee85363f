"""The solves of ``reconstruct_hand``: reprojection-only with outlier rounds, the
depth sweep (scale samples and the frames' surfaces), and the metric RGB-D solve.

The functions take the stage's ``ReconstructConfig`` as ``cfg``; ``reconstruct_hand`` strings
them together.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T
from graspcap.tasks.hand_sfm.frame_screen import (
    jumping_poses,
    robust_sigma,
    swapped_fingers,
    unexplained_frames,
)
from graspcap.tasks.hand_sfm.graph import bundle_adjust, reprojection_residuals
from graspcap.tasks.hand_sfm.metric_scale import ratio_mode
from graspcap.tasks.hand_sfm.two_view_init import normalise

# scipy: imported where used, so that importing the stage table stays cheap

STAGE = "reconstruct_hand"


class DepthUse(StrEnum):
    """How the aligned depth enters the solve."""

    SCALE = "scale"
    """Only the metric scale (the paper's reprojection-only SfM, then scaled)."""
    FACTORS = "factors"
    """Also one range factor per inlier keypoint with valid depth (RGB-D bundle adjustment);
    per-frame poses of a small, distant hand are ill-conditioned from pixels alone."""



def fill_poses(T_c_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate missing poses (NaN) from their neighbours (slerp); hold at the ends."""
    from scipy.spatial.transform import Rotation, Slerp

    m = len(T_c_w)
    valid = np.all(np.isfinite(T_c_w.reshape(m, -1)), axis=1)
    if valid.all():
        return T_c_w, valid
    idx = np.flatnonzero(valid)
    T_w_c = np.stack([inv_T(T) for T in T_c_w[idx]])
    t = np.clip(np.arange(m), idx[0], idx[-1])
    rot = Slerp(idx, Rotation.from_matrix(T_w_c[:, :3, :3]))(t).as_matrix()
    out = np.tile(np.eye(4), (m, 1, 1))
    out[:, :3, :3] = rot
    out[:, :3, 3] = np.stack([np.interp(t, idx, T_w_c[:, k, 3]) for k in range(3)], axis=1)
    return np.stack([inv_T(T) for T in out]), valid


def sample_depth(cfg, conf, inlier, T_c_w, X, frame_at):
    """Depth readings (m, 21) of the confident inliers (NaN where not sampled), camera-frame
    joint z (m, 21) and the surfaces (list, None where none) of the frames sampled.

    ``frame_at(i) -> FrameDepth`` (``hand_sfm.depth_sweep``) gives solve frame i's readings at
    every usable keypoint and its surface, each frame computed once per stage call.
    """
    m = len(conf)
    sample = inlier & (conf >= cfg.depth_min_confidence)
    depth = np.full((m, 21), np.nan)
    surfaces: list = [None] * m
    for i in np.flatnonzero(sample.any(1)):
        fd = frame_at(int(i))
        depth[i, sample[i]] = fd.readings[sample[i]]
        surfaces[i] = fd.surface
    z = np.einsum("mb,jb->mj", T_c_w[:, 2, :3], X) + T_c_w[:, 2, 3][:, None]
    return depth, z, surfaces


def depth_scorer(cfg, conf, ok, frame_at, offset):
    """``score(frames, T_c_w, X)``: share of depth readings within ``scale_rel_tol`` / 2 of the
    densest ratio ``(depth + offset) / z`` (scale-free, so it applies before the scale);
    ``frame_at`` as in :func:`sample_depth`."""
    sample = ok & (conf >= cfg.depth_min_confidence)

    def score(frames: np.ndarray, T_c_w: np.ndarray, X: np.ndarray) -> float:
        ratios = []
        for i, T in zip(frames, T_c_w, strict=True):
            if not np.all(np.isfinite(T)):
                continue
            readings = np.where(sample[i], frame_at(int(i)).readings, np.nan)
            z = X @ T[2, :3] + T[2, 3]
            ratios.append((readings + offset) / z)
        r = np.concatenate(ratios) if ratios else np.zeros(0)
        r = r[np.isfinite(r) & (r > 0)]
        if len(r) < cfg.min_scale_samples:
            return 0.0
        tol = cfg.scale_rel_tol / 2
        return float(np.mean(np.abs(r / ratio_mode(r, tol) - 1.0) < tol))

    return score


@dataclass(frozen=True)
class NoiseScreen:
    """What the reprojection-only solve measured and rejected (``hand_sfm.frame_screen``).

    sigma_px : per-coordinate pixel noise of the accepted frames' detections (robust, from
        the residuals' median; NaN when not measured); gate_px : the inlier gate, at least
        ``outlier_px``, else ``outlier_sigmas * sigma_px``; noise_factor : the confidence-
        scaled sigmas were multiplied by this (>= 1) for the solves after the robust one;
    rejected : solve row -> reason, frames dropped whole; swapped : (m, 21) bool, detections
        of two neighbouring fingers whose labels are exchanged (not used).
    """

    sigma_px: float
    gate_px: float
    noise_factor: float
    rejected: dict[int, str]
    swapped: np.ndarray

    def accepted(self, m: int) -> np.ndarray:
        """(m,) bool: rows not rejected."""
        keep = np.ones(m, bool)
        keep[list(self.rejected)] = False
        return keep


def _measure(cfg, uv, ok, sigma, K, T_c_w, X, res, rejected, first_frame):
    """Rejected frames (row -> reason, ``rejected`` extended), the gate and the noise after a
    solve: iterated until the frames the static hand does not explain settle."""
    rejected = dict(rejected)
    for _ in range(4):
        keep = ok.copy()
        keep[list(rejected)] = False
        sigma_px = robust_sigma(np.where(keep, res, np.nan))
        gate = max(cfg.outlier_px, cfg.outlier_sigmas * sigma_px) if np.isfinite(sigma_px) \
            else cfg.outlier_px
        found = unexplained_frames(
            np.where(keep, res, np.nan), keep, gate, min_share=cfg.frame_min_inlier_share,
            first_frame=first_frame,
        )  # fmt: skip
        accepted = ok.any(1)
        accepted[list(rejected | found)] = False
        found |= jumping_poses(T_c_w, X, K, accepted, cfg.pose_jump_gates * gate,
                               first_frame=first_frame, max_gap=cfg.jump_max_gap,
                               motion_share=cfg.jump_motion_share,
                               residual_px=np.where(keep, res, np.nan))  # fmt: skip
        if not found:
            break
        rejected |= found
    keep = ok.copy()
    keep[list(rejected)] = False
    Xc = np.einsum("mab,jb->mja", T_c_w[:, :3, :3], X) + T_c_w[:, None, :3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        proj = (Xc[..., :2] / Xc[..., 2:]) * np.diag(K)[:2] + K[:2, 2]
    swapped = swapped_fingers(uv, keep, proj, gate, gain=cfg.swap_gain)
    inl = keep & ~swapped & (res < gate)
    w = np.where(inl, res / sigma, np.nan)
    factor = max(1.0, robust_sigma(w)) if inl.any() else 1.0
    return NoiseScreen(float(sigma_px), float(gate), float(factor), rejected, swapped)


def solve_visual(cfg, uv, ok, sigma, K, T_c_w, X, pair, *, rejected=None, first_frame=0):
    """Robust reprojection-only solve, then reject-and-re-solve rounds ->
    (ba, res, inlier, n, screen).

    With ``cfg.frame_rejection`` the robust solve's residuals give the noise scale, the gate,
    the frames the static hand does not explain and the swapped fingers (``NoiseScreen``;
    ``rejected`` : row -> reason, frames already rejected before the solve, kept so); each
    round re-measures them over the accepted frames (a frame once rejected stays so). Without
    it the gate is ``outlier_px`` and nothing is rejected whole.
    """
    m = len(uv)
    screen = NoiseScreen(float("nan"), cfg.outlier_px, 1.0, dict(rejected or {}),
                         np.zeros(ok.shape, bool))
    use, huber = ok & screen.accepted(m)[:, None], cfg.huber_k
    for rounds in range(1, cfg.outlier_rounds + 2):  # noqa: B007 (returned)
        ba = bundle_adjust(
            uv,
            use,
            sigma * screen.noise_factor,
            K,
            T_c_w,
            X,
            anchor=pair.a,
            scale_ref=pair.b,
            huber_k=huber,
            scale_sigma_rel=cfg.scale_prior_rel,
            min_observations=cfg.min_points_per_frame // 2 + 1,
            max_iterations=(
                cfg.visual_max_iterations
                if cfg.depth_use is DepthUse.FACTORS
                else cfg.max_iterations
            ),
            relative_tol=(
                cfg.robust_relative_tol
                if huber is not None
                else cfg.visual_relative_tol
                if cfg.depth_use is DepthUse.FACTORS
                else 1e-7
            ),
        )
        T_c_w, X = ba.T_c_w, ba.points_w
        res = reprojection_residuals(K, T_c_w, X, uv)
        if cfg.frame_rejection:
            screen = _measure(cfg, uv, ok, sigma, K, T_c_w, X, res, screen.rejected,
                              first_frame)
        inlier = ok & screen.accepted(m)[:, None] & ~screen.swapped & (res < screen.gate_px)
        if not inlier.any():
            raise StageError(
                STAGE,
                f"every detection is an outlier (residual >= {screen.gate_px:.1f} px "
                "after the robust solve): the keypoints are not those of one static hand",
            )
        if np.array_equal(inlier, use) and huber is None:
            break
        use, huber = inlier, None
    return ba, res, inlier, rounds, screen


def rotation_span_deg(T_c_w: np.ndarray) -> float:
    """Largest rotation (degrees) of a posed camera (m, 4, 4) away from the first posed one."""
    posed = np.all(np.isfinite(T_c_w.reshape(len(T_c_w), -1)), axis=1)
    R = T_c_w[posed, :3, :3]
    if len(R) < 2:
        return 0.0
    cos = (np.einsum("mij,ij->m", R, R[0]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())


def ranges(T_c_w, X):
    """Distance (m, 21) from each camera centre to each joint."""
    return np.linalg.norm(
        np.einsum("mab,jb->mja", T_c_w[:, :3, :3], X) + T_c_w[:, None, :3, 3], axis=2
    )


def gate_readings(
    residual_m: np.ndarray, gate_m: float, frame_share: float, min_readings: int,
    max_shift_m: float = np.inf,
) -> np.ndarray:
    """Range readings that get a factor: (m, 21) bool from the residuals (m, 21) (reading
    minus solve, NaN where none).

    A reading within ``gate_m`` of the solve is kept. A frame that keeps fewer than
    ``frame_share`` of its readings this way, while at least that share (and at least
    ``min_readings``) agree with each other within ``gate_m`` around one common offset of at
    most ``max_shift_m``, keeps those instead: its pose is off in depth, which the pixels of
    a small hand barely fix (a synthetic frame solved 18 mm too far got no range factor at
    all and stayed there; as the first steady frame it shifted the whole hand by 18 mm).
    With ``frame_share`` 0 only the plain gate applies.
    """
    keep, lost, shifted = _frame_gate(residual_m, gate_m, frame_share, min_readings, max_shift_m)
    keep[lost] = shifted
    return keep


def frames_off_in_depth(
    residual_m: np.ndarray, gate_m: float, frame_share: float, min_readings: int,
    max_shift_m: float = np.inf,
) -> np.ndarray:
    """(m,) bool: frames whose readings ``gate_readings`` would keep around an offset of their
    own (they agree with each other, not with the solve); none when ``frame_share`` is 0."""
    off = np.zeros(len(residual_m), bool)
    off[_frame_gate(residual_m, gate_m, frame_share, min_readings, max_shift_m)[1]] = True
    return off


def _frame_gate(residual_m, gate_m, frame_share, min_readings, max_shift_m):
    """The plain gate (m, 21), the frames kept around an offset of their own (k,) and their
    readings kept (k, 21)."""
    r = np.asarray(residual_m, dtype=float)
    none = np.zeros(0, int), np.zeros((0, r.shape[1]), bool)
    with np.errstate(invalid="ignore"):
        keep = np.abs(r) <= gate_m
        if frame_share <= 0:
            return (keep, *none)
        n = np.isfinite(r).sum(1)
        need = np.maximum(frame_share * n, min_readings)
        lost = np.flatnonzero((keep.sum(1) < frame_share * n) & (n >= min_readings))
        if not len(lost):
            return (keep, *none)
        rl = r[lost]
        near = np.abs(rl[:, :, None] - rl[:, None, :]) <= gate_m  # (k, 21, 21)
        support = np.where(np.isfinite(rl), near.sum(2), -1)  # readings near each reading
        members = near[np.arange(len(lost)), support.argmax(1)]
        centre = np.array([np.median(rl[i, members[i]]) for i in range(len(lost))])
        shifted = np.abs(rl - centre[:, None]) <= gate_m
        ok = (shifted.sum(1) >= need[lost]) & (np.abs(centre) <= max_shift_m)
    return keep, lost[ok], shifted[ok]


def solve_rgbd(cfg, K, uv, ok, inlier, sigma, T_c_w, X, depth, offset, anchor, link_fn=None,
               screen: NoiseScreen | None = None, first_link_round: int = 2):
    """Reprojection + range factors, metric. Each round gates every reading afresh against
    the current solution: ``depth_gate_m`` against the scaled visual solve, then
    ``range_gate_sigmas`` sigmas against the previous RGB-D solve. With ``link_fn``
    (``(T_c_w) -> links``) rounds 2 .. 1 + ``depth_links.rounds`` also get dense depth
    links measured from the previous round's solution (later rounds keep the last).
    Also returns the frames (m,) bool whose readings still agree with each other but not
    with the final solve (``frames_off_in_depth``). With ``screen`` (``solve_visual``'s) the
    final inliers are gated by its ``gate_px``, without its rejected frames and swapped
    fingers; else by ``outlier_px``. ``first_link_round`` 1 adds the links from the first
    round (a ``link_fn`` that registers from fixed cameras)."""
    m = len(uv)
    rays = np.concatenate(
        [normalise(K, uv.reshape(-1, 2)).reshape(m, 21, 2), np.ones((m, 21, 1))], 2
    )
    measured = np.where(
        np.isfinite(depth) & (depth > 0), (depth + offset) * np.linalg.norm(rays, axis=2), np.nan
    )
    gate = cfg.depth_gate_m
    used = np.zeros((m, 21), bool)
    links: list = []
    link_rounds = cfg.depth_links.rounds if link_fn is not None else 0
    last_link_round = first_link_round + link_rounds - 1
    for rounds in range(1, max(cfg.range_rounds, last_link_round) + 1):  # noqa: B007
        keep = gate_readings(
            measured - ranges(T_c_w, X), gate, cfg.frame_gate_share, cfg.min_points_per_frame,
            cfg.frame_gate_max_m,
        )  # fmt: skip
        link_round = first_link_round <= rounds <= last_link_round
        if rounds > 1 and np.array_equal(keep, used) and not link_round:
            break
        used = keep
        if link_round:
            links = link_fn(T_c_w)
        ba = bundle_adjust(
            uv,
            inlier,
            sigma,
            K,
            T_c_w,
            X,
            anchor=anchor,
            scale_ref=None,
            huber_k=None,
            range_m=np.where(used, measured, np.nan),
            range_sigma_m=cfg.depth_sigma_m,
            min_observations=cfg.min_points_per_frame // 2 + 1,
            max_iterations=cfg.max_iterations,
            links=links,
        )
        T_c_w, X = ba.T_c_w, ba.points_w
        gate = cfg.range_gate_sigmas * cfg.depth_sigma_m
    res = reprojection_residuals(K, T_c_w, X, uv)
    off = frames_off_in_depth(  # also with frame_gate_share 0: what it would have moved
        measured - ranges(T_c_w, X), gate, cfg.frame_gate_share or 0.5,
        cfg.min_points_per_frame, cfg.frame_gate_max_m,
    )  # fmt: skip
    if screen is None:
        return T_c_w, X, res, ok & (res < cfg.outlier_px), rounds, used, links, off
    inl = ok & screen.accepted(m)[:, None] & ~screen.swapped & (res < screen.gate_px)
    return T_c_w, X, res, inl, rounds, used, links, off
