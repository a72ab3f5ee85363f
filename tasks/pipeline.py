"""One capture session as a DAG of stages, in the order of ``pipeline.md`` (no Prefect here).

Each :class:`Stage` names the stages it consumes (``upstream``), the session files
whose bytes it reads (``reads``: roles of :meth:`Session.input_files`), its code
version and config type, and a ``run`` function: a few lines of glue that pull the
stage's inputs out of the session and the upstream results (``up``, by stage name) and call
the stage module's function, where the stage's logic lives. ``flows/`` turns each stage into
a cached Prefect task from exactly this table; :func:`run_session` runs the same table bare
and in order (the baseline the build is benchmarked against, and a way to debug one session
without Prefect).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.tasks.contact import build_contactmap, symmetric_contact
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, rotation_error_deg, transform_points
from graspcap.tasks.core.presets import PIPELINE_PRESETS, UnknownPreset, apply_settings
from graspcap.tasks.hand import fit_hand, refine_grasp
from graspcap.tasks.hand.final import FinalHand, final_hand, final_pose
from graspcap.tasks.hand.model import SURFACE_OFFSET_M, HandSide
from graspcap.tasks.hand_sfm import crosscheck_sfm, joint_solve, reconstruct_hand, select_steady
from graspcap.tasks.hand_sfm.frame_screen import hand_size_px
from graspcap.tasks.hand_sfm.metric_scale import depth_lookup
from graspcap.tasks.keypoints import detect_keypoints
from graspcap.tasks.keypoints.detect_keypoints import why_missing
from graspcap.tasks.object_pose import (
    adjustment_steady,
    estimate_adjustment,
    register_object,
    register_scan,
    track_object,
    tracked_average,
)
from graspcap.tasks.outputs import (
    frame_validity,
    pictures,
    propagate_poses,
    qa_metrics,
)
from graspcap.tasks.session import load_session
from graspcap.tasks.session.load_session import Session
from graspcap.tasks.session.manifest_guard import restricted

SESSION_STAGE = "load_session"
WHOLE_MANIFEST = ("*",)
"""``Stage.fields`` of a stage that reads all of ``session.json`` (``load_session``)."""
LABEL_FIELDS = ("participant", "object_id", "intent")
"""``session.json`` labels no stage reads: the rows take them from the current manifest, and
``load_session``'s key covers only whether each is valid, so editing one runs no stage."""
ALL_FILES = (  # load_session reads all but "manifest" by bytes, the manifest by its fields
    "manifest", "object_mesh", "stage1", "grasp_color", "grasp_depth", "grasp_keypoints",
    "scan_thermal", "scan_depth",
)  # fmt: skip


@dataclass(frozen=True)
class Stage:
    """One node of the session DAG."""

    name: str
    version: str
    presets: Mapping[str, StageConfig]
    upstream: tuple[str, ...]
    reads: tuple[str, ...]
    run: Callable[..., Any]
    """``run(session, config, **upstream_results) -> result``."""
    fields: tuple[str, ...] = ()
    """The ``session.json`` fields the stage reads (dotted paths: ``color_camera.K``,
    ``grasp.steady_from``; a section name covers all of it), beside ``session_id``, which every
    stage may read. Its cache key digests exactly these (canonical JSON), not the whole
    manifest, and the session its glue gets lets no other field be read
    (:func:`~graspcap.tasks.session.manifest_guard.restricted` raises naming the field).
    ``load_session`` reads the whole manifest: ``("*",)``."""

    @property
    def key_upstream(self) -> tuple[str, ...]:
        """The upstream stages whose result digests are in the key: all but ``load_session``,
        whose result a stage reads only through its declared roles and fields."""
        return tuple(u for u in self.upstream if u != SESSION_STAGE)

    @property
    def config_type(self) -> type[StageConfig]:
        return type(self.presets["default"])


