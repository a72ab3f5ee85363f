"""Quality gate of one session: the metrics of ``pipeline.md`` item 11 and a verdict.

Every metric is read from the upstream stage results (reprojection RMSE and inlier ratio of
reconstruct_hand, the GTSAM vs pycolmap and RGB-D vs pixels-only discrepancies, fitness and inlier
RMSE of the three rigid registrations, the hand fit residual, the contact map's coverage,
``refine_grasp``'s before / after penetration and contact agreement) or computed here from
them (the worst window of keypoint outliers; penetration and agreement of fit_hand's hand
when there is no refinement, by the same ``hand.surface`` functions).

Each metric has a :class:`Bound` in the config: beyond ``flag`` the session is ``flagged``
(usable, worth a look), beyond ``fail`` it is ``failed`` (the result cannot be trusted); the
default limits are calibrated against synthetic truth (``bench/qa_calibration.py``). The
stages' own warnings (an ambiguous stage-1 or scan registration of a symmetric object, scan
views that see empty space where the registered mesh lies, an all-ambient thermal scan) flag
the session too; an ambiguity the pipeline resolves itself (estimate_adjustment's, see
:func:`stage_notes`) is a note. A metric whose stage did not run
(crosscheck disabled, no refinement yet) is reported in ``missing`` and never changes the
verdict. This module is the one place that decides a session's ``status``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from graspcap.schemas.qa import QA_METRICS
from graspcap.schemas.tables import Status
from graspcap.tasks.core.config import StageConfig
from graspcap.tasks.outputs.qa_measures import (
    hand_object_metrics,
    refined_metrics,
    window_outlier_share,
)

STAGE_VERSION = "qa_metrics/15"
STAGE = "qa_metrics"


Verdict = Status
"""A session's QA verdict: the ``status`` of its catalog row (one enum for both)."""


class Bound(StageConfig):
    """Limits of one metric; which side is bad is the metric's (see ``METRICS``)."""

    flag: float | None = None
    """Beyond this the session is flagged; None: never flagged by this metric."""
    fail: float | None = None
    """Beyond this the session failed; None: never failed by this metric."""


@dataclass(frozen=True)
class MetricSpec:
    """How a metric reads in a reason: its label, unit and which side is bad."""

    label: str
    unit: str
    higher_is_worse: bool
    digits: int = 2


METRICS: dict[str, MetricSpec] = {
    m.name: MetricSpec(m.label, m.unit, m.higher_is_worse, m.digits) for m in QA_METRICS
}  # declared once, in schemas/qa.py
"""Every metric of a :class:`QaReport`, in report order."""


