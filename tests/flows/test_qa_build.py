"""The QA gate in a build: qa_metrics decides each row's status, the pictures are stored by
content under ``<catalog>/pictures/`` and shown on the build's report page
(``<catalog>/reports/<build_id>/index.html``), a QA-failed session is a failed row with its
reasons (the build does not crash), ``graspcap status`` says where its page is, and
``graspcap report`` writes an older version's page, whose pictures are still there."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import trimesh

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.flows.rows import QA_COLUMNS
from graspcap.schemas.qa import qa_columns
from graspcap.tasks.outputs.drawing import decode_png
from tests.flow_fixtures import PRESET, copy_catalog, executions
from tests.report_html import check_page

PICTURES = ["contact.ply", "contact.png", "keypoints.png", "reprojection.png", "strip.png"]


def test_pictures_are_written_and_rows_carry_the_qa_verdict(warm):
    catalog, report = warm
    cat = gc.open(catalog)
    rows = cat.table("sessions").to_pylist()
    by_id = {s.session_id: s for s in report.sessions}
    for r in rows:
        files = by_id[r["session_id"]].pictures
        assert sorted(files) == PICTURES
        keypoints = decode_png((catalog / files["keypoints.png"]).read_bytes())
        contact = decode_png((catalog / files["contact.png"]).read_bytes())
        reprojection = decode_png((catalog / files["reprojection.png"]).read_bytes())
        strip = decode_png((catalog / files["strip.png"]).read_bytes())
        assert keypoints.shape[0] > 100 and keypoints.shape[1] > keypoints.shape[0]
        assert contact.shape[1] > contact.shape[0] > 100
        assert reprojection.shape[0] >= 100 and reprojection.shape[1] > 100
        assert strip.shape[0] <= 160 and strip.shape[1] > 4 * strip.shape[0]  # 5 small frames
        mesh = trimesh.load(catalog / files["contact.ply"], file_type="ply", process=False)
        colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
        assert len(mesh.vertices) > 100 and len(np.unique(colours, axis=0)) > 3  # coloured
        assert r["status"] in ("ok", "flagged") and r["error"] is None
        for col in ("qa_reproj_rmse_px", "qa_penetration_max_mm", "qa_contact_agreement",
                    "qa_contact_coverage", "qa_window_outlier_share", "qa_crosscheck_camera_deg",
                    "qa_rgbd_discrepancy_mm", "qa_fit_contact_agreement"):
            assert r[col] is not None, col


def test_the_build_writes_a_report_page_of_every_session(warm):
    catalog, report = warm
    assert report.report_page == str(catalog.resolve() / "reports" / "warm" / "index.html")
    assert f"report: {report.report_page}" in report.summary()
    page = check_page(Path(report.report_page))  # links resolve, no URL, failed first
    rows = gc.open(catalog).table("sessions").to_pylist()
    assert sorted(r.session_id for r in page.rows) == sorted(r["session_id"] for r in rows)
    for r in rows:
        (row,) = [x for x in page.rows if x.session_id == r["session_id"]]
        assert row.status == r["status"]
        files = next(s for s in report.sessions if s.session_id == r["session_id"]).pictures
        assert len(row.images) == 4 and len(row.links) == 5  # 4 thumbnails and the mesh
        assert {(Path(report.report_page).parent / x).resolve() for x in row.links} == {
            (catalog / f).resolve() for f in files.values()}
        for flag in r["qa_flags"]:
            assert flag in page.row_text(r["session_id"])
    assert page.plots == 2 * len(qa_columns())  # a histogram and a trend per metric
    assert page.limit_lines >= len(qa_columns())  # the flag limits drawn at least
    text = " ".join(page.text)
    assert "Timings" in text and "total" in text and "version 1" in text


def test_every_qa_column_holds_its_qa_report_metric(warm):
    """The ``qa_*`` columns (format 3: thirteen) are the QaReport's metrics of the row's
    session, null exactly where the report has none."""
    import pickle

    catalog, _ = warm
    reports = [pickle.loads(p.read_bytes())
               for p in (catalog / "work" / "results" / "qa_metrics").glob("*.pkl")]
    rows = gc.open(catalog).table("sessions").to_pylist()
    assert len(rows) == 2 and len(reports) >= 2
    assert len(QA_COLUMNS) == 13
    assert {f"qa_{n}" for n in QA_COLUMNS} == {c for c in rows[0] if c.startswith("qa_")} - {
        "qa_flags", "qa_notes"}  # format 4: the report's reasons (tests/flows/test_rows_qa_text.py)
    for r in rows:
        report = next(q for q in reports
                      if q.metrics["reproj_rmse_px"] == r["qa_reproj_rmse_px"])
        assert str(report.verdict) == r["status"]
        for name in QA_COLUMNS:
            assert r[f"qa_{name}"] == report.metrics.get(name), name
        for name in ("window_outlier_share", "crosscheck_camera_deg", "rgbd_discrepancy_mm",
                     "fit_contact_agreement"):
            assert name in report.metrics, name


def test_a_qa_failed_session_is_a_failed_row_with_its_reasons(warm, synth_root, tmp_path):
    from graspcap.catalog.export import export_version
    from graspcap.cli import main
    from graspcap.flows.commands import status_text

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    strict = {"reproj_rmse_px": {"flag": 0.0, "fail": 0.01},
              "contact_coverage": {"flag": 1.01, "fail": 0.0}}  # a flag with its reason too
    report = build_dataset([synth_root], catalog, PRESET, overrides={"qa_metrics": strict},
                           build_id="strict-qa")
    assert {st for _, st in executions(catalog, "strict-qa")} == {"qa_metrics", "pictures"}
    rows = gc.open(catalog).table("sessions").to_pylist()
    assert rows and all(r["status"] == "failed" for r in rows)
    for r in rows:
        assert r["error"].startswith("qa_metrics: reprojection RMSE ")
        assert "> 0.01 px" in r["error"]
        assert r["T_w_p"] is not None  # the results stay, for a person to look at
        assert any(f.startswith("contact-map coverage ") for f in r["qa_flags"])
    assert all(s.status == "failed" and s.error for s in report.sessions)
    text = status_text(catalog)
    assert text.count(f"failed; pictures and reasons: {report.report_page}") == len(rows)

    # the new version's page: every session failed, with its error and its flags
    page = check_page(Path(report.report_page))
    assert {r.status for r in page.rows} == {"failed"} and len(page.rows) == len(rows)
    for r in rows:
        shown = page.row_text(r["session_id"])
        assert all(line in shown for line in r["error"].splitlines()[1:]) and r["qa_flags"]
        assert all(flag in shown for flag in r["qa_flags"])
    # new pictures (the verdict and reasons are written on them), the old ones kept
    old = {s.session_id: s.pictures for s in warm[1].sessions}
    for s in report.sessions:
        assert s.pictures["keypoints.png"] != old[s.session_id]["keypoints.png"]
        assert all((catalog / f).is_file() for f in old[s.session_id].values())

    # version 1's page again, from the command line: its own (older) pictures
    shutil.rmtree(catalog / "reports" / "warm")
    assert main(["report", "--catalog", str(catalog), "1"]) == 0
    again = check_page(catalog / "reports" / "warm" / "index.html")
    links = {(catalog / "reports" / "warm" / x).resolve() for x in again.links
             if "pictures/" in x}
    assert links == {(catalog / f).resolve() for p in old.values() for f in p.values()}
    assert {r.status for r in again.rows} <= {"ok", "flagged"}
    assert main(["report", "--catalog", str(catalog), "7"]) == 2  # no such version

    # the export carries the version's pictures and its page
    out = export_version(gc.open(catalog), 1, tmp_path / "export")
    exported = check_page(out.out / "report.html")
    assert len(exported.rows) == len(old)
    for sid, files in old.items():
        folder = out.out / "pictures" / sid
        assert sorted(p.name for p in folder.iterdir()) == PICTURES
        for name, rel in files.items():
            assert (folder / name).read_bytes() == (catalog / rel).read_bytes()


def test_rows_from_before_format_3_get_the_new_qa_columns_from_cached_results(
        warm, synth_root, tmp_path):
    """A migrated format-2 catalog's rows have null format-3 QA columns; the next build fills
    them in without running a stage (the QaReports are in the work area)."""
    import pyarrow as pa

    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    cat = gc.open(catalog)
    filled = cat.table("sessions")
    old = filled
    new_cols = ["qa_window_outlier_share", "qa_crosscheck_camera_deg", "qa_rgbd_discrepancy_mm",
                "qa_fit_contact_agreement"]
    for col in new_cols:
        i = old.schema.get_field_index(col)
        old = old.set_column(i, old.schema.field(i), pa.nulls(old.num_rows, old.schema[i].type))
    v = cat.commit(gc.BuildCommit(gc.BuildInfo("pre-format-3", "old", "x" * 64), sessions=old,
                                  frames=cat.table("frames")))
    assert all(cat.table("sessions", v)[c].null_count == old.num_rows for c in new_cols)
    report = build_dataset([synth_root], catalog, PRESET, build_id="fill3")
    assert executions(catalog, "fill3") == []
    assert report.catalog_version == v + 1 and len(report.changed) == old.num_rows
    new = cat.table("sessions", v + 1).sort_by("session_id")
    filled = filled.sort_by("session_id")
    for col in new_cols:
        assert new[col].null_count == 0, col
        assert new[col].to_pylist() == filled[col].to_pylist(), col
    again = build_dataset([synth_root], catalog, PRESET, build_id="noop3")
    assert again.catalog_version is None and sorted(again.unchanged) == sorted(
        r["session_id"] for r in new.to_pylist())


def test_rows_carry_the_refined_hand_and_frames_propagate_it(warm):
    """The catalog's hand is stage 5's (pipeline.md: refine_grasp -> propagate_poses): the
    row's palm, angles and joints are the refinement's, and every frame's ``T_c_p`` is
    ``inv(T_w_c) @ T_w_p`` of that palm (and its ``T_c_o`` ``inv(T_w_c) @ T_adj @
    T_w_o_stage1``, where the object was tracked in the frame's depth too)."""
    import pickle

    import numpy as np

    catalog, _ = warm
    refined = [pickle.loads(p.read_bytes())
               for p in (catalog / "work" / "results" / "refine_grasp").glob("*.pkl")]
    fitted = [pickle.loads(p.read_bytes()).joints_fit_w
              for p in (catalog / "work" / "results" / "fit_hand").glob("*.pkl")]
    cat = gc.open(catalog)
    frames = cat.table("frames").to_pandas()
    rows = cat.table("sessions").to_pylist()
    moved = [not any(np.array_equal(f, np.reshape(r["joints_fit_w"], (21, 3))) for f in fitted)
             for r in rows]
    assert any(moved)  # the refinement moved a hand, so the fit would not pass for it
    for r in rows:
        joints = np.reshape(r["joints_fit_w"], (21, 3))
        ref = next(g for g in refined if np.array_equal(g.joints_w, joints))
        T_w_p = np.reshape(r["T_w_p"], (4, 4))
        assert np.array_equal(T_w_p, ref.T_w_p)
        assert np.array_equal(r["joint_angles_rad"], ref.angles_rad)
        mine = frames[frames.session_id == r["session_id"]]
        assert len(mine) > 10
        T_w_o = np.reshape(r["T_adj"], (4, 4)) @ np.reshape(r["T_w_o_stage1"], (4, 4))
        for T_w_c, T_c_p, T_c_o in zip(mine.T_w_c, mine.T_c_p, mine.T_c_o, strict=True):
            T_w_c, T_c_p = np.reshape(T_w_c, (4, 4)), np.reshape(T_c_p, (4, 4))
            np.testing.assert_allclose(T_w_c @ T_c_p, T_w_p, atol=1e-9)
            # the frame's object pose, tracked in its depth or not, sits on the same camera
            np.testing.assert_allclose(T_w_c @ np.reshape(T_c_o, (4, 4)), T_w_o, atol=1e-9)
