"""The QA metrics, declared once: what ``qa_metrics`` reports, how a reason reads them, and
which of them the catalog's ``sessions`` table keeps as a ``qa_<name>`` column.

Below both ``tasks/`` (the stage's metric specs and report order) and ``schemas/tables.py`` (the
``qa_*`` columns, their docs, units and the format that added them), which derive from
:data:`QA_METRICS`; ``flows/rows.py`` fills the columns from it, and a test holds the stage
config's flag/fail bounds to the same names. A column's doc is part of the catalog format
(``docs/data_changelog.md``): rewording one is a format change.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class QaMetric:
    """One QA metric."""

    name: str
    label: str
    """How a flag or fail reason names it."""
    unit: str
    """Unit as a reason prints it ('' for a share or ratio)."""
    higher_is_worse: bool
    digits: int = 2
    column_doc: str | None = None
    """Doc of its ``qa_<name>`` column in ``sessions``; None: not in the catalog."""
    column_format: int | None = None
    """Catalog format that added the column."""

    @property
    def column(self) -> str | None:
        return f"qa_{self.name}" if self.column_doc is not None else None

    @property
    def column_unit(self) -> str:
        """The column's unit metadata ('1' for a share or ratio)."""
        return self.unit or "1"


_F3 = "Format 3; null on rows written before."

QA_METRICS: tuple[QaMetric, ...] = (
    QaMetric("reproj_rmse_px", "reprojection RMSE", "px", True,
             column_doc="SfM reprojection RMSE.", column_format=1),
    QaMetric("inlier_ratio", "keypoint inlier ratio", "", False,
             column_doc="Share of keypoint observations kept as inliers.", column_format=1),
    QaMetric("window_outlier_share", "keypoint outliers in the worst frame window", "", True,
             column_doc="Share of the keypoint detections stage 2 rejected as outliers in the "
             "worst window of consecutive steady frames (8 by default; high: the hand moved "
             f"after the detected onset). {_F3}", column_format=3),
    QaMetric("crosscheck_mm", "GTSAM vs pycolmap joint discrepancy", "mm", True,
             column_doc="GTSAM vs COLMAP joint discrepancy.", column_format=1),
    QaMetric("crosscheck_camera_deg", "GTSAM vs pycolmap camera discrepancy", "deg", True,
             column_doc="Largest camera rotation discrepancy between GTSAM and pycolmap on the "
             f"same pixels-only problem. {_F3}", column_format=3),
    QaMetric("rgbd_discrepancy_mm", "RGB-D result vs pixels-only optimum", "mm", True,
             column_doc="Largest joint difference between the RGB-D result and pycolmap's "
             f"pixels-only optimum, after a similarity. {_F3}", column_format=3),
    QaMetric("registration_fitness", "stage-1 registration fitness", "", False),
    QaMetric("registration_rmse_mm", "stage-1 registration RMSE", "mm", True,
             column_doc="Object registration inlier RMSE.", column_format=1),
    QaMetric("adjustment_fitness", "adjustment registration fitness", "", False),
    QaMetric("adjustment_rmse_mm", "adjustment registration RMSE", "mm", True),
    QaMetric("object_spread_deg", "spread of the object's pose over the tracked frames", "deg",
             True),
    QaMetric("scan_fitness", "scan registration fitness", "", False),
    QaMetric("scan_rmse_mm", "scan registration RMSE", "mm", True),
    QaMetric("fit_residual_mm", "hand fit residual", "mm", True,
             column_doc="Hand model fit residual.", column_format=1),
    QaMetric("penetration_max_mm", "hand-object penetration (max)", "mm", True,
             column_doc="Maximum hand-object penetration.", column_format=1),
    QaMetric("penetration_mean_mm", "hand-object penetration (mean)", "mm", True,
             column_doc="Mean hand-object penetration.", column_format=1),
    QaMetric("fit_contact_agreement", "contacted vertices near the fitted hand", "", False,
             column_doc="qa_contact_agreement of the stage-3 fit, before refine_grasp drew the "
             "hand to the contact map (low: the video's hand and the thermal scan disagree on "
             f"the grasp). {_F3}", column_format=3),
    QaMetric("contact_agreement", "contacted vertices near the hand", "", False,
             column_doc="Share of the contacted object vertices (seen by a thermal view, "
             "contact >= 0.4) that the final hand (refined, else fitted) touches: within 3 mm "
             "of its surface or inside it (hand_surface.contact_agreement; 0.4 and 3 mm are "
             "the stage configs' defaults).", column_format=1),
    QaMetric("hand_contact_agreement", "hand-touching vertices contacted", "", False),
    QaMetric("contact_coverage", "contact-map coverage", "", False,
             column_doc="Share of object vertices seen by a thermal view.", column_format=1),
)
"""Every metric of a QA report, in report order."""

QA_BY_NAME: dict[str, QaMetric] = {m.name: m for m in QA_METRICS}


def qa_columns(max_format: int | None = None) -> tuple[QaMetric, ...]:
    """The metrics with a ``sessions`` column, in column order (by the format that added them,
    then report order); up to ``max_format`` when given."""
    kept = [m for m in QA_METRICS if m.column_doc is not None
            and (max_format is None or m.column_format <= max_format)]
    return tuple(sorted(kept, key=lambda m: m.column_format))