class QaMetricsConfig(StageConfig):
    """Flag and fail limits per metric, and how the hand-object metrics are measured.

    The default limits are calibrated by ``bench/qa_calibration.py`` on 26 synthetic sessions
    (20 realistic, 6 hard; 11 trustworthy and 15 wrong by the truth): a flag limit lies 1.5x
    beyond the worst trustworthy value ("x 1.5": upper limits are that value x 1.5, lower
    limits have its distance to 1 x 1.5), unless its docstring says otherwise; a fail limit
    lies where the wrong sessions were and no trustworthy one came near.
    """

    reproj_rmse_px: Bound = Bound(flag=5.9, fail=8.0)
    """SfM reprojection RMSE (px), upper limits; trustworthy <= 3.91 (x 1.5)."""
    inlier_ratio: Bound = Bound(flag=0.915, fail=0.6)
    """Share of keypoint observations kept as inliers by reconstruct_hand, lower limits; trustworthy
    >= 0.944 (x 1.5); the hard sessions, all wrong, had 0.74-0.83."""
    window_outlier_share: Bound = Bound(flag=0.2, fail=0.45)
    """Share of the keypoint detections that reconstruct_hand rejected as outliers, in the worst
    window of ``outlier_window_frames`` consecutive steady frames (see
    :func:`window_outlier_share`), upper limits; trustworthy <= 0.099 (x 2: a window's share
    fluctuates more than a session's); onsets detected 12-24 frames early gave 0.54-0.67."""
    crosscheck_mm: Bound = Bound(flag=0.5, fail=5.0)
    """Largest joint discrepancy between GTSAM and pycolmap on the same pixels-only problem
    (mm, after a similarity), upper limits; trustworthy <= 0.05 (numerical noise), so the
    flag is half of issue 3's 1 mm target instead of x 1.5."""
    crosscheck_camera_deg: Bound = Bound(flag=0.57, fail=5.0)
    """Largest camera rotation discrepancy between GTSAM and pycolmap (deg), upper limits;
    trustworthy <= 0.378 (x 1.5); 0.94-2.9 where the cameras were wrong."""
    rgbd_discrepancy_mm: Bound = Bound(flag=21.7, fail=25.0)
    """Largest joint difference between the RGB-D result and pycolmap's pixels-only optimum
    (mm, after a similarity), upper limits; the depth terms move joints by several mm by
    design. Recalibrated in session 18 on 80 realistic tuning sessions (``[9400, i]`` i < 20
    at 60/90/120 frames, ``[86381]``, ``[53582]``, ``[83761]``, ``[77421]``, ``[42813]`` x12
    at 60; ``bench/qa_calibration.py``): trustworthy <= 14.46 (x 1.5), the 14 not-good ones
    3.1-13.7 and never caught by it alone (the 26-session calibration's 8.14 x 1.5 = 12.5
    flagged a good session at 14.46)."""
    registration_fitness: Bound = Bound(flag=0.90, fail=0.6)
    """register_object's registration fitness (share of scene points explained), lower limits;
    on the 80 tuning sessions above trustworthy >= 0.934 (x 1.5 gives 0.901), the not-good ones
    0.984-1.00 (a wrong stage-1 pose of a near-symmetric object explains the depth as well);
    the 26-session calibration's 0.972 x 1.5 (0.95) flagged good sessions at 0.934 and 0.94."""
    registration_rmse_mm: Bound = Bound(flag=1.7, fail=5.0)
    """register_object's inlier RMSE (mm), upper limits; trustworthy <= 1.12 (x 1.5)."""
    adjustment_fitness: Bound = Bound(flag=0.5, fail=0.3)
    """Fitness of the object at the first steady frame (``estimate_adjustment``), lower
    limits; trustworthy >= 0.644 (x 1.5 gives 0.47; the stage itself refuses < 0.5)."""
    adjustment_rmse_mm: Bound = Bound(flag=5.0, fail=10.0)
    """Inlier RMSE of ``estimate_adjustment`` (mm), upper limits; trustworthy <= 3.3 (x 1.5)."""
    object_spread_deg: Bound = Bound(flag=1.05)
    """Median rotation of the object's pose in the hand's world, each registered steady frame's
    ``T_w_c @ T_c_o`` (stage 2's camera and the object registered in that frame's own depth),
    from their mean (``TrackedAverage.spread_deg``), upper limit: after the onset hand and
    object are one rigid body, so the spread is how far stage 2's cameras disagree with the
    depth, a camera error seen without the pixels. Set in session 18 on 80 realistic tuning
    sessions (``registration_fitness``'s pool): good ones <= 0.70 (x 1.5), the two not-good
    sessions QA passed for their cameras (1.22 and 1.33 deg off, good <= 1) 1.71 and 1.21. It
    does not see cameras that are wrong together with the object's tracking (real-detector
    tuning ``[22282, 2/7/10]``, cameras 16-20 deg off, spread 0.12-0.25: their contact
    agreements fail them)."""
    scan_fitness: Bound = Bound(flag=0.94, fail=0.6)
    """Fitness of the object on the platter during the thermal scan, lower limits;
    trustworthy >= 0.962 (x 1.5 gives 0.943)."""
    scan_rmse_mm: Bound = Bound(flag=1.9, fail=5.0)
    """Inlier RMSE of the scan registration (mm), upper limits; trustworthy <= 1.26 (x 1.5)."""
    fit_residual_mm: Bound = Bound(fail=15.0)
    """RMS distance of the fitted hand model's joints to the SfM joints (mm), upper limit: a
    fail only. It measures how well our 20-DoF model fits the hand, and another hand's
    proportions are not our model's: the wild rig's hands (``graspcap/synth/wild_hand.py``)
    leave 4.6-9.4 mm with every other output good, so no flag (issue 18: a model misfit is
    not evidence that the session is wrong; the old flag, 3.75 mm, was x 1.5 our own rig's
    2.46). The fail stays where the SfM hand itself was wrong: 24-34 mm on our rig, 17-37 mm
    on the wild tuning set (seed 9700), all with cameras tens of degrees off."""
    penetration_max_mm: Bound = Bound(flag=2.0, fail=10.0)
    """Deepest hand vertex inside the object (mm), upper limits: issue 6's target (trustworthy
    <= 0.13, x 1.5 would flag sub-millimetre contact noise; 2.98 on a wrong session)."""
    penetration_mean_mm: Bound = Bound(flag=1.0)
    """Mean depth of the hand vertices inside the object (mm; 0 when none is), upper."""
    fit_contact_agreement: Bound = Bound(flag=0.3)
    """``contact_agreement`` of fit_hand's fit, before ``refine_grasp`` drew the hand to the
    contact map, lower limits: the video's hand and the thermal scan, two independent
    measurements, agree on where the grasp is (low: the hand poses, the object pose or the
    contact map's registration is wrong); trustworthy >= 0.405, wrong 0-0.29 where this was
    the first sign: the flag sits between them (x 1.18, a thinner margin than the others)."""
    contact_agreement: Bound = Bound(flag=0.92, fail=0.3)
    """Share of contacted observed vertices within ``near_hand_mm`` of the final hand, lower
    limits; objects registered upside down gave 0-0.28. Flag set on the issue-18 tuning set
    (realistic ``[9400, i]`` i < 20, good by ``GOOD_IF``): good sessions >= 0.926, not-good
    ones 0.30-0.91 where this was the evidence (the earlier 0.94 flagged a good mug at
    0.926)."""
    hand_contact_agreement: Bound = Bound(flag=0.3)
    """Share of observed vertices within ``near_hand_mm`` of the final hand that are
    contacted, lower limits; trustworthy >= 0.533 (x 1.5; fingers lying along a surface
    without pressure leave little heat)."""
    contact_coverage: Bound = Bound(flag=0.35, fail=0.15)
    """Share of object vertices seen by a thermal view, lower limits; trustworthy >= 0.563
    (x 1.5; the face an object stands on is never seen)."""
    noisy_share: float = 0.04
    """Detections whose SfM reprojection RMSE exceeds this share of the hand's image size are
    a noisy detector's (a real detector on real grasping hands misses by 5-10 % of the hand;
    our rig's clean detections leave 1-2.5 %). There the pixel-consistency metrics
    (:data:`PIXEL_CONSISTENCY`) measure the detector, not the output: the cameras come from
    the depth (``joint_solve``'s chain start) and a session whose every other output was good
    had 12.8-25.9 px (real-detector ``[82332, i]``, tuning since session 13). They are then
    not judged by their limits but by ``noisy_fail_share`` alone, and the session is
    flagged, never ``ok``: nothing here measures its cameras and hand then (real-detector
    ``[56705, i]``, held out at qa_metrics/10, which let such sessions be ``ok``: 2 of 3
    ``ok`` were not good, cameras 1.4-2.5 deg off). Failures still come from the
    measurements that do not depend on the pixels' noise (registrations, penetration, the
    contact agreements)."""
    noisy_fail_share: float = 0.25
    """With noisy detections, a reprojection RMSE beyond this share of the hand's image size
    fails the session: no one hand explains the detections (real-detector tuning sessions
    ``[82332, i]``: 7-16 %, good or not; ``docs/qa.md``)."""
    contact_threshold: float = 0.4
    """A vertex with contact at or above this counts as contacted (the issue's binarisation);
    used when ``refine_grasp`` did not run (else its own, equal by default, was used)."""
    near_hand_mm: float = 3.0
    """An object vertex this close to the hand surface counts as touched by the hand; used
    when ``refine_grasp`` did not run, else its ``agreement_dist_mm`` (3 mm, issue 6's
    distance) was. ``pipeline.md`` says 5 mm; one distance for both stages is what matters."""
    outlier_window_frames: int = 8
    """Consecutive steady frames per window of ``window_outlier_share``."""
    stage_flags: bool = True
    """Flag the stages' own warnings (an ambiguous stage-1 or scan registration, an all-ambient
    scan, a mesh with zero-area faces, joints behind a camera). ``crosscheck_sfm``'s own flag is
    not one: its three numbers are judged here, by these limits; a rejected refinement and an
    ambiguous estimate_adjustment registration are notes (:func:`stage_notes`)."""


