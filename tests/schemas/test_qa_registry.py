"""One declaration per QA metric (schemas/qa.py): the stage's metric specs, its config bounds,
the catalog's qa_* columns and the rows' column lists all follow it."""

from __future__ import annotations

from graspcap.flows.rows import FORMAT_3_QA, QA_COLUMNS
from graspcap.schemas.qa import QA_BY_NAME, QA_METRICS, qa_columns
from graspcap.schemas.tables import SESSIONS_SCHEMA
from graspcap.tasks.outputs.qa_metrics import METRICS, Bound, QaMetricsConfig


def test_the_stage_reports_and_bounds_the_registry_in_its_order():
    names = [m.name for m in QA_METRICS]
    assert list(METRICS) == names
    bounds = [n for n, f in QaMetricsConfig.model_fields.items() if f.annotation is Bound]
    assert bounds == names
    assert METRICS["crosscheck_camera_deg"].unit == "deg"
    assert METRICS["inlier_ratio"].higher_is_worse is False


def test_the_catalog_columns_are_the_registry_columns_unchanged():
    qa_fields = [f for f in SESSIONS_SCHEMA if f.name.startswith("qa_")
                 and f.name not in ("qa_flags", "qa_notes")]
    assert [f.name for f in qa_fields] == [  # the catalog's columns, in format order
        "qa_reproj_rmse_px", "qa_inlier_ratio", "qa_crosscheck_mm", "qa_registration_rmse_mm",
        "qa_fit_residual_mm", "qa_penetration_max_mm", "qa_penetration_mean_mm",
        "qa_contact_agreement", "qa_contact_coverage", "qa_window_outlier_share",
        "qa_crosscheck_camera_deg", "qa_rgbd_discrepancy_mm", "qa_fit_contact_agreement",
    ]
    assert [f.name for f in qa_fields] == [m.column for m in qa_columns()]
    for f in qa_fields:
        m = QA_BY_NAME[f.name[3:]]
        assert f.metadata[b"unit"].decode() == m.column_unit
        assert f.metadata[b"doc"].decode() == m.column_doc + " Null when not computed."
    assert SESSIONS_SCHEMA.field("qa_contact_coverage").metadata[b"doc"] == (
        b"Share of object vertices seen by a thermal view. Null when not computed.")


def test_the_rows_fill_the_registry_columns():
    assert QA_COLUMNS == tuple(m.name for m in qa_columns())
    assert FORMAT_3_QA == ("qa_window_outlier_share", "qa_crosscheck_camera_deg",
                           "qa_rgbd_discrepancy_mm", "qa_fit_contact_agreement")
    assert [m.name for m in qa_columns(max_format=1)] == list(QA_COLUMNS[:9])
    assert {m.name for m in QA_METRICS} - set(QA_COLUMNS) == {
        "registration_fitness", "adjustment_fitness", "adjustment_rmse_mm", "scan_fitness",
        "scan_rmse_mm", "hand_contact_agreement", "object_spread_deg"}
