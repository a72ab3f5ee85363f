"""Write-audit-publish in a real build: a build whose audit fails commits a staged version,
readers stay on the published one, status and the report say why; publish moves readers."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import graspcap.catalog as gc
from graspcap.flows.build import build_dataset
from graspcap.flows.commands import status_text
from tests.flow_fixtures import PRESET, copy_catalog

STRICT = {"tolerated_sessions": 0}
"""Default gates without the small-catalog allowance: one failed session of three fails."""


def _broken_copy(synth_root: Path, dest: Path) -> Path:
    """A copy of the first fixture session as ``broken-one`` whose manifest lacks a field."""
    first = sorted(p for p in synth_root.iterdir() if (p / "session.json").exists())[0]
    bad = dest / "broken"
    shutil.copytree(first, bad)
    manifest = json.loads((bad / "session.json").read_text())
    manifest["session_id"] = "broken-one"
    del manifest["depth_scale_m"]
    (bad / "session.json").write_text(json.dumps(manifest))
    return dest


def test_a_build_whose_audit_fails_is_staged_until_published(warm, synth_root, tmp_path):
    catalog = copy_catalog(warm[0], tmp_path / "catalog")
    more = _broken_copy(synth_root, tmp_path / "more")
    report = build_dataset([synth_root, more], catalog, PRESET, build_id="nightly",
                           gates=STRICT)
    assert report.catalog_version == 2 and set(report.failed) == {"broken-one"}
    assert report.publication["state"] == "staged"
    assert report.publication["published_version"] == 1
    audit = report.publication["audit"]
    assert not audit["passed"] and audit["compared_to"] == 1
    assert audit["reasons"] == [
        "failed share: 33.3% of sessions failed, 0.0% in published version 1 (rise 33.3% > "
        "max_failed_share_rise 10.0%)"]
    summary = report.summary()
    assert "  staged: AUDIT FAILED; readers read version 1" in summary
    assert "    publish it anyway: graspcap catalog publish 2; drop it: graspcap catalog " \
           "reject 2" in summary
    # readers stay on version 1; version 2 reads by number
    cat = gc.open(catalog)
    assert cat.table("sessions").num_rows == 2 and cat.table("sessions", 2).num_rows == 3
    assert gc.GraspDataset(catalog).version == 1
    # status and the report page say it
    status = status_text(catalog)
    assert status.splitlines()[0].endswith(
        "latest version 2 (staged); published version 1 (readers' default)")
    assert "build nightly (version 2, staged): 0 added, 0 changed, 2 unchanged, 1 failed" \
        in status
    assert "    AUDIT FAILED against published version 1:\n      failed share: 33.3%" in status
    assert "`graspcap catalog publish 2`" in status
    page = Path(report.report_page).read_text()
    assert "<b>staged</b>: audit FAILED against published version 1" in page

    # the next build plans against the staged version; the broken session's load_session
    # runs again and fails as the catalog already records (same error, same inputs and
    # configs): nothing new, no version (issue 20 item 6), readers still on version 1
    again = build_dataset([synth_root, more], catalog, PRESET, build_id="again", gates=STRICT)
    assert (again.previous_version, again.catalog_version) == (2, None)
    assert sorted(again.unchanged) == sorted(report.unchanged)
    assert set(again.failed) == {"broken-one"}
    assert again.publication["published_version"] == 1

    assert gc.open(catalog).publish(2, "a broken capture is expected")
    assert gc.open(catalog).table("sessions").num_rows == 3
    status = status_text(catalog)
    assert "build nightly (version 2, published)" in status
    assert "readers read it by default" in status.splitlines()[0]
