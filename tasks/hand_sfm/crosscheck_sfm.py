"""Cross-check of ``reconstruct_hand``: the same inlier observations solved by pycolmap
(COLMAP's BA).

One PINHOLE camera from K, one image (trivial rig and frame) per posed video frame, one 3D
point per reconstructed joint with its inlier observations as the track; poses start from
the stage's reprojection-only solve, perturbed (or from the GTSAM initialisation).
pycolmap's Ceres bundle adjuster runs single-threaded with the intrinsics held. GTSAM solves
the identical problem (same tracks, unit pixel weights, no depth) from the unperturbed
reprojection-only solve, and the two solutions are compared after a similarity (Umeyama on
the joints): that is the solver cross-check, two solvers reaching one optimum from two
starts. How far that pixels-only
optimum lies from the stage's RGB-D result (depth factors and links) is reported beside it
(``max_rgbd_joint_discrepancy_m``): millimetres, the depth's contribution, not a failure.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, make_T, rotation_error_deg, umeyama
from graspcap.tasks.hand_sfm.graph import bundle_adjust, reprojection_residuals
from graspcap.tasks.hand_sfm.reconstruct_hand import HandReconstruction

# pycolmap, scipy: imported where used, so that importing the stage table stays cheap

STAGE = "crosscheck_sfm"
STAGE_VERSION = "crosscheck_sfm/3"


class StartFrom(StrEnum):
    """Where pycolmap's poses and points start."""

    INITIALISATION = "initialisation"
    """GTSAM's robust initialisation (two-view + PnP), before any bundle adjustment."""
    PERTURBED = "perturbed"
    """GTSAM's reprojection-only solve (the stage's ``T_w_c_visual``, ``joints_w_visual``)
    with seeded random pose and point perturbations. (Perturbing the RGB-D result instead
    leaves Ceres crawling back along the flat depth direction for 80-130 iterations.)"""


class GtsamStart(StrEnum):
    """Where the GTSAM solve of the cross-check problem starts."""

    VISUAL = "visual"
    """The stage's own reprojection-only optimum (confidence-weighted, already near the
    unit-weight optimum): GTSAM converges in a few iterations, from a start other than
    pycolmap's, so agreement means both reach one optimum from two places."""
    SAME = "same"
    """pycolmap's start (``start_from``), under a stiff scale gauge: LM crawls along the
    flat scale and depth direction for tens of iterations."""


class CrosscheckConfig(StageConfig):
    start_from: StartFrom = StartFrom.PERTURBED
    """Start of pycolmap's solve. From the initialisation pycolmap (pixels only, no robust
    loss) can settle in another minimum on short sequences, so the default checks that the
    GTSAM optimum, perturbed, is also where pycolmap's solve ends."""
    perturb_deg: float = 2.0
    """Rotation perturbation (degrees, per axis sigma) for ``start_from = perturbed``."""
    perturb_m: float = 0.005
    """Translation and point perturbation (metres, per axis sigma) for ``perturbed``."""
    seed: int = 0
    """Seed of the perturbation."""
    max_iterations: int = 200
    """Ceres iterations (and GTSAM's)."""
    gtsam_start: GtsamStart = GtsamStart.VISUAL
    """Start of GTSAM's solve of the identical problem."""
    max_solver_discrepancy_m: float = 0.001
    """Flag when a joint of GTSAM's and pycolmap's solutions of the identical pixels-only
    problem differs by more than this after the similarity alignment (the solvers disagree)."""
    max_joint_discrepancy_m: float = 0.004
    """Flag when a joint of the stage's RGB-D result differs by more than this from the
    pixels-only optimum (after a similarity): depth factors move joints < 1 mm median, up to
    ~3 mm, on synthetic data with 2.5 px noise; more means the result and the pixels disagree."""
    max_camera_rotation_deg: float = 5.0
    """Flag when a camera's rotation differs by more than this after the alignment."""


PRESETS: dict[str, CrosscheckConfig] = {
    "default": CrosscheckConfig(),
    "from_initialisation": CrosscheckConfig(start_from=StartFrom.INITIALISATION),
    "lenient": CrosscheckConfig(max_joint_discrepancy_m=0.008, max_camera_rotation_deg=10.0),
}


