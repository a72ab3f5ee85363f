"""The report page of a version (``catalog/report_page.py``) on catalogs committed without a
build: every session a row, failed first with its reasons, metric cells against the build's
limits, one histogram and one trend per QA column, medians per version, and ``graspcap
report`` by number and tag (the pictures of real builds: tests/flows/test_qa_build.py)."""

from __future__ import annotations

import dataclasses
import re
import statistics
from pathlib import Path

import numpy as np

import graspcap.catalog as gc
from graspcap.catalog.report_page import gather, histogram_svg
from graspcap.cli import main
from graspcap.schemas.qa import QA_BY_NAME, qa_columns
from tests.catalog_factory import make_build
from tests.report_html import check_page

LIMITS = {"configs": {"qa_metrics": {"reproj_rmse_px": {"flag": 0.8, "fail": 1.5},
                                     "contact_coverage": {"flag": 0.3, "fail": None}}}}


def _catalog(root: Path) -> gc.Catalog:
    cat = gc.open(root, create=True)
    cat.commit(make_build(["p01-mug-use-00", "p02-drill-use-00"], seed=1, build_id="b1"))
    second = make_build(["p03-bowl-use-00", "p04-mug-use-00", "p05-mug-use-00"], seed=2,
                        build_id="b2", failed=("p04-mug-use-00",))
    second.sessions[2]["status"] = "flagged"
    second.sessions[2]["qa_flags"] = ["keypoint inlier ratio 0.90 < 0.92"]
    second.sessions[2]["qa_notes"] = ["register_object: near-symmetric object"]
    cat.commit(dataclasses.replace(
        second, build=dataclasses.replace(second.build, parameters=LIMITS)))
    return cat


def test_every_session_is_a_row_failed_first_with_reasons_and_limits(tmp_path):
    cat = _catalog(tmp_path / "cat")
    assert main(["report", "--catalog", str(tmp_path / "cat")]) == 0
    path = tmp_path / "cat" / "reports" / "b2" / "index.html"
    page = check_page(path)
    rows = cat.table("sessions", 2).to_pylist()
    assert [(r.session_id, r.status) for r in page.rows] == [
        ("p04-mug-use-00", "failed"), ("p05-mug-use-00", "flagged"),
        ("p01-mug-use-00", "ok"), ("p02-drill-use-00", "ok"), ("p03-bowl-use-00", "ok")]
    assert len(rows) == 5
    assert "register_object: no platter plane in stage1/depth.png" in page.row_text(
        "p04-mug-use-00")
    flagged = page.row_text("p05-mug-use-00")
    assert "keypoint inlier ratio 0.90 < 0.92" in flagged
    assert "note: register_object: near-symmetric object" in flagged
    assert page.plots == 2 * len(qa_columns())
    # reproj: flag and fail in its histogram and its trend; coverage: the flag in both
    assert page.limit_lines == 2 * 2 + 2 * 1
    text = path.read_text()
    levels = set()
    for r in rows:  # the metric cells against the limits of the build (b2's parameters)
        value = r["qa_reproj_rmse_px"]
        level = "" if value is None else "fail" if value > 1.5 else "flag" if value > 0.8 else ""
        levels.add(level)
        cell = re.search(rf'data-session="{r["session_id"]}".*?<td class="metric ([a-z]*)" '
                         r'data-metric="reproj_rmse_px">', text, re.S)
        assert cell.group(1) == level, (r["session_id"], value)
    assert len(levels) >= 2  # the seed gives cells on both sides of a limit
    # across versions: the median of each version's sessions
    for v in (1, 2):
        values = [x for x in cat.table("sessions", v)["qa_fit_residual_mm"].to_pylist()
                  if x is not None]
        median = statistics.median(values)
        assert f"version {v}: median {median:.3g}" in text
    # the versions table links version 1's page once it is written, by tag too
    cat.tag(1, "first")
    assert main(["report", "--catalog", str(tmp_path / "cat"), "first"]) == 0
    assert (tmp_path / "cat" / "reports" / "b1" / "index.html").is_file()
    assert main(["report", "--catalog", str(tmp_path / "cat")]) == 0
    assert "../b1/index.html" in check_page(path).links


def test_a_catalog_written_before_reports_has_pages_without_pictures(tmp_path):
    """Rows without a build record of pictures (a migrated catalog, or these factory
    builds): the page says so, and a legacy ``pictures/<session>/`` folder is shown."""
    cat = _catalog(tmp_path / "cat")
    legacy = tmp_path / "cat" / "pictures" / "p01-mug-use-00"
    legacy.mkdir(parents=True)
    (legacy / "keypoints.png").write_bytes(b"\x89PNG")
    data = gather(cat, 1)
    by_id = {e.session_id: e for e in data.sessions}
    assert by_id["p01-mug-use-00"].pictures == {
        "keypoints.png": "pictures/p01-mug-use-00/keypoints.png"}
    assert by_id["p02-drill-use-00"].pictures == {}
    assert main(["report", "--catalog", str(tmp_path / "cat"), "1"]) == 0
    page = check_page(tmp_path / "cat" / "reports" / "b1" / "index.html")
    assert page.rows[0].images == ["../../pictures/p01-mug-use-00/keypoints.png"]
    assert "no pictures" in page.row_text("p02-drill-use-00")


def test_histogram_counts_every_value_and_draws_the_limits():
    m = QA_BY_NAME["reproj_rmse_px"]
    values = list(np.linspace(0.5, 3.0, 17))
    svg = histogram_svg(m, values, {"flag": 5.9, "fail": 8.0})
    counts = [int(c) for c in re.findall(r"<title>(\d+) session\(s\) in", svg)]
    assert sum(counts) == len(values)
    assert 'class="limit-flag"' in svg and 'class="limit-fail"' in svg
    assert "http" not in svg
    assert "no values" in histogram_svg(m, [], {})
    assert sum(int(c) for c in re.findall(r"<title>(\d+) session", histogram_svg(
        m, [2.0, 2.0], {}))) == 2  # all equal: one bar, no division by zero


def test_report_of_an_empty_or_missing_catalog_is_one_line_and_exit_2(tmp_path, capsys):
    gc.open(tmp_path / "empty", create=True)
    assert main(["report", "--catalog", str(tmp_path / "empty")]) == 2
    assert main(["report", "--catalog", str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"graspcap report: catalog {tmp_path / 'empty'} has no version yet"
    assert err[1].startswith(f"graspcap report: {tmp_path / 'nowhere'} is not a graspcap catalog")
    assert len(err) == 2 and not (tmp_path / "nowhere").exists()
    assert not (tmp_path / "empty" / "reports").exists()
