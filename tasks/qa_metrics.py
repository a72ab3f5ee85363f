"""Quality gate of one session: the metrics of ``pipeline.md`` item 11 and a verdict.

Every metric is read from the upstream stage results (reprojection RMSE and inlier ratio of
stage 2, the GTSAM vs pycolmap discrepancy, fitness and inlier RMSE of the three rigid
registrations, the hand fit residual, the contact map's coverage) or measured here on the
final hand and the object (penetration depth, contact agreement in both directions), so
that the hand-object numbers have one definition whichever stage produced the hand.

Each metric has a :class:`Bound` in the config: beyond ``flag`` the session is ``flagged``
(usable, worth a look), beyond ``fail`` it is ``failed`` (the result cannot be trusted). The
stages' own warnings (an ambiguous registration of a symmetric object, two solvers that
disagree, an all-ambient thermal scan) flag the session too. A metric whose stage did not run
(crosscheck disabled, no refinement yet) is reported in ``missing`` and never changes the
verdict. This module is the one place that decides a session's ``status``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import open3d as o3d

from graspcap.schemas.tables import Status
from graspcap.tasks.config import StageConfig
from graspcap.tasks.hand_surface import penetration_mm

STAGE_VERSION = "qa_metrics/1"
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
    "reproj_rmse_px": MetricSpec("reprojection RMSE", "px", True),
    "inlier_ratio": MetricSpec("keypoint inlier ratio", "", False),
    "crosscheck_mm": MetricSpec("GTSAM vs pycolmap joint discrepancy", "mm", True),
    "registration_fitness": MetricSpec("stage-1 registration fitness", "", False),
    "registration_rmse_mm": MetricSpec("stage-1 registration RMSE", "mm", True),
    "adjustment_fitness": MetricSpec("adjustment registration fitness", "", False),
    "adjustment_rmse_mm": MetricSpec("adjustment registration RMSE", "mm", True),
    "scan_fitness": MetricSpec("scan registration fitness", "", False),
    "scan_rmse_mm": MetricSpec("scan registration RMSE", "mm", True),
    "fit_residual_mm": MetricSpec("hand fit residual", "mm", True),
    "penetration_max_mm": MetricSpec("hand-object penetration (max)", "mm", True),
    "penetration_mean_mm": MetricSpec("hand-object penetration (mean)", "mm", True),
    "contact_agreement": MetricSpec("contacted vertices near the hand", "", False),
    "hand_contact_agreement": MetricSpec("hand-touching vertices contacted", "", False),
    "contact_coverage": MetricSpec("contact-map coverage", "", False),
}
"""Every metric of a :class:`QaReport`, in report order."""


class QaMetricsConfig(StageConfig):
    """Flag and fail limits per metric, and how the hand-object metrics are measured."""

    reproj_rmse_px: Bound = Bound(flag=5.0, fail=8.0)
    """SfM reprojection RMSE (px), upper limits (detector noise of 2.5 px per coordinate
    alone gives about 3.5 px)."""
    inlier_ratio: Bound = Bound(flag=0.8, fail=0.5)
    """Share of keypoint observations kept as inliers by stage 2, lower limits."""
    crosscheck_mm: Bound = Bound(flag=6.0, fail=25.0)
    """Largest joint discrepancy between GTSAM and pycolmap after a similarity (mm), upper
    limits (``crosscheck_sfm`` raises its own flag by its own config as well)."""
    registration_fitness: Bound = Bound(flag=0.6, fail=0.3)
    """Stage-1 registration fitness (share of scene points explained), lower limits."""
    registration_rmse_mm: Bound = Bound(flag=3.0, fail=10.0)
    """Stage-1 registration inlier RMSE (mm), upper limits."""
    adjustment_fitness: Bound = Bound(flag=0.6, fail=0.3)
    """Fitness of the object at the first steady frame (``estimate_adjustment``), lower."""
    adjustment_rmse_mm: Bound = Bound(flag=3.0, fail=10.0)
    """Inlier RMSE of ``estimate_adjustment`` (mm), upper limits."""
    scan_fitness: Bound = Bound(flag=0.6, fail=0.3)
    """Fitness of the object on the platter during the thermal scan, lower limits."""
    scan_rmse_mm: Bound = Bound(flag=3.0, fail=10.0)
    """Inlier RMSE of the scan registration (mm), upper limits."""
    fit_residual_mm: Bound = Bound(flag=8.0, fail=20.0)
    """RMS distance of the fitted hand model's joints to the SfM joints (mm), upper limits."""
    penetration_max_mm: Bound = Bound(flag=5.0, fail=20.0)
    """Deepest hand vertex inside the object (mm), upper limits."""
    penetration_mean_mm: Bound = Bound(flag=2.0)
    """Mean depth of the hand vertices inside the object (mm; 0 when none is), upper."""
    contact_agreement: Bound = Bound(flag=0.5)
    """Share of contacted observed vertices within ``near_hand_mm`` of the hand, lower."""
    hand_contact_agreement: Bound = Bound(flag=0.1)
    """Share of observed vertices within ``near_hand_mm`` of the hand that are contacted,
    lower limits (low: the hand touches where the thermal scan saw no warmth; fingers lying
    along a surface without pressure leave little heat, so 0.2 to 0.4 is usual)."""
    contact_coverage: Bound = Bound(flag=0.6, fail=0.2)
    """Share of object vertices seen by a thermal view, lower limits (the face an object
    stands on is never seen: 0.7 to 0.8 is usual)."""
    contact_threshold: float = 0.4
    """A vertex with contact at or above this counts as contacted (the issue's binarisation)."""
    near_hand_mm: float = 5.0
    """An object vertex this close to the hand surface counts as touched by the hand."""
    stage_flags: bool = True
    """Flag the stages' own warnings (ambiguous registrations, solver disagreement, an
    all-ambient scan, a mesh with zero-area faces)."""


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
    "strict": _scaled(QaMetricsConfig(), 0.6),
    "lenient": _scaled(QaMetricsConfig(), 1.6),
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
    """

    verdict: Verdict
    failures: tuple[str, ...]
    flags: tuple[str, ...]
    metrics: dict[str, float] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)

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


def hand_object_metrics(
    object_vertices: np.ndarray,
    object_faces: np.ndarray,
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    contact: np.ndarray | None,
    observed: np.ndarray | None,
    config: QaMetricsConfig = PRESETS["default"],
) -> tuple[dict[str, float], dict[str, str]]:
    """Penetration and contact agreement of a hand and an object, both in the object frame.

    Parameters
    ----------
    object_vertices : (n, 3) float
    object_faces : (m, 3) int
    hand_vertices : (k, 3) float
    hand_faces : (l, 3) int
    contact : (n,) float or None
        Contact in [0, 1] per object vertex.
    observed : (n,) bool or None
        Vertices a thermal view saw; the others count in neither agreement.

    Returns
    -------
    metrics : dict
        ``penetration_max_mm``, ``penetration_mean_mm`` (depth of the hand vertices inside
        the object by Open3D's signed distance; mean over the penetrating vertices, 0 when
        none is) and, with a contact map, ``contact_agreement`` and
        ``hand_contact_agreement``.
    missing : dict
        Agreements that have no denominator (nothing contacted, nothing near the hand).
    """
    pen_max_mm, pen_mean_mm = penetration_mm(object_vertices, object_faces, hand_vertices)
    metrics = {"penetration_max_mm": pen_max_mm, "penetration_mean_mm": pen_mean_mm}
    missing: dict[str, str] = {}
    if contact is None or observed is None:
        why = "no contact map (build_contactmap did not run)"
        return metrics, {"contact_agreement": why, "hand_contact_agreement": why}
    hand = o3d.t.geometry.RaycastingScene()
    hand.add_triangles(np.asarray(hand_vertices, np.float32), np.asarray(hand_faces, np.uint32))
    dist_mm = hand.compute_distance(np.asarray(object_vertices, np.float32)).numpy() * 1000.0
    observed = np.asarray(observed, bool)
    contacted = observed & (np.asarray(contact, float) >= config.contact_threshold)
    near = observed & (dist_mm <= config.near_hand_mm)
    if contacted.any():
        metrics["contact_agreement"] = float(np.mean(dist_mm[contacted] <= config.near_hand_mm))
    else:
        missing["contact_agreement"] = "no observed vertex is contacted"
    if near.any():
        metrics["hand_contact_agreement"] = float(np.mean(contacted[near]))
    else:
        missing["hand_contact_agreement"] = (
            f"no observed vertex within {config.near_hand_mm:g} mm of the hand")
    return metrics, missing


def _attr(results: Mapping[str, Any], stage: str, attr: str) -> Any:
    result = results.get(stage)
    return None if result is None else getattr(result, attr, None)


_SOURCES: dict[str, tuple[str, str, float]] = {
    "reproj_rmse_px": ("reconstruct_hand", "reproj_rmse_px", 1.0),
    "inlier_ratio": ("reconstruct_hand", "inlier_ratio", 1.0),
    "crosscheck_mm": ("crosscheck_sfm", "max_joint_discrepancy_m", 1000.0),
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


def stage_warnings(results: Mapping[str, Any]) -> list[str]:
    """The warnings the stages raise themselves, as flag reasons."""
    reasons = []
    if _attr(results, "crosscheck_sfm", "flagged"):
        reasons.append(f"crosscheck_sfm: {_attr(results, 'crosscheck_sfm', 'reason')}")
    if _attr(results, "register_object", "ambiguous"):
        reasons.append("register_object: symmetric object, registration ambiguous")
    if _attr(results, "estimate_adjustment", "ambiguous"):
        reasons.append("estimate_adjustment: ambiguous")
    if _attr(results, "register_scan", "ambiguous"):
        reasons.append("register_scan: symmetric object, scan registration ambiguous")
    if _attr(results, "build_contactmap", "all_ambient"):
        reasons.append("build_contactmap: no contact anywhere (the thermal scan is all ambient)")
    n_behind = _attr(results, "propagate_poses", "n_behind")
    if n_behind:
        reasons.append(f"propagate_poses: {int(n_behind)} joint(s) at or behind a virtual "
                       "camera (its pose is wrong)")
    if _attr(results, "refine_grasp", "accepted") is False:
        reasons.append(f"refine_grasp: refinement rejected, the stage-3 fit kept "
                       f"({_attr(results, 'refine_grasp', 'reason')})")
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
        The final (refined, else fitted) hand surface in the object frame.
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
    if object_mesh is None or hand_mesh_o is None:
        for name in ("penetration_max_mm", "penetration_mean_mm", "contact_agreement",
                     "hand_contact_agreement"):
            missing[name] = "no object mesh or hand mesh given"
    else:
        contact = results.get("build_contactmap")
        measured, why = hand_object_metrics(
            *object_mesh, *hand_mesh_o,
            None if contact is None else contact.contact,
            None if contact is None else contact.observed, config,
        )  # fmt: skip
        metrics.update(measured)
        missing.update(why)
    failures, flags = [], []
    for name in METRICS:
        if name in metrics:
            failure, flag = judge(metrics[name], name, getattr(config, name))
            failures += [failure] if failure else []
            flags += [flag] if flag else []
    if config.stage_flags:
        flags += stage_warnings(results)
    verdict = Verdict.FAILED if failures else Verdict.FLAGGED if flags else Verdict.OK
    ordered = {n: metrics[n] for n in METRICS if n in metrics}
    return QaReport(verdict, tuple(failures), tuple(flags), ordered,
                    {n: missing[n] for n in METRICS if n in missing})


__all__ = [
    "METRICS", "PRESETS", "STAGE_VERSION", "Bound", "MetricSpec", "QaMetricsConfig", "QaReport",
    "Verdict", "hand_object_metrics", "judge", "qa_metrics", "stage_warnings",
]  # fmt: skip