# --- glue: session + upstream results -> pure stage call ------------------------------------
# Each takes the upstream results as ``**up`` by stage name and reads them as ``up["stage"]``:
# a bare stage name below is always the stage's module, never its result.


LABEL_PLACEHOLDER = "(a label: the catalog rows read it from session.json)"
"""What a label (:data:`LABEL_FIELDS`) holds in ``load_session``'s result: its key covers only
that the label is valid, so its result must not hold the value either."""


def _load(session_dir: Path | str, config) -> Session:
    session = load_session.load_session(Path(session_dir), check_images=config.check_images,
                                        limits=config.limits)
    manifest = session.manifest.model_copy(update=dict.fromkeys(LABEL_FIELDS, LABEL_PLACEHOLDER))
    return Session(root=session.root, manifest=manifest)


def _ideal_keypoints(session: Session, keypoints: np.ndarray) -> np.ndarray:
    """The detector's keypoints (raw colour pixels) in ideal pinhole pixels of
    ``color_camera.K`` (``color_camera.dist`` undone; as is when it is zero): the pixels every
    stage's geometry works in (``tasks/core/camera.py``)."""
    return session.color_camera.undistort_keypoints(keypoints)


def _register_object(session: Session, config, **up):
    return register_object.register_object(
        session.read_depth_m(session.manifest.stage1.depth), session.color_K,
        session.T_color_turntable, *session.read_mesh(), config,
        depth_name=f"stage1.depth {session.manifest.stage1.depth}", mesh_name=session.mesh_name,
    )


def _detect_keypoints(session: Session, config, **up):
    return detect_keypoints.detect_keypoints(session, config)


DEPTH_CACHE_BYTES = 512 * 2**20
"""Decoded grasp depth (float32 metres) a stage that visits frames more than once keeps: as
many frames as fit (at least 4). select_steady's depth onset reads each frame up to six times
(hand centres, two registrations, two free-space checks); decoding a depth PNG costs ~10 ms.
The stages that read each frame once, in order (estimate_adjustment's tracking,
propagate_poses' validity), keep the reader's default few."""


