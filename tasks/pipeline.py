"""One capture session as a DAG of stages, in the order of ``pipeline.md`` (no Prefect here).

Each :class:`Stage` names the stages it consumes (``upstream``), the session files
whose bytes it reads (``reads``: roles of :meth:`Session.input_files`), its code
version and config type, and a ``run`` function: a few lines of glue that pull the
stage's inputs out of the session and the upstream results and call the pure stage
function. ``flows/`` turns each stage into a cached Prefect task from exactly this
table; :func:`run_session` runs the same table bare and in order (the baseline the
build is benchmarked against, and a way to debug one session without Prefect).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from graspcap.tasks.contact import build_contactmap
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.core.errors import StageError
from graspcap.tasks.core.geometry import inv_T, project, transform_points
from graspcap.tasks.core.presets import PIPELINE_PRESETS, UnknownPreset
from graspcap.tasks.hand import fit_hand, refine_grasp
from graspcap.tasks.hand.model import SURFACE_OFFSET_M, HandSide
from graspcap.tasks.hand_sfm import crosscheck_sfm, reconstruct_hand, select_steady
from graspcap.tasks.hand_sfm.metric_scale import window_median
from graspcap.tasks.keypoints import detect_keypoints
from graspcap.tasks.object_pose import estimate_adjustment, register_object, register_scan
from graspcap.tasks.outputs import pictures, propagate_poses, qa_metrics
from graspcap.tasks.session import load_session
from graspcap.tasks.session.load_session import Session

ALL_FILES = (
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

    @property
    def config_type(self) -> type[StageConfig]:
        return type(self.presets["default"])


# --- glue: session + upstream results -> pure stage call ------------------------------------


def read_mesh(session: Session) -> tuple[np.ndarray, np.ndarray]:
    """The object mesh as (vertices (n, 3) float, faces (m, 3) int), in file vertex order."""
    mesh = trimesh.load(session.path(session.manifest.object_mesh), force="mesh", process=False)
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)


def mesh_name(session: Session) -> str:
    """The object mesh as messages name it: ``object_mesh <file>``."""
    return f"object_mesh {session.manifest.object_mesh}"


def _K(session: Session) -> np.ndarray:
    return np.asarray(session.manifest.color_camera.K, dtype=float)


def _T_color_turntable(session: Session) -> np.ndarray:
    return np.asarray(session.manifest.turntable.T_color_turntable, dtype=float)


def depth_lookup(session: Session, window_px: int = 2, read: Callable | None = None):
    """``depth_at(frame, uv (k, 2)) -> (k,)`` metres, median of non-zero depth around each
    pixel; frames are read lazily (a session's depth video does not fit in memory as float),
    by ``read(frame) -> (h, w)`` metres when given (to share a cache)."""
    read = read or lru_cache(maxsize=4)(
        lambda i: session.read_depth_m(session.grasp_path("depth", i))
    )

    def depth_at(frame: int, uv: np.ndarray) -> np.ndarray:
        return window_median(read(int(frame)), uv, window_px)

    return depth_at


def _load(session_dir: Path | str, config) -> Session:
    return load_session.load_session(Path(session_dir), check_images=config.check_images,
                                     limits=config.limits)


def _register_object(session, config, **_):
    depth = session.read_depth_m(session.manifest.stage1.depth)
    V, F = read_mesh(session)
    return register_object.register_object(
        depth, _K(session), _T_color_turntable(session), V, F, config,
        depth_name=f"stage1.depth {session.manifest.stage1.depth}", mesh_name=mesh_name(session),
    )


def _detect_keypoints(session, config, **_):
    return detect_keypoints.detect_keypoints(session, config)


def _select_steady(session, config, detect_keypoints, **_):
    return select_steady.select_steady(
        detect_keypoints.keypoints, _K(session), session.manifest.grasp.steady_from, config,
        why_missing=_why_missing(detect_keypoints),
    )


def _why_missing(keypoints: Any) -> str:
    """``Keypoints2D.missing_summary()``; empty for a result cached before it had one."""
    summary = getattr(keypoints, "missing_summary", None)
    return summary() if summary is not None else ""


def _reconstruct_hand(session, config, detect_keypoints, select_steady, **_):
    read = lru_cache(maxsize=4)(lambda i: session.read_depth_m(session.grasp_path("depth", i)))
    return reconstruct_hand.reconstruct_hand(
        detect_keypoints.keypoints,
        _K(session),
        select_steady.steady_from,
        depth_lookup(session, read=read),
        np.asarray(SURFACE_OFFSET_M),
        config,
        depth_frame=read,
        T_color_turntable=_T_color_turntable(session),
        why_missing=_why_missing(detect_keypoints),
    )


def _crosscheck_sfm(session, config, detect_keypoints, reconstruct_hand, **_):
    return crosscheck_sfm.crosscheck_sfm(
        detect_keypoints.keypoints, _K(session), reconstruct_hand, config
    )


def _fit_hand(session, config, reconstruct_hand, **_):
    return fit_hand.fit_hand(reconstruct_hand.joints_w, HandSide(session.manifest.hand), config)


def _estimate_adjustment(
    session, config, register_object, detect_keypoints, select_steady, reconstruct_hand,
    fit_hand, **_,
):
    s = select_steady.steady_from
    hand = fit_hand.mesh()
    return estimate_adjustment.estimate_adjustment_steady(
        lambda k: session.read_depth_m(session.grasp_path("depth", s + k)), _K(session),
        *read_mesh(session), (hand.vertices, hand.faces),
        detect_keypoints.keypoints[s : s + len(reconstruct_hand.T_w_c)], reconstruct_hand.T_w_c,
        reconstruct_hand.pose_valid, register_object.T_w_o, config,
        # a stage-1 pose that could be another (near-symmetric object) is tried both ways
        T_w_o_stage1_alt=register_object.T_w_o_runner_up if register_object.ambiguous else None,
    )


def _register_scan(session, config, **_):
    views = [
        (session.read_depth_m(v.depth), np.radians(v.angle_deg))
        for v in session.manifest.scan.views
    ]
    V, F = read_mesh(session)
    return register_scan.register_scan(
        views, _K(session), _T_color_turntable(session), V, F, config,
        view_names=[v.depth for v in session.manifest.scan.views], mesh_name=mesh_name(session),
    )


def _build_contactmap(session, config, register_scan, **_):
    m = session.manifest
    cam = m.thermal_camera
    views = [(session.read_thermal_k(v.thermal), np.radians(v.angle_deg)) for v in m.scan.views]
    V, F = read_mesh(session)
    return build_contactmap.build_contactmap(
        V, F, views, np.asarray(cam.K, dtype=float), np.asarray(cam.T_color_thermal, dtype=float),
        _T_color_turntable(session), register_scan.T_turntable_o_scan, config,
        image_size=(cam.width, cam.height), view_names=[v.thermal for v in m.scan.views],
        mesh_name=mesh_name(session),
    )


def _refine_grasp(session, config, fit_hand, estimate_adjustment, build_contactmap, **_):
    V, F = read_mesh(session)
    return refine_grasp.refine_grasp(
        fit_hand, HandSide(session.manifest.hand), estimate_adjustment.T_w_o, V, F,
        build_contactmap.contact, build_contactmap.observed, config,
    )


def _propagate_poses(
    session,
    config,
    detect_keypoints,
    select_steady,
    reconstruct_hand,
    fit_hand,
    register_object,
    estimate_adjustment,
    refine_grasp=None,
    **_,
):
    s = select_steady.steady_from
    frames = np.arange(s, session.manifest.grasp.count)
    T_w_p, _, joints_hand_w = final_pose(fit_hand, refine_grasp)
    return propagate_poses.propagate_poses(
        reconstruct_hand.T_w_c, estimate_adjustment.T_adj, register_object.T_w_o,
        T_w_p, reconstruct_hand.joints_w, _K(session), frames,
        detect_keypoints.keypoints[frames], joints_fit_w=joints_hand_w, config=config,
    )


def final_pose(fit: Any, refined: Any | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The session's final hand pose from the results of ``fit_hand`` and ``refine_grasp``
    (None when it did not run): palm ``T_w_p`` (4, 4), ``angles_rad`` (20,) and joints
    (21, 3) in the world; the refinement's when there is one, else the stage-3 fit's."""
    if refined is not None:
        return refined.T_w_p, refined.angles_rad, refined.joints_w
    return fit.T_w_p, fit.angles_rad, fit.joints_fit_w


def final_hand(results: Mapping[str, Any]) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """The session's final hand: (vertices (k, 3) in the object frame, faces), and its joints
    (21, 3) in the world; refined when ``refine_grasp`` ran, else the stage-3 fit."""
    refined = results.get("refine_grasp")
    if refined is not None:
        return (refined.hand_vertices_o, refined.hand_faces), refined.joints_w
    fit = results["fit_hand"]
    hand = fit.mesh()
    T_o_w = inv_T(results["estimate_adjustment"].T_w_o)  # object at the first steady frame
    return (transform_points(T_o_w, hand.vertices), hand.faces), fit.joints_fit_w


def _qa_metrics(session, config, **upstream):
    return qa_metrics.qa_metrics(upstream, config, object_mesh=read_mesh(session),
                                 hand_mesh_o=final_hand(upstream)[0])


def _pictures(session, config, **up):
    """The first steady frame (its camera is the world frame) and the final hand."""
    f = up["select_steady"].steady_from
    sfm, contact = up["reconstruct_hand"], up["build_contactmap"]
    i = int(np.flatnonzero(np.asarray(sfm.frames) == f)[0])
    hand_o, joints_w = final_hand(up)
    image, background = pictures.read_frame(session, f)
    return pictures.pictures(
        image, background, up["detect_keypoints"].keypoints[f],
        project(_K(session), transform_points(inv_T(sfm.T_w_c[i]), joints_w)), f,
        session_id=session.session_id, outlier=~np.asarray(sfm.inlier[i], bool),
        object_mesh=read_mesh(session), contact=contact.contact, observed=contact.observed,
        hand_mesh_o=hand_o, up_o=up["register_scan"].T_turntable_o_scan[2, :3],
        note=str(up["qa_metrics"].verdict), config=config,
    )


# --- the DAG ----------------------------------------------------------------------------------

_REFINE: tuple[str, ...] = ("refine_grasp",)
"""``("refine_grasp",)`` once ``refine_grasp`` is in the DAG: propagate_poses, qa_metrics and
pictures then use the refined hand (``final_hand``); until then ``fit_hand``'s."""

STAGES: dict[str, Stage] = {
    s.name: s
    for s in [
        Stage("load_session", load_session.STAGE_VERSION, load_session.PRESETS, (), ALL_FILES,
              _load),
        Stage("register_object", register_object.STAGE_VERSION, register_object.PRESETS,
              ("load_session",), ("manifest", "object_mesh", "stage1"), _register_object),
        Stage("detect_keypoints", detect_keypoints.STAGE_VERSION, detect_keypoints.PRESETS,
              ("load_session",), ("manifest", "grasp_keypoints", "grasp_color"),
              _detect_keypoints),
        Stage("select_steady", select_steady.STAGE_VERSION, select_steady.PRESETS,
              ("load_session", "detect_keypoints"), ("manifest",), _select_steady),
        Stage("reconstruct_hand", reconstruct_hand.STAGE_VERSION, reconstruct_hand.PRESETS,
              ("load_session", "detect_keypoints", "select_steady"), ("manifest", "grasp_depth"),
              _reconstruct_hand),
        Stage("crosscheck_sfm", crosscheck_sfm.STAGE_VERSION, crosscheck_sfm.PRESETS,
              ("load_session", "detect_keypoints", "reconstruct_hand"), ("manifest",),
              _crosscheck_sfm),
        Stage("fit_hand", fit_hand.STAGE_VERSION, fit_hand.PRESETS,
              ("load_session", "reconstruct_hand"), ("manifest",), _fit_hand),
        Stage("estimate_adjustment", estimate_adjustment.STAGE_VERSION,
              estimate_adjustment.PRESETS,
              ("load_session", "register_object", "detect_keypoints", "select_steady",
               "reconstruct_hand", "fit_hand"),
              ("manifest", "object_mesh", "grasp_depth"), _estimate_adjustment),
        Stage("register_scan", register_scan.STAGE_VERSION, register_scan.PRESETS,
              ("load_session",), ("manifest", "object_mesh", "scan_depth"), _register_scan),
        Stage("build_contactmap", build_contactmap.STAGE_VERSION, build_contactmap.PRESETS,
              ("load_session", "register_scan"), ("manifest", "object_mesh", "scan_thermal"),
              _build_contactmap),
        Stage("refine_grasp", refine_grasp.STAGE_VERSION, refine_grasp.PRESETS,
              ("load_session", "fit_hand", "estimate_adjustment", "build_contactmap"),
              ("manifest", "object_mesh"), _refine_grasp),
        Stage("propagate_poses", propagate_poses.STAGE_VERSION, propagate_poses.PRESETS,
              ("load_session", "detect_keypoints", "select_steady", "reconstruct_hand",
               "fit_hand", "register_object", "estimate_adjustment") + _REFINE,
              ("manifest",), _propagate_poses),
        Stage("qa_metrics", qa_metrics.STAGE_VERSION, qa_metrics.PRESETS,
              ("load_session", "detect_keypoints", "reconstruct_hand", "crosscheck_sfm",
               "fit_hand", "register_object", "estimate_adjustment", "register_scan",
               "build_contactmap", "propagate_poses") + _REFINE, ("manifest", "object_mesh"),
              _qa_metrics),
        Stage("pictures", pictures.STAGE_VERSION, pictures.PRESETS,
              ("load_session", "detect_keypoints", "select_steady", "reconstruct_hand",
               "fit_hand", "estimate_adjustment", "register_scan", "build_contactmap",
               "qa_metrics") + _REFINE,
              ("manifest", "object_mesh", "grasp_color", "grasp_depth"), _pictures),
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
    return {
        name: overrides.get(name) or stage.presets.get(preset, stage.presets["default"])
        for name, stage in STAGES.items()
    }


def settings_overrides(settings: list[str] | tuple[str, ...],
                       preset: str = "default") -> dict[str, StageConfig]:
    """``["stage.field=value", ...]`` (``--set``) as the configs of the stages they change,
    ``preset``'s with the fields set, each setting checked against the stage's config model:
    the stage, the field (a dotted path into nested configs) and the value's type. The value
    is read as JSON (``1.5``, ``true``, ``"x"``, ``[1, 2]``), else taken as a string (enum
    values). Raises ``ValueError`` naming the setting and what is wrong with it."""
    import json

    from pydantic import ValidationError

    base = configs_for(preset)
    out: dict[str, dict[str, Any]] = {}
    configs: dict[str, StageConfig] = {}
    for setting in settings:
        path, sep, raw = setting.partition("=")
        stage, _, field = path.strip().partition(".")
        if not sep or not field:
            raise ValueError(f"--set {setting!r}: expected STAGE.FIELD=VALUE")
        if stage not in STAGES:
            raise ValueError(f"--set {setting!r}: no stage {stage!r}; stages are {list(STAGES)}")
        try:
            value = json.loads(raw)
        except ValueError:
            value = raw
        fields = out.setdefault(stage, {})
        node, model, keys = fields, type(base[stage]), field.split(".")
        for i, key in enumerate(keys):
            known = getattr(model, "model_fields", None)
            if known is None or key not in known:
                where = ".".join([stage, *keys[:i]])
                raise ValueError(f"--set {setting!r}: {where} has no field {key!r}; its fields "
                                 f"are {sorted(known or [])}")
            if i == len(keys) - 1:
                node[key] = value
            else:
                node = node.setdefault(key, {})
                model = known[key].annotation
        merged = _deep_merge(base[stage].model_dump(), fields)
        try:
            configs[stage] = type(base[stage]).model_validate(merged)
        except ValidationError as exc:
            raise ValueError(f"--set {setting!r}: {exc.errors()[0]['msg']}") from None
    return configs


def _deep_merge(a: dict, b: Mapping) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, Mapping) and isinstance(
            out.get(k), dict) else v
    return out


def run_stage(
    stage: Stage, session_dir: Path | str, config: StageConfig, upstream: Mapping[str, Any]
) -> Any:
    """Run one stage given its upstream results (``load_session`` gets the directory)."""
    if stage.name == "load_session":
        return stage.run(session_dir, config)
    return stage.run(upstream["load_session"], config, **{k: upstream[k] for k in stage.upstream})


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