def _scaled(config: QaMetricsConfig, factor: float) -> QaMetricsConfig:
    """Every limit moved by ``factor`` toward (<1) or away from (>1) the good side: upper
    limits are multiplied, lower limits (shares in [0, 1]) have their distance to 1 scaled."""
    update = {}
    for name, spec in METRICS.items():
        b: Bound = getattr(config, name)

        def move(x: float | None, spec=spec) -> float | None:
            if x is None:
                return None
            moved = x * factor if spec.higher_is_worse else max(0.0, 1.0 - (1.0 - x) * factor)
            return round(moved, 6)

        update[name] = Bound(flag=move(b.flag), fail=move(b.fail))
    return config.model_copy(update=update)


PRESETS: dict[str, QaMetricsConfig] = {
    "default": QaMetricsConfig(),
    "strict": _scaled(QaMetricsConfig(), 0.8),
    "lenient": _scaled(QaMetricsConfig(), 1.5),
}


@dataclass(frozen=True)
class QaReport:
    """Result of :func:`qa_metrics`.

    Attributes
    ----------
    verdict : Verdict
        ``failed`` if any fail limit is crossed, else ``flagged`` if any flag limit is
        crossed or a stage raised a warning, else ``ok``.
    failures, flags : tuple of str
        Human-readable reasons, e.g. ``"reprojection RMSE 4.1 px > 3.0 px"``.
    metrics : dict of str to float
        Every computed metric by its ``METRICS`` name (finite values only).
    missing : dict of str to str
        Metrics that could not be computed, with why (e.g. the stage did not run).
    notes : tuple of str
        What a person may want to know that changes no verdict (:func:`stage_notes`).
    """

    verdict: Verdict
    failures: tuple[str, ...]
    flags: tuple[str, ...]
    metrics: dict[str, float] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def reasons(self) -> tuple[str, ...]:
        """Failures first, then flags."""
        return self.failures + self.flags

    @property
    def error(self) -> str | None:
        """The catalog row's ``error``: the failures, or None unless failed."""
        if self.verdict != Verdict.FAILED:
            return None
        return "qa_metrics: " + "; ".join(self.failures)

    def summary(self) -> str:
        """A few lines a person can read: verdict, reasons, metrics, missing."""
        lines = [f"verdict: {self.verdict}"]
        lines += [f"  FAIL {r}" for r in self.failures] + [f"  flag {r}" for r in self.flags]
        for name, value in self.metrics.items():
            spec = METRICS.get(name)
            unit = f" {spec.unit}" if spec and spec.unit else ""
            lines.append(f"  {name} = {value:.4g}{unit}")
        lines += [f"  {name}: missing ({why})" for name, why in self.missing.items()]
        lines += [f"  note {n}" for n in self.notes]
        return "\n".join(lines)