@dataclass(frozen=True)
class SfmCrosscheck:
    """Discrepancies between the GTSAM and the pycolmap solutions of one problem (after a
    similarity).

    joint_discrepancy_m : (21,) float, NaN for joints either solver left out.
    max_rgbd_joint_discrepancy_m : largest joint difference between pycolmap's pixels-only
        optimum and the stage's RGB-D result (after a similarity).
    camera_rotation_deg, camera_translation_m : (m,) per frame, NaN where not compared.
    similarity_scale : scale of the pycolmap -> GTSAM similarity.
    colmap_reproj_rmse_px : pycolmap's final RMS reprojection error.
    """

    joint_discrepancy_m: np.ndarray
    max_joint_discrepancy_m: float
    median_joint_discrepancy_m: float
    camera_rotation_deg: np.ndarray
    camera_translation_m: np.ndarray
    max_camera_rotation_deg: float
    median_camera_translation_m: float
    similarity_scale: float
    colmap_reproj_rmse_px: float
    max_rgbd_joint_discrepancy_m: float
    flagged: bool
    reason: str


def _start(rec: HandReconstruction, cfg: CrosscheckConfig) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    if cfg.start_from is StartFrom.INITIALISATION:
        return rec.diagnostics.T_w_c_init, rec.diagnostics.joints_w_init
    rng = np.random.default_rng(cfg.seed)
    d = rec.diagnostics
    T = np.where(np.isfinite(d.T_w_c_visual), d.T_w_c_visual, rec.T_w_c)
    X = np.where(np.isfinite(d.joints_w_visual), d.joints_w_visual, rec.joints_w)
    for i in range(len(T)):
        dR = Rotation.from_rotvec(np.radians(rng.normal(0, cfg.perturb_deg, 3))).as_matrix()
        T[i] = make_T(dR @ T[i, :3, :3], T[i, :3, 3] + rng.normal(0, cfg.perturb_m, 3))
    return T, X + rng.normal(0, cfg.perturb_m, X.shape)


def _colmap_solve(K, uv, use, T_w_c, X, cfg):
    """Build and bundle-adjust a pycolmap.Reconstruction -> (T_w_c, X, rmse), NaN where absent."""
    import pycolmap

    m, nj = use.shape
    recon = pycolmap.Reconstruction()
    camera = pycolmap.Camera(
        camera_id=1,
        model=pycolmap.CameraModelId.PINHOLE,
        width=int(2 * K[0, 2]),
        height=int(2 * K[1, 2]),
        params=np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]),
    )
    recon.add_camera_with_trivial_rig(camera)
    ba_config = pycolmap.BundleAdjustmentConfig()
    for i in range(m):
        T_c_w = inv_T(T_w_c[i])
        image = pycolmap.Image(
            name=f"{i:06d}", keypoints=np.nan_to_num(uv[i]), camera_id=1, image_id=i + 1
        )
        recon.add_image_with_trivial_frame(image, pycolmap.Rigid3d(T_c_w[:3]))
        ba_config.add_image(i + 1)
    point_ids = {}
    for j in range(nj):
        track = pycolmap.Track(
            [pycolmap.TrackElement(int(i) + 1, j) for i in np.flatnonzero(use[:, j])]
        )
        point_ids[j] = recon.add_point3D(X[j], track)
    ba_config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    options = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False,
        refine_principal_point=False,
        refine_extra_params=False,
        print_summary=False,
    )
    options.ceres.solver_options.num_threads = 1
    # every camera sees every joint: eliminating the 21 points (Schur, COLMAP's choice) leaves
    # a dense camera system; sparse Cholesky of the normal equations is ~40 % cheaper
    options.ceres.auto_select_solver_type = False
    options.ceres.solver_options.linear_solver_type = type(
        options.ceres.solver_options.linear_solver_type
    ).SPARSE_NORMAL_CHOLESKY
    options.ceres.solver_options.max_num_iterations = cfg.max_iterations
    options.ceres.solver_options.function_tolerance = 1e-10
    options.ceres.solver_options.parameter_tolerance = 1e-10
    pycolmap.create_default_bundle_adjuster(options, ba_config, recon).solve()
    T_out = np.stack(
        [
            inv_T(np.vstack([recon.image(i + 1).cam_from_world().matrix(), [0, 0, 0, 1]]))
            for i in range(m)
        ]
    )
    X_out = np.stack([recon.point3D(point_ids[j]).xyz for j in range(nj)])
    res = reprojection_residuals(K, np.stack([inv_T(T) for T in T_out]), X_out, uv)
    return T_out, X_out, float(np.sqrt(np.mean(res[use] ** 2)))


