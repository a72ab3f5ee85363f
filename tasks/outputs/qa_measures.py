"""What ``qa_metrics`` computes itself from the stage results (the limits and the verdict stay
in ``qa_metrics``): the worst window of keypoint outliers, and the hand-object metrics of the
final hand (``refine_grasp``'s own after-refinement numbers, or the same ``hand.surface``
measures on fit_hand's hand)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from graspcap.tasks.hand.surface import contact_agreement, penetration_mm


def hand_object_metrics(
    object_vertices: np.ndarray,
    object_faces: np.ndarray,
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    contact: np.ndarray | None,
    observed: np.ndarray | None,
    *,
    near_mm: float,
    contact_threshold: float,
) -> tuple[dict[str, float], dict[str, str]]:
    """Penetration and contact agreement of a hand and an object, both in the object frame.

    The measures are ``hand.surface.penetration_mm`` and ``hand.surface.contact_agreement``,
    the ones ``refine_grasp`` reports before and after its refinement.

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
    near_mm, contact_threshold : float
        As ``hand.surface.contact_agreement``.

    Returns
    -------
    metrics : dict
        ``penetration_max_mm``, ``penetration_mean_mm`` (depth of the hand vertices inside
        the object; mean over the penetrating vertices, 0 when none is) and, with a contact
        map, ``contact_agreement`` and ``hand_contact_agreement``.
    missing : dict
        Agreements that have no denominator (nothing contacted, nothing near the hand).
    """
    pen_max_mm, pen_mean_mm = penetration_mm(object_vertices, object_faces, hand_vertices)
    metrics = {"penetration_max_mm": pen_max_mm, "penetration_mean_mm": pen_mean_mm}
    if contact is None or observed is None:
        why = "no contact map (build_contactmap did not run)"
        return metrics, {"contact_agreement": why, "hand_contact_agreement": why}
    near, touch = contact_agreement(
        object_vertices, contact, observed, hand_vertices, hand_faces,
        near_mm=near_mm, contact_threshold=contact_threshold,
    )  # fmt: skip
    return _agreements(metrics, near, touch, near_mm)


def _agreements(metrics: dict[str, float], near: float, touch: float, near_mm: float | None
                ) -> tuple[dict[str, float], dict[str, str]]:
    """The two agreement shares into ``metrics``, or into missing when NaN (no denominator)."""
    missing: dict[str, str] = {}
    if math.isfinite(near):
        metrics["contact_agreement"] = float(near)
    else:
        missing["contact_agreement"] = "no observed vertex is contacted"
    if math.isfinite(touch):
        metrics["hand_contact_agreement"] = float(touch)
    else:
        within = "near" if near_mm is None else f"within {near_mm:g} mm of"
        missing["hand_contact_agreement"] = f"no observed vertex {within} the hand"
    return metrics, missing


def refined_metrics(refined: Any) -> tuple[dict[str, float], dict[str, str]]:
    """Penetration and contact agreement of the final hand as ``refine_grasp`` measured it
    (its ``after`` metrics: the hand it returns, by the same functions)."""
    after = refined.after
    metrics = {"penetration_max_mm": float(after.penetration_max_mm),
               "penetration_mean_mm": float(after.penetration_mean_mm)}
    metrics, missing = _agreements(metrics, after.contact_near_share,
                                   after.touch_contacted_share, None)
    if math.isfinite(refined.before.contact_near_share):
        metrics["fit_contact_agreement"] = float(refined.before.contact_near_share)
    else:
        missing["fit_contact_agreement"] = "no observed vertex is contacted"
    return metrics, missing


def window_outlier_share(inlier: np.ndarray, residuals_px: np.ndarray, window: int) -> float:
    """Share of the detections rejected as outliers in the worst window of steady frames.

    ``reconstruct_hand`` keeps one rigid hand for every frame from the onset on; where the hand
    still moves (an onset detected too early, a re-grasp) the detections of those frames cannot fit
    it and most are rejected, while detector outliers are spread evenly over the video. So the
    worst window of ``window`` consecutive frames stands out when the static-hand assumption
    broke, even when the session's overall inlier ratio and RMSE look normal.

    Parameters
    ----------
    inlier : (m, 21) bool
        ``reconstruct_hand``'s inlier flags per solve frame (from the onset on).
    residuals_px : (m, 21) float
        Its residuals, NaN where nothing was detected.
    window : int
        Frames per window (all frames when fewer).

    Returns
    -------
    float
        Outliers / detections in the worst window; NaN without detections.
    """
    detected = np.isfinite(np.asarray(residuals_px, float))
    outlier = detected & ~np.asarray(inlier, bool)
    k = max(1, min(int(window), len(detected)))
    det = np.concatenate([[0], np.cumsum(detected.sum(1))])
    out = np.concatenate([[0], np.cumsum(outlier.sum(1))])
    n_det = det[k:] - det[:-k]
    if not n_det.any():
        return float("nan")
    share = (out[k:] - out[:-k]) / np.maximum(n_det, 1)
    return float(share[n_det > 0].max())


__all__ = ["hand_object_metrics", "refined_metrics", "window_outlier_share"]