def _fmt(value: float, spec: MetricSpec) -> str:
    unit = f" {spec.unit}" if spec.unit else ""
    return f"{value:.{spec.digits}f}{unit}"


def judge(value: float, name: str, bound: Bound) -> tuple[str | None, str | None]:
    """``(failure, flag)`` reasons of one metric value against its bound (None: fine)."""
    spec = METRICS[name]

    def beyond(limit: float | None) -> bool:
        if limit is None:
            return False
        return value > limit if spec.higher_is_worse else value < limit

    op = ">" if spec.higher_is_worse else "<"
    for level, limit in (("fail", bound.fail), ("flag", bound.flag)):
        if beyond(limit):
            reason = f"{spec.label} {_fmt(value, spec)} {op} {_fmt(limit, spec)}"
            return (reason, None) if level == "fail" else (None, reason)
    return None, None


def _attr(results: Mapping[str, Any], stage: str, attr: str) -> Any:
    result = results.get(stage)
    return None if result is None else getattr(result, attr, None)


PIXEL_CONSISTENCY: tuple[str, ...] = (
    "reproj_rmse_px", "inlier_ratio", "window_outlier_share", "crosscheck_mm",
    "crosscheck_camera_deg", "rgbd_discrepancy_mm", "fit_residual_mm",
)
"""Metrics of how well the detections' pixels agree with the solve (and the pixels-only
cross-check with it; ``fit_residual_mm`` of the joint solve, which noisy detections take, is
each joint's distance from its detections' rays): judged by their limits only where the
detections are clean (``QaMetricsConfig.noisy_share``)."""