def crosscheck_sfm(
    keypoints: np.ndarray,
    K: np.ndarray,
    reconstruction: HandReconstruction,
    config: CrosscheckConfig = PRESETS["default"],
) -> SfmCrosscheck:
    """Solve the reconstruction's inlier observations with pycolmap and compare.

    Parameters
    ----------
    keypoints : (n, 21, 3) float, the same keypoints ``reconstruct_hand`` saw.
    K : (3, 3) colour intrinsics.
    reconstruction : the GTSAM result.
    """
    rec, cfg = reconstruction, config
    K = np.asarray(K, dtype=float)
    uv = np.asarray(keypoints, dtype=float)[rec.frames, :, :2]
    frames = rec.pose_valid & (rec.inlier.sum(1) >= 3)
    joints = rec.joint_valid & (rec.inlier[frames].sum(0) >= 2)
    if frames.sum() < 3 or joints.sum() < 6:
        raise StageError(
            STAGE, f"too little to compare: {frames.sum()} frames, {joints.sum()} joints"
        )
    fi, ji = np.flatnonzero(frames), np.flatnonzero(joints)
    use = rec.inlier[np.ix_(fi, ji)]
    T0, X0 = _start(rec, cfg)
    T_col, X_col, rmse = _colmap_solve(K, uv[np.ix_(fi, ji)], use, T0[fi], X0[ji], cfg)
    # GTSAM on the identical problem (same tracks and unit weights as pycolmap's)
    T1, X1, soft = T0[fi], X0[ji], None
    if cfg.gtsam_start is GtsamStart.VISUAL:
        d = rec.diagnostics
        T1 = np.where(np.isfinite(d.T_w_c_visual[fi]), d.T_w_c_visual[fi], T1)
        X1 = np.where(np.isfinite(d.joints_w_visual[ji]), d.joints_w_visual[ji], X1)
        soft = 1e-3  # the similarity takes out the scale; a stiff gauge only slows LM
    ba = bundle_adjust(
        uv[np.ix_(fi, ji)], use, np.ones(use.shape), K, np.stack([inv_T(T) for T in T1]), X1,
        anchor=0, scale_ref=int(np.argmax(np.linalg.norm(T1[:, :3, 3] - T1[0, :3, 3], axis=1))),
        huber_k=None, scale_sigma_rel=soft, min_observations=1,
        max_iterations=cfg.max_iterations, relative_tol=1e-10,
    )  # fmt: skip
    T_gt = np.stack([inv_T(T) for T in ba.T_c_w])
    X_gt = ba.points_w
    S, s = umeyama(X_col, X_gt)
    X_al = s * X_col @ S[:3, :3].T + S[:3, 3]
    joint_d = np.full(21, np.nan)
    joint_d[ji] = np.linalg.norm(X_al - X_gt, axis=1)
    S_r, s_r = umeyama(X_col, rec.joints_w[ji])
    rgbd_d = np.linalg.norm(s_r * X_col @ S_r[:3, :3].T + S_r[:3, 3] - rec.joints_w[ji], axis=1)
    rot_d = np.full(len(frames), np.nan)
    tr_d = np.full(len(frames), np.nan)
    for k, i in enumerate(fi):
        R_al = S[:3, :3] @ T_col[k, :3, :3]
        c_al = s * S[:3, :3] @ T_col[k, :3, 3] + S[:3, 3]
        rot_d[i] = rotation_error_deg(R_al, T_gt[k, :3, :3])
        tr_d[i] = float(np.linalg.norm(c_al - T_gt[k, :3, 3]))
    max_j, max_r = float(np.nanmax(joint_d)), float(np.nanmax(rot_d))
    reasons = []
    if max_j > cfg.max_solver_discrepancy_m:
        reasons.append(
            f"joint {int(np.nanargmax(joint_d))} differs by {max_j * 1000:.2f} mm "
            f"> {cfg.max_solver_discrepancy_m * 1000:.2f} mm between GTSAM and pycolmap"
        )
    if rgbd_d.max() > cfg.max_joint_discrepancy_m:
        reasons.append(
            f"joint {int(ji[np.argmax(rgbd_d)])} of the result differs by "
            f"{rgbd_d.max() * 1000:.2f} mm > {cfg.max_joint_discrepancy_m * 1000:.2f} mm from "
            "the pixels-only optimum"
        )
    if max_r > cfg.max_camera_rotation_deg:
        reasons.append(
            f"camera of frame {int(rec.frames[np.nanargmax(rot_d)])} differs by "
            f"{max_r:.2f} deg > {cfg.max_camera_rotation_deg} deg"
        )
    return SfmCrosscheck(
        joint_discrepancy_m=joint_d,
        max_joint_discrepancy_m=max_j,
        median_joint_discrepancy_m=float(np.nanmedian(joint_d)),
        camera_rotation_deg=rot_d,
        camera_translation_m=tr_d,
        max_camera_rotation_deg=max_r,
        median_camera_translation_m=float(np.nanmedian(tr_d)),
        similarity_scale=s,
        colmap_reproj_rmse_px=rmse,
        max_rgbd_joint_discrepancy_m=float(np.max(rgbd_d)),
        flagged=bool(reasons),
        reason="; ".join(reasons),
    )