def _depth_reader(session: Session) -> Callable[[int], np.ndarray]:
    """Grasp depth frame -> (h, w) float32 metres, decoded once while ``DEPTH_CACHE_BYTES``
    holds the frames visited."""
    w, h = session.color_camera.size
    return session.grasp_depth_reader(max(4, DEPTH_CACHE_BYTES // (4 * w * h)))


def _select_steady(session: Session, config, **up):
    keypoints = up["detect_keypoints"]
    return select_steady.select_steady(
        _ideal_keypoints(session, keypoints.keypoints), session.color_K,
        session.manifest.grasp.steady_from, config,
        why_missing=why_missing(keypoints), depth_frame=_depth_reader(session),
        T_color_turntable=session.T_color_turntable,
    )


def _joint_solve(session: Session, config, **up):
    """The hand model inside the SfM (``hand_sfm.joint_solve``); None with ``mode = off``, and
    then ``reconstruct_hand`` and ``fit_hand`` run the staged path."""
    if config.mode is joint_solve.HandPath.OFF:
        return None
    keypoints, read = up["detect_keypoints"], session.grasp_depth_reader()
    return joint_solve.joint_solve(
        _ideal_keypoints(session, keypoints.keypoints), session.color_K,
        up["select_steady"].steady_from, depth_lookup(read), HandSide(session.manifest.hand),
        config, depth_frame=read, T_color_turntable=session.T_color_turntable,
        why_missing=why_missing(keypoints),
    )


def _reconstruct_hand(session: Session, config, **up):
    """The staged SfM, or the joint solve's cameras and joints when it ran."""
    if up["joint_solve"] is not None:
        return up["joint_solve"].reconstruction
    keypoints, read = up["detect_keypoints"], session.grasp_depth_reader()
    return reconstruct_hand.reconstruct_hand(
        _ideal_keypoints(session, keypoints.keypoints), session.color_K,
        up["select_steady"].steady_from,
        depth_lookup(read), np.asarray(SURFACE_OFFSET_M), config, depth_frame=read,
        T_color_turntable=session.T_color_turntable, why_missing=why_missing(keypoints),
    )


def _crosscheck_sfm(session: Session, config, **up):
    return crosscheck_sfm.crosscheck_sfm(
        _ideal_keypoints(session, up["detect_keypoints"].keypoints), session.color_K,
        up["reconstruct_hand"], config,
    )


def _fit_hand(session: Session, config, **up):
    """The staged hand fit, or the joint solve's hand when it ran."""
    if up["joint_solve"] is not None:
        return up["joint_solve"].fit
    return fit_hand.fit_hand(up["reconstruct_hand"].joints_w, HandSide(session.manifest.hand),
                             config)


def _estimate_adjustment(session: Session, config, **up):
    """``T_adj`` registered in the first steady frame(s); with ``config.tracking.enabled`` the
    object then tracked in every steady frame's depth and, with ``config.average.enabled``,
    ``T_w_o`` the robust mean of the registered frames' poses (:mod:`tracked_average`)."""
    s, sfm, stage1 = up["select_steady"].steady_from, up["reconstruct_hand"], up["register_object"]
    hand, mesh = up["fit_hand"].mesh(), session.read_mesh()
    frames = np.arange(s, s + len(sfm.T_w_c))
    keypoints = _ideal_keypoints(session, up["detect_keypoints"].keypoints[frames])
    adj = adjustment_steady.estimate_adjustment_steady(
        lambda k: session.read_depth_m(session.grasp_path("depth", s + k)), session.color_K,
        *mesh, (hand.vertices, hand.faces), keypoints, sfm.T_w_c, sfm.pose_valid,
        stage1.T_w_o, config, T_w_o_stage1_alt=stage1.second_hypothesis,
    )
    return _track_adjustment(session, config, adj, **up)


def _track_adjustment(session: Session, config, adj: estimate_adjustment.Adjustment, **up):
    """``adj``'s object tracked in every steady frame's depth (``config.tracking``), and its
    ``T_w_o`` the robust mean over the registered frames (``config.average``)."""
    if not config.tracking.enabled:
        return adj
    s, sfm, stage1 = up["select_steady"].steady_from, up["reconstruct_hand"], up["register_object"]
    hand, mesh = up["fit_hand"].mesh(), session.read_mesh()
    frames = np.arange(s, s + len(sfm.T_w_c))
    keypoints = _ideal_keypoints(session, up["detect_keypoints"].keypoints[frames])

    def track(T_w_o: np.ndarray) -> track_object.ObjectTracking:
        T_o_w = inv_T(T_w_o)  # the static hand in the frame of that object pose
        return track_object.track_object(
            np.stack([inv_T(T) @ T_w_o for T in sfm.T_w_c]),
            frames, session.grasp_depth_reader(), session.color_K, mesh,
            (transform_points(T_o_w, hand.vertices), hand.faces), keypoints, config.tracking,
            joints_o=transform_points(T_o_w, sfm.joints_w),
        )

    tracking = track(adj.T_w_o)
    adj = replace(adj, tracking=tracking)
    if not config.average.enabled:
        return adj
    average = tracked_average.average_tracking(
        sfm.T_w_c, tracking, np.asarray(mesh[0], float).mean(axis=0), config.average,
    )
    if average.T_w_o is None:
        return replace(adj, average=average)
    retrack = config.average.retrack_deg
    if retrack > 0 and rotation_error_deg(average.T_w_o[:3, :3], adj.T_w_o[:3, :3]) > retrack:
        # the frames the gain test left untracked deliver the pose carried from the mean, so
        # the tracking is judged again against that pose, from it; the mean itself stays
        tracking = track(average.T_w_o)
    return replace(adj, T_w_o=average.T_w_o, T_adj=average.T_w_o @ inv_T(stage1.T_w_o),
                   T_w_o_first=adj.T_w_o, average=average, tracking=tracking)


def _register_scan(session: Session, config, **up):
    views = session.manifest.scan.views
    return register_scan.register_scan(
        [(session.read_depth_m(v.depth), np.radians(v.angle_deg)) for v in views],
        session.color_K, session.T_color_turntable, *session.read_mesh(), config,
        view_names=[v.depth for v in views], mesh_name=session.mesh_name,
    )


def _build_contactmap(session: Session, config, **up):
    """The thermal contact map, carried into the grasp's frame on a symmetric object
    (``contact.symmetric_contact``)."""
    cam, views = session.manifest.thermal_camera, session.manifest.scan.views
    mesh = session.read_mesh()
    cmap = build_contactmap.build_contactmap(
        *mesh,
        [(session.read_thermal_k(v.thermal), np.radians(v.angle_deg)) for v in views],
        np.asarray(cam.K, dtype=float), np.asarray(cam.T_color_thermal, dtype=float),
        session.T_color_turntable, up["register_scan"].T_turntable_o_scan, config,
        image_size=(cam.width, cam.height), dist_thermal=session.thermal_camera.dist,
        view_names=[v.thermal for v in views],
        mesh_name=session.mesh_name,
    )
    if not config.align_to_hand:
        return cmap
    hand_o = final_hand(up["fit_hand"], None, up["estimate_adjustment"].T_w_o).vertices_o
    tracking = getattr(up["estimate_adjustment"], "tracking", None)

    def bare() -> np.ndarray | None:
        if tracking is None:
            return None
        read, s = session.grasp_depth_reader(), up["select_steady"].steady_from
        return symmetric_contact.tracked_bare_share(
            *mesh, tracking.T_c_o, tracking.tracked, session.color_K, lambda j: read(s + j),
            frames=config.align_bare_frames, bare_m=config.align_bare_m,
            window_px=config.align_bare_window_px)

    return symmetric_contact.align_to_hand(
        *mesh, cmap, hand_o, tolerance_m=config.symmetry_tolerance_m,
        near_mm=config.align_near_mm, margin=config.align_margin, ratio=config.align_ratio,
        contact_threshold=config.align_contact_threshold, bare=bare,
    )  # fmt: skip


def _refine_grasp(session: Session, config, **up):
    contact = up["build_contactmap"]
    return refine_grasp.refine_grasp(
        up["fit_hand"], HandSide(session.manifest.hand), up["estimate_adjustment"].T_w_o,
        *session.read_mesh(), contact.contact, contact.observed, config,
    )


def _propagate_poses(session: Session, config, **up):
    """The poses carried by stage 2's cameras, or on a frame where ``estimate_adjustment``
    tracked the object in its depth by the camera that tracking defines
    (``propagate_poses.tracked_cameras``); then each frame's validity (its depth against the
    object at its pose)."""
    sfm, frames = up["reconstruct_hand"], np.arange(up["select_steady"].steady_from,
                                                    session.manifest.grasp.count)
    T_w_p, _, joints_hand_w = final_pose(up["fit_hand"], up.get("refine_grasp"))
    keypoints = _ideal_keypoints(session, up["detect_keypoints"].keypoints[frames])
    T_adj, T_w_o1 = up["estimate_adjustment"].T_adj, up["register_object"].T_w_o
    tracking = getattr(up["estimate_adjustment"], "tracking", None)
    T_w_c = (sfm.T_w_c if tracking is None
             else propagate_poses.tracked_cameras(sfm.T_w_c, T_adj @ T_w_o1, tracking))
    prop = replace(propagate_poses.propagate_poses(
        T_w_c, T_adj, T_w_o1, T_w_p, sfm.joints_w, session.color_K, frames, keypoints,
        joints_fit_w=joints_hand_w, config=config,
    ), tracking=tracking)
    read_depth = session.grasp_depth_reader()  # the validity reads each frame once, in order
    hand_o, mesh = _final_hand(up).mesh_o, session.read_mesh()
    validity = frame_validity.frame_validity(
        prop.frame_indices, keypoints, sfm.frames, sfm.pose_valid, sfm.inlier, prop.T_c_o,
        read_depth, session.color_K, mesh, hand_o, config.validity,
        sfm.diagnostics.frame_rejected,
    )
    return replace(prop, validity=validity)


def _final_hand(up: Mapping[str, Any]) -> FinalHand:
    return final_hand(up["fit_hand"], up.get("refine_grasp"), up["estimate_adjustment"].T_w_o)


def steady_hand_size_px(up: Mapping[str, Any]) -> float | None:
    """The hand's image size in the steady frames: the median over them of the detections'
    bounding-box diagonal (px); None without a detection there."""
    frames = up["reconstruct_hand"].frames if up.get("reconstruct_hand") is not None else []
    kp = np.asarray(up["detect_keypoints"].keypoints, dtype=float)[np.asarray(frames, int)]
    sizes = hand_size_px(kp[..., :2], (kp[..., 2] > 0) & np.all(np.isfinite(kp), axis=2))
    return float(np.nanmedian(sizes)) if np.isfinite(sizes).any() else None


def _qa_metrics(session: Session, config, **up):
    """QA of the session; the hand's image size (:func:`steady_hand_size_px`) tells noisy
    detections from clean ones."""
    return qa_metrics.qa_metrics(up, config, object_mesh=session.read_mesh(),
                                 hand_mesh_o=_final_hand(up).mesh_o,
                                 hand_size_px=steady_hand_size_px(up))


def _pictures(session: Session, config, **up):
    """The first steady frame (its camera is the world frame), the final hand, the object
    where ``propagate_poses`` (the catalog's ``T_c_o``) puts it, a strip of frames across the
    video and the QA reasons; drawn in ideal pixels (the colour frames and detections
    undistorted through the lens, as the stages saw them; unchanged without distortion)."""
    f, sfm, hand = up["select_steady"].steady_from, up["reconstruct_hand"], _final_hand(up)
    contact, poses, qa = up["build_contactmap"], up["propagate_poses"], up["qa_metrics"]
    camera, keypoints = session.color_camera, up["detect_keypoints"].keypoints

    def frame(i: int) -> tuple[np.ndarray, Any, np.ndarray]:
        image, background = pictures.read_frame(session, i)
        if background == pictures.Background.COLOR:
            image = camera.undistort_image(image, nearest=False)
        return image, background, _ideal_keypoints(session, keypoints[i])

    model_px, outlier = pictures.model_keypoints(session.color_K, f, sfm.frames, sfm.T_w_c,
                                                 sfm.inlier, hand.joints_w)
    T_c_o = {int(i): T for i, T in zip(poses.frame_indices, poses.T_c_o, strict=True)}
    strip = [(i, *frame(i), T_c_o.get(i))
             for i in pictures.strip_indices(session.manifest.grasp.count, config.strip_frames)]
    return pictures.pictures(
        *frame(f), model_px, f,
        session_id=session.session_id, outlier=outlier, object_mesh=session.read_mesh(),
        contact=contact.contact, observed=contact.observed, hand_mesh_o=hand.mesh_o,
        up_o=up["register_scan"].T_turntable_o_scan[2, :3], note=str(qa.verdict),
        K=session.color_K, T_c_o=T_c_o.get(f), strip=strip, steady_from=f,
        reasons=qa.reasons, notes=qa.notes, config=config,
    )


# --- the DAG ----------------------------------------------------------------------------------

_REFINE: tuple[str, ...] = ("refine_grasp",)
"""``("refine_grasp",)`` once ``refine_grasp`` is in the DAG: propagate_poses, qa_metrics and
pictures then use the refined hand (``final_hand``); until then ``fit_hand``'s."""

_CAM, _T_TT, _DEPTH_SCALE, _MESH = ("color_camera", "turntable.T_color_turntable",
                                    "depth_scale_m", "object_mesh")
"""Manifest fields many stages read: ``Session.color_K`` and ``color_camera`` (the lens:
K, dist and size; ``read_depth_m`` and the keypoints' undistortion read ``dist``),
``T_color_turntable``, ``read_depth_m`` and ``read_mesh``/``mesh_name``."""

STAGES: dict[str, Stage] = {
    s.name: s
    for s in [
        Stage("load_session", load_session.STAGE_VERSION, load_session.PRESETS, (),
              tuple(r for r in ALL_FILES if r != "manifest"), _load, fields=WHOLE_MANIFEST),
        Stage("register_object", register_object.STAGE_VERSION, register_object.PRESETS,
              ("load_session",), ("object_mesh", "stage1"), _register_object,
              fields=("stage1.depth", _DEPTH_SCALE, _CAM, _T_TT, _MESH)),
        Stage("detect_keypoints", detect_keypoints.STAGE_VERSION, detect_keypoints.PRESETS,
              ("load_session",), ("grasp_keypoints", "grasp_color"), _detect_keypoints,
              fields=("hand", "color_camera.width", "color_camera.height", "grasp.count",
                      "grasp.keypoints", "grasp.color")),
        Stage("select_steady", select_steady.STAGE_VERSION, select_steady.PRESETS,
              ("load_session", "detect_keypoints"), ("grasp_depth",), _select_steady,
              fields=(_CAM, "grasp.steady_from", "grasp.count", "grasp.depth", _DEPTH_SCALE,
                      _T_TT)),
        Stage("joint_solve", joint_solve.STAGE_VERSION, joint_solve.PRESETS,
              ("load_session", "detect_keypoints", "select_steady"), ("grasp_depth",),
              _joint_solve, fields=(_CAM, "grasp.count", "grasp.depth", _DEPTH_SCALE, _T_TT,
                                    "hand")),
        Stage("reconstruct_hand", reconstruct_hand.STAGE_VERSION, reconstruct_hand.PRESETS,
              ("load_session", "detect_keypoints", "select_steady", "joint_solve"),
              ("grasp_depth",),
              _reconstruct_hand, fields=(_CAM, "grasp.count", "grasp.depth", _DEPTH_SCALE, _T_TT)),
        Stage("crosscheck_sfm", crosscheck_sfm.STAGE_VERSION, crosscheck_sfm.PRESETS,
              ("load_session", "detect_keypoints", "reconstruct_hand"), (), _crosscheck_sfm,
              fields=(_CAM,)),
        Stage("fit_hand", fit_hand.STAGE_VERSION, fit_hand.PRESETS,
              ("load_session", "reconstruct_hand", "joint_solve"), (), _fit_hand,
              fields=("hand",)),
        Stage("estimate_adjustment", estimate_adjustment.STAGE_VERSION,
              estimate_adjustment.PRESETS,
              ("load_session", "register_object", "detect_keypoints", "select_steady",
               "reconstruct_hand", "fit_hand"),
              ("object_mesh", "grasp_depth"), _estimate_adjustment,
              fields=(_CAM, "grasp.count", "grasp.depth", _DEPTH_SCALE, _MESH)),
        Stage("register_scan", register_scan.STAGE_VERSION, register_scan.PRESETS,
              ("load_session",), ("object_mesh", "scan_depth"), _register_scan,
              fields=("scan.views", _DEPTH_SCALE, _CAM, _T_TT, _MESH)),
        Stage("build_contactmap", build_contactmap.STAGE_VERSION, build_contactmap.PRESETS,
              ("load_session", "select_steady", "fit_hand", "estimate_adjustment",
               "register_scan"),
              ("object_mesh", "scan_thermal", "grasp_depth"), _build_contactmap,
              fields=("thermal_camera", "scan.views", _T_TT, _MESH, _CAM, "grasp.count",
                      "grasp.depth", _DEPTH_SCALE)),
        Stage("refine_grasp", refine_grasp.STAGE_VERSION, refine_grasp.PRESETS,
              ("load_session", "fit_hand", "estimate_adjustment", "build_contactmap"),
              ("object_mesh",), _refine_grasp, fields=("hand", _MESH)),
        Stage("propagate_poses", propagate_poses.STAGE_VERSION, propagate_poses.PRESETS,
              ("load_session", "detect_keypoints", "select_steady", "reconstruct_hand",
               "fit_hand", "register_object", "estimate_adjustment") + _REFINE,
              ("object_mesh", "grasp_depth"), _propagate_poses,
              fields=(_CAM, "grasp.count", "grasp.depth", _DEPTH_SCALE, _MESH)),
        Stage("qa_metrics", qa_metrics.STAGE_VERSION, qa_metrics.PRESETS,
              ("load_session", "detect_keypoints", "reconstruct_hand", "crosscheck_sfm",
               "fit_hand", "register_object", "estimate_adjustment", "register_scan",
               "build_contactmap", "propagate_poses") + _REFINE, ("object_mesh",),
              _qa_metrics, fields=(_MESH,)),
        Stage("pictures", pictures.STAGE_VERSION, pictures.PRESETS,
              ("load_session", "detect_keypoints", "select_steady", "reconstruct_hand",
               "fit_hand", "estimate_adjustment", "register_scan", "build_contactmap",
               "propagate_poses", "qa_metrics") + _REFINE,
              ("object_mesh", "grasp_color", "grasp_depth"), _pictures,
              fields=(_CAM, "grasp.count", "grasp.color", "grasp.depth", _DEPTH_SCALE, _MESH)),
    ]
}  # fmt: skip


AID_STAGES: frozenset[str] = frozenset({"pictures"})
"""Stages that only help a person look at a session (not part of its data): when one fails,
the build still commits the session's rows with its QA status, and notes the failure in the
build report; it never fails the session."""


def _check_presets() -> None:
    """Every stage preset is a named pipeline preset (``core.presets``)."""
    for stage in STAGES.values():
        missing = set(stage.presets) - set(PIPELINE_PRESETS)
        if missing:
            raise RuntimeError(f"{stage.name}: presets {sorted(missing)} are not in "
                               "tasks/core/presets.py PIPELINE_PRESETS")


_check_presets()


def _check_fields() -> None:
    """Every declared manifest field (``Stage.fields``) is a field of ``SessionManifest``: a
    misspelt one would key on nothing."""
    from pydantic import BaseModel

    from graspcap.schemas.session import SessionManifest

    for stage in STAGES.values():
        for path in () if stage.fields == WHOLE_MANIFEST else stage.fields:
            model: Any = SessionManifest
            for part in path.split("."):
                if model is None or part not in model.model_fields:
                    raise RuntimeError(f"{stage.name}: Stage.fields names {path!r}, which is "
                                       "not a field of session.json (schemas/session.py)")
                kind = model.model_fields[part].annotation
                model = kind if isinstance(kind, type) and issubclass(kind, BaseModel) else None


_check_fields()


def preset_stages(preset: str) -> tuple[str, ...]:
    """The stages whose config ``preset`` sets (the others run their default)."""
    if preset not in PIPELINE_PRESETS:
        raise UnknownPreset(preset)
    return tuple(n for n, s in STAGES.items() if preset in s.presets)


def configs_for(preset: str = "default", **overrides: StageConfig) -> dict[str, StageConfig]:
    """Every stage's config: the named preset where the stage has one, else its default,
    with explicit per-stage ``overrides``. An unknown preset raises :class:`UnknownPreset`
    (it lists the known ones)."""
    if preset not in PIPELINE_PRESETS:
        raise UnknownPreset(preset)
    unknown = set(overrides) - set(STAGES)
    if unknown:
        raise KeyError(f"no such stage(s): {sorted(unknown)}; stages are {list(STAGES)}")
    return tie_configs({
        name: overrides.get(name) or stage.presets.get(preset, stage.presets["default"])
        for name, stage in STAGES.items()
    })


def tie_configs(configs: Mapping[str, StageConfig]) -> dict[str, StageConfig]:
    """``configs`` with ``joint_solve``'s staged start set to the ``reconstruct_hand`` and
    ``fit_hand`` configs beside it: where ``joint_solve`` runs, it runs the staged path itself
    and the two stages pass its result on, so a preset or ``--set`` of either must reach it
    (and its cache key)."""
    out = dict(configs)
    if {"joint_solve", "reconstruct_hand", "fit_hand"} <= set(out):
        out["joint_solve"] = out["joint_solve"].model_copy(
            update={"staged": out["reconstruct_hand"], "fit": out["fit_hand"]})
    return out


def settings_overrides(settings: list[str] | tuple[str, ...],
                       preset: str = "default") -> dict[str, StageConfig]:
    """``["stage.field=value", ...]`` (``--set``) as the configs of the stages they change:
    ``preset``'s with the fields set, each checked against the stage's config model
    (:func:`~graspcap.tasks.core.presets.apply_settings`). Raises ``ValueError`` naming the
    setting and what is wrong with it."""
    return apply_settings(settings, configs_for(preset))


OPTIONAL_UPSTREAM = frozenset({"joint_solve"})
"""Upstream stages a bare :func:`run_stage` may lack (given None): a partial run without
``joint_solve`` runs the staged hand path, as ``joint_solve.mode = off`` does. A build runs
every stage, so their results are always in the keys."""


def run_stage(
    stage: Stage, session_dir: Path | str, config: StageConfig, upstream: Mapping[str, Any]
) -> Any:
    """Run one stage given its upstream results (``load_session`` gets the directory); the
    session a stage gets reads only the manifest fields and file roles it declares
    (``Stage.fields``, ``Stage.reads``); an absent result of :data:`OPTIONAL_UPSTREAM` is
    None."""
    if stage.name == SESSION_STAGE:
        return stage.run(session_dir, config)
    session = restricted(upstream[SESSION_STAGE], stage.fields, stage.name, stage.reads)
    up = {k: session if k == SESSION_STAGE else
          upstream.get(k) if k in OPTIONAL_UPSTREAM else upstream[k] for k in stage.upstream}
    return stage.run(session, config, **up)


NOTES = "notes"
"""Key of :func:`run_session`'s results holding its notes (a tuple of str), beside the
stages' names."""


def run_session(
    session_dir: Path | str,
    configs: Mapping[str, StageConfig] | None = None,
    timings_s: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Every stage of one session, bare and in order; the results by stage name.

    A failing stage raises (``StageError`` with its reason), except an aid stage
    (``AID_STAGES``: pictures), which fails as it does in a build: its result is left out and
    ``results[NOTES]`` (always there; empty when nothing failed) says why. When ``timings_s``
    is given it receives each stage's wall time in seconds.
    """
    configs = configs or configs_for()
    results: dict[str, Any] = {}
    notes: list[str] = []
    for name, stage in STAGES.items():
        t0 = time.perf_counter()
        try:
            results[name] = run_stage(stage, session_dir, configs[name], results)
        except Exception as exc:
            if name not in AID_STAGES:
                raise
            why = (str(exc) if isinstance(exc, StageError)
                   else f"{name}: {type(exc).__name__}: {exc}")
            notes.append(f"{why} (a QA aid: the session's results stand without it)")
        if timings_s is not None:
            timings_s[name] = time.perf_counter() - t0
    results[NOTES] = tuple(notes)
    return results