_SOURCES: dict[str, tuple[str, str, float]] = {
    "reproj_rmse_px": ("reconstruct_hand", "reproj_rmse_px", 1.0),
    "inlier_ratio": ("reconstruct_hand", "inlier_ratio", 1.0),
    "crosscheck_mm": ("crosscheck_sfm", "max_joint_discrepancy_m", 1000.0),
    "crosscheck_camera_deg": ("crosscheck_sfm", "max_camera_rotation_deg", 1.0),
    "rgbd_discrepancy_mm": ("crosscheck_sfm", "max_rgbd_joint_discrepancy_m", 1000.0),
    "registration_fitness": ("register_object", "fitness", 1.0),
    "registration_rmse_mm": ("register_object", "inlier_rmse_m", 1000.0),
    "adjustment_fitness": ("estimate_adjustment", "fitness", 1.0),
    "adjustment_rmse_mm": ("estimate_adjustment", "inlier_rmse_m", 1000.0),
    "scan_fitness": ("register_scan", "fitness", 1.0),
    "scan_rmse_mm": ("register_scan", "inlier_rmse_m", 1000.0),
    "fit_residual_mm": ("fit_hand", "rmse_mm", 1.0),
    "contact_coverage": ("build_contactmap", "coverage", 1.0),
}
"""Metrics read off a stage result: (stage, attribute, factor to the metric's unit)."""


def object_spread(results: Mapping[str, Any]) -> tuple[float, str | None]:
    """``estimate_adjustment``'s spread of the object's pose over the registered frames (deg),
    or NaN and why it is missing (``QaMetricsConfig.object_spread_deg``)."""
    if results.get("estimate_adjustment") is None:
        return math.nan, "estimate_adjustment did not run"
    average = _attr(results, "estimate_adjustment", "average")
    if average is None:
        return math.nan, "estimate_adjustment took no mean over the tracked frames"
    if average.T_w_o is None or not math.isfinite(average.spread_deg):
        return math.nan, f"no mean over the tracked frames: {average.reason}"
    return float(average.spread_deg), None


def stage_notes(results: Mapping[str, Any]) -> list[str]:
    """What the stages report that changes no verdict: a refinement rejected in favour of the
    fit_hand's fit (whose agreement with the contact map ``fit_contact_agreement`` judges), and an
    ambiguous estimate_adjustment registration of a symmetric object. The pipeline resolves that
    itself (it tries register_object's runner-up and keeps the pose the depth agrees with
    better, and among equal poses the one nearest register_object's), and a wrong resolution
    puts the hand on the wrong side of the object, which the contact agreements judge against
    the independent thermal scan (the accuracy bench's 12 x 120-frame sessions: as a flag it
    flagged trustworthy sessions and no wrong one). An ambiguous register_object registration
    was a note too until ``qa_metrics/14``; it is a flag now (:data:`STAGE1_AMBIGUOUS`).

    Also what the stages noted about unusual input: keypoint frames dropped (far outside the
    image, corrupt) or with several candidate hands, scan views sharing an angle or skipped,
    thermal views left out, a contact map from one view; the hand's shape left at the template's
    proportions because the joints were too far off for it (``HandFit.shape_note``); an object
    pose estimate_adjustment found only by its last resort (``frame_consensus``: a small object
    in the fist; the tracking and ``object_spread_deg`` judge it frame by frame)."""
    notes = []
    if _attr(results, "refine_grasp", "accepted") is False:
        notes.append(f"refine_grasp: refinement rejected, the stage-3 fit kept "
                     f"({_attr(results, 'refine_grasp', 'reason')})")
    if _attr(results, "estimate_adjustment", "ambiguous"):
        notes.append("estimate_adjustment: ambiguous (the pose nearest stage 1 kept)")
    if str(_attr(results, "estimate_adjustment", "path")) == "frame_consensus":
        notes.append(f"estimate_adjustment: the object found alone in "
                     f"{_attr(results, 'estimate_adjustment', 'views')} steady frames that "
                     "agree (too few depth pixels beside the hand in any one frame)")
    keypoints = results.get("detect_keypoints")
    if keypoints is not None and hasattr(keypoints, "qa_notes"):
        notes += keypoints.qa_notes()
    notes += [f"register_object: {n}" for n in _attr(results, "register_object", "notes") or ()]
    notes += [f"register_scan: {n}" for n in _attr(results, "register_scan", "notes") or ()]
    notes += [f"build_contactmap: {n}" for n in _attr(results, "build_contactmap", "notes") or ()]
    if _attr(results, "fit_hand", "shape_note"):
        notes.append(f"fit_hand: {_attr(results, 'fit_hand', 'shape_note')}")
    if _first_camera_copied(results) and _T_w_o_averaged(results):
        # the flag's worry, T_adj registered through a copied camera, does not apply: T_w_o is
        # the mean over the tracked frames; frames.camera_solved marks the frame itself
        notes.append("reconstruct_hand: the first steady frame has no pose of its own (a "
                     "neighbour's was copied onto it); T_w_o is the mean over the tracked "
                     "frames, not that frame's registration")
    return notes


def _first_camera_copied(results: Mapping[str, Any]) -> bool:
    valid = _attr(results, "reconstruct_hand", "pose_valid")
    return valid is not None and len(valid) > 0 and not valid[0]


def _T_w_o_averaged(results: Mapping[str, Any]) -> bool:
    """``estimate_adjustment``'s ``T_w_o`` is the mean over the tracked frames, not the first
    steady frame's registration (``tracked_average``)."""
    average = _attr(results, "estimate_adjustment", "average")
    return average is not None and getattr(average, "T_w_o", None) is not None


STAGE1_AMBIGUOUS = ("register_object: near-symmetric object, T_w_o_stage1 ambiguous (a twin "
                    "or a turn about an axis fits the turntable depth as well; the per-frame "
                    "poses come from estimate_adjustment's own registration in the grasp)")
"""The flag of an ambiguous stage-1 registration. It was a note until ``qa_metrics/14``:
``estimate_adjustment`` registers the object again in the grasp, so the per-frame poses do not
rest on it, but the catalog's ``T_w_o_stage1`` does, and a good session (``docs/qa.md``) has
it within 2 deg. On 80 realistic tuning sessions (session 18) 11 were ambiguous, 8 of them
with the stage-1 pose 2.1-50 deg off; of the 69 others none was (``docs/qa.md``)."""


def stage_warnings(results: Mapping[str, Any]) -> list[str]:
    """The warnings the stages raise themselves, as flag reasons."""
    reasons = []
    if _attr(results, "register_object", "ambiguous"):
        reasons.append(STAGE1_AMBIGUOUS)
    note = _attr(results, "register_scan", "note")  # ambiguity, or views contradicting it
    if note:
        reasons.append(f"register_scan: {note}")
    elif _attr(results, "register_scan", "ambiguous"):
        reasons.append("register_scan: symmetric object, scan registration ambiguous")
    if _attr(results, "build_contactmap", "all_ambient"):
        reasons.append("build_contactmap: no contact anywhere (the thermal scan is all ambient)")
    uncertain = _attr(results, "select_steady", "uncertain")
    if uncertain:
        reasons.append(f"select_steady: steady onset uncertain: {uncertain}")
    if _first_camera_copied(results) and not _T_w_o_averaged(results):
        reasons.append("reconstruct_hand: the first steady frame, whose camera is the world "
                       "frame, has no pose of its own (a neighbour's was copied onto it)")
    n_behind = _attr(results, "propagate_poses", "n_behind")
    if n_behind:
        reasons.append(f"propagate_poses: {int(n_behind)} joint(s) at or behind a virtual "
                       "camera (its pose is wrong)")
    n_bad = _attr(results, "build_contactmap", "n_degenerate_faces")
    if n_bad:
        reasons.append(f"build_contactmap: object mesh has {int(n_bad)} zero-area face(s)")
    return reasons


def qa_metrics(
    results: Mapping[str, Any],
    config: QaMetricsConfig = PRESETS["default"],
    *,
    object_mesh: tuple[np.ndarray, np.ndarray] | None = None,
    hand_mesh_o: tuple[np.ndarray, np.ndarray] | None = None,
    hand_size_px: float | None = None,
) -> QaReport:
    """Metrics and verdict of one session.

    Parameters
    ----------
    results : mapping of stage name to result
        Upstream results (``tasks.pipeline.STAGES`` names); an absent or None entry is a
        stage that did not run, and its metrics are reported missing.
    config : QaMetricsConfig
    object_mesh : ((n, 3) float, (m, 3) int), optional
        The object mesh in its own frame, file vertex order (as the contact map).
    hand_mesh_o : ((k, 3) float, (l, 3) int), optional
        The final (refined, else fitted) hand surface in the object frame. When
        ``refine_grasp`` ran, penetration and contact agreement are its ``after`` metrics
        (the same functions on the same hand) and the meshes are not needed.
    hand_size_px : float, optional
        The hand's image size in the steady frames (median bounding-box diagonal of the
        detections); with it, noisy detections are told from clean ones (``noisy_share``).
    """
    metrics: dict[str, float] = {}
    missing: dict[str, str] = {}
    for name, (stage, attr, factor) in _SOURCES.items():
        value = _attr(results, stage, attr)
        if value is None:
            missing[name] = f"{stage} did not run"
        elif not math.isfinite(float(value)):
            missing[name] = f"{stage} gave {float(value)}"
        else:
            metrics[name] = float(value) * factor
    spread, why = object_spread(results)
    if why is None:
        metrics["object_spread_deg"] = spread
    else:
        missing["object_spread_deg"] = why
    rec = results.get("reconstruct_hand")
    if rec is None:
        missing["window_outlier_share"] = "reconstruct_hand did not run"
    else:
        share = window_outlier_share(rec.inlier, rec.residuals_px, config.outlier_window_frames)
        if math.isfinite(share):
            metrics["window_outlier_share"] = share
        else:
            missing["window_outlier_share"] = "no keypoint detected in the steady frames"
    refined = results.get("refine_grasp")
    if refined is not None and getattr(refined, "after", None) is not None:
        measured, why = refined_metrics(refined)
        metrics.update(measured)
        missing.update(why)
    elif object_mesh is None or hand_mesh_o is None:
        for name in ("penetration_max_mm", "penetration_mean_mm", "fit_contact_agreement",
                     "contact_agreement", "hand_contact_agreement"):
            missing[name] = "no object mesh or hand mesh given"
    else:
        contact = results.get("build_contactmap")
        measured, why = hand_object_metrics(
            *object_mesh, *hand_mesh_o,
            None if contact is None else contact.contact,
            None if contact is None else contact.observed,
            near_mm=config.near_hand_mm, contact_threshold=config.contact_threshold,
        )  # fmt: skip
        metrics.update(measured)
        missing.update(why)
        if "contact_agreement" in measured:  # no refinement: the final hand is the fit
            metrics["fit_contact_agreement"] = measured["contact_agreement"]
        elif "contact_agreement" in why:
            missing["fit_contact_agreement"] = why["contact_agreement"]
    failures, flags = [], []
    share = (metrics.get("reproj_rmse_px", math.nan) / hand_size_px
             if hand_size_px is not None and hand_size_px > 0 else math.nan)
    noisy = math.isfinite(share) and share > config.noisy_share
    if noisy:
        flags.append(f"noisy detections: reprojection RMSE {metrics['reproj_rmse_px']:.1f} px "
                     f"is {share:.1%} of the hand's {hand_size_px:.0f} px (> "
                     f"{config.noisy_share:.1%}): no check here vouches for the cameras and "
                     "the hand, the pixel-consistency metrics are not judged")
        if share > config.noisy_fail_share:
            failures.append(f"reprojection RMSE {share:.1%} of the hand's image size > "
                            f"{config.noisy_fail_share:.1%}: no one hand explains the detections")
    for name in METRICS:
        if name in metrics and not (noisy and name in PIXEL_CONSISTENCY):
            failure, flag = judge(metrics[name], name, getattr(config, name))
            failures += [failure] if failure else []
            flags += [flag] if flag else []
    if config.stage_flags:
        flags += stage_warnings(results)
    verdict = Verdict.FAILED if failures else Verdict.FLAGGED if flags else Verdict.OK
    ordered = {n: metrics[n] for n in METRICS if n in metrics}
    return QaReport(verdict, tuple(failures), tuple(flags), ordered,
                    {n: missing[n] for n in METRICS if n in missing}, tuple(stage_notes(results)))


__all__ = [
    "METRICS", "PIXEL_CONSISTENCY", "PRESETS", "STAGE_VERSION", "Bound", "MetricSpec",
    "object_spread",
    "QaMetricsConfig", "QaReport",
    "Verdict", "hand_object_metrics", "judge", "qa_metrics", "refined_metrics", "stage_notes",
    "stage_warnings",
    "window_outlier_share",
]  # fmt: skip
