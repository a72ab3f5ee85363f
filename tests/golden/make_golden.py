"""Regenerate the golden catalogs under tests/golden/ (checked in with this script).

    .venv/bin/python tests/golden/make_golden.py [--formats 1 2 3 4 5 6]

- ``catalog_v0/``: the stamp of a catalog of format 0 (never released, no migration leads from
  it), for the "rebuild it" error. A few hundred bytes.
- ``catalog_v<k>.tar.gz`` for every older format ``k`` a migration leads from: a real catalog
  of format ``k``: ``build()`` committed as version 1 and tagged ``golden``, written by today's
  commit code with format ``k``'s differences (``COLUMNS_ADDED`` after ``k`` left out of the
  schemas; Delta tables without ``DELTA_TABLE_PROPERTIES`` for format 1; stamp and versions row
  saying ``k``; docs/data_changelog.md). ``catalog_v2.tar.gz`` was first written by the code of
  format 2 itself (before format 3's columns existed), ``catalog_v3.tar.gz`` by the code of
  format 3 (before ``frames.camera_solved``, ``sessions.qa_flags`` and ``qa_notes``),
  ``catalog_v4.tar.gz`` by the code of format 4 (Zarr groups without format 5's manifests and
  all-fill chunks, which this script now writes: only the columns are compared),
  ``catalog_v5.tar.gz`` by this script when format 6 came (before the per-frame validity
  columns), ``catalog_v6.tar.gz`` by this script when format 7 came (before
  ``sessions.hand_shape``, the audit columns of ``builds``, ``versions.state`` and the
  ``publications`` table);
  ``test_golden_script_still_writes_...`` checks that this script still writes the same
  columns. Unpacked one is ~86 KB in 33 files
  (Delta logs, and Parquet footers repeating the schema's docs), packed ~15-20 KB. Tests unpack
  them into a temporary folder: opening fails naming ``graspcap catalog migrate``, migrating
  makes them readable.

``build()`` and ``expected()`` describe the tiny build (one session, two frames, a 4-vertex
object), nothing random; ``--unpacked DIR`` also writes the catalogs unpacked for inspection.
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import io
import json
import shutil
import tarfile
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pyarrow as pa

import graspcap.catalog as gc
from graspcap.catalog.commit import commit_build
from graspcap.catalog.delta import create_tables
from graspcap.catalog.layout import CatalogLayout, write_format_file
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION, DELTA_TABLE_PROPERTIES, TABLE_SCHEMAS

HERE = Path(__file__).resolve().parent
SESSION = "p01-cube-use-00"
COLUMNS_ADDED: dict[int, dict[str, tuple[str, ...]]] = {
    2: {"sessions": ("keypoint_backend", "keypoint_frames_detected")},
    3: {"sessions": ("qa_window_outlier_share", "qa_crosscheck_camera_deg",
                     "qa_rgbd_discrepancy_mm", "qa_fit_contact_agreement")},
    4: {"frames": ("camera_solved",), "sessions": ("qa_flags", "qa_notes")},
    6: {"frames": ("camera_reason", "hand_used", "hand_reason", "object_supported",
                   "object_reason", "object_depth_agreement")},
    7: {"sessions": ("hand_shape",),
        "builds": ("audit_passed", "audit_reasons", "audit_json"), "versions": ("state",)},
}
"""``{format: {table: columns that format added}}`` (docs/data_changelog.md): a catalog of an
older format lacks them."""
TABLES_ADDED: dict[int, tuple[str, ...]] = {7: ("publications",)}
"""``{format: tables that format added}``: a catalog of an older format has none of them."""
FORMAT_2_COLUMNS = COLUMNS_ADDED[2]
GOLDEN_FORMATS = (1, 2, 3, 4, 5, 6)
"""Older formats with a golden catalog (every one ``graspcap catalog migrate`` leads from)."""


def archive(fmt: int) -> Path:
    """The golden catalog of format ``fmt``."""
    return HERE / f"catalog_v{fmt}.tar.gz"


def added_after(fmt: int) -> dict[str, tuple[str, ...]]:
    """``{table: columns}`` added by the formats after ``fmt`` (a format-``fmt`` catalog lacks
    them)."""
    out: dict[str, tuple[str, ...]] = {}
    for k, tables in COLUMNS_ADDED.items():
        if k > fmt:
            for name, cols in tables.items():
                out[name] = out.get(name, ()) + cols
    return out


def expected() -> dict:
    """The golden build's content, computed (nothing random)."""
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.2, 0.5]
    return {
        "T": T, "joints": np.arange(63, dtype=float).reshape(21, 3) * 1e-3,
        "contact": np.linspace(0, 1, 4, dtype=np.float32),
        "observed": np.array([True, True, False, True]),
        "vertices": np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], np.float32),
        "faces": np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], np.int32),
    }


def build() -> gc.BuildCommit:
    e = expected()
    session = {
        "session_id": SESSION, "participant": "p01", "object_id": "cube", "intent": "use",
        "hand": "right", "status": "ok", "error": None, "steady_from": 3,
        "keypoint_backend": "openpose_json", "keypoint_frames_detected": 2,
        "T_w_o_stage1": e["T"], "T_adj": e["T"], "T_w_p": e["T"], "T_turntable_o_scan": e["T"],
        "hand_scale": 1.0, "joint_angles_rad": np.zeros(20), "joints_w": e["joints"],
        "hand_shape": np.linspace(0.016, 0.045, 20),
        "joints_fit_w": e["joints"], "input_digest": "0" * 64, "code_version": "golden",
        "build_id": "golden-1", "config_digest": "1" * 64,
        **dict.fromkeys(["qa_reproj_rmse_px", "qa_inlier_ratio", "qa_crosscheck_mm",
                         "qa_registration_rmse_mm", "qa_fit_residual_mm",
                         "qa_penetration_max_mm", "qa_penetration_mean_mm",
                         "qa_contact_agreement", "qa_contact_coverage",
                         *COLUMNS_ADDED[3]["sessions"]], 0.5),
        "qa_flags": [], "qa_notes": ["register_object: symmetric object, registration "
                                     "ambiguous (resolved by estimate_adjustment)"],
    }
    session = {k: v for k, v in session.items() if k in TABLE_SCHEMAS["sessions"].names}
    frames = {
        "session_id": [SESSION] * 2, "frame": np.array([3, 4]), "T_w_c": np.stack([e["T"]] * 2),
        "camera_solved": [True, False],
        "camera_reason": [None, "interpolated from its neighbours: no detection"],
        "hand_used": [True, False], "hand_reason": [None, "no detection"],
        "object_supported": [True, None],
        "object_reason": [None, "too few object pixels visible: 12 of 240 outside the hand "
                                "(need 50; the hand covers it)"],
        "object_depth_agreement": [0.9, None],
        "T_c_o": np.stack([e["T"]] * 2), "T_c_p": np.stack([e["T"]] * 2),
        "joints_2d_px": np.full((2, 21, 2), 320.0), "keypoint_conf": np.ones((2, 21)),
        "joints_c": np.stack([e["joints"]] * 2), "reproj_err_px": np.zeros((2, 21)),
        "build_id": ["golden-1"] * 2,
    }
    arrays = gc.SessionArrays(contact=e["contact"], observed=e["observed"],
                              hand_vertices=e["vertices"], hand_faces=e["faces"],
                              joints=e["joints"])
    return gc.BuildCommit(
        build=gc.BuildInfo(build_id="golden-1", code_version="golden", config_digest="1" * 64),
        sessions=[session], frames=frames, session_arrays={SESSION: arrays},
        object_meshes={"cube": gc.ObjectMesh(e["vertices"], e["faces"])})


@contextmanager
def schemas_of(fmt: int) -> Iterator[None]:
    """Within: ``TABLE_SCHEMAS`` without the columns added after format ``fmt`` (the writer
    code reads it at call time), so today's create and commit code writes format ``fmt``'s
    columns."""
    saved = dict(TABLE_SCHEMAS)
    for k, names in TABLES_ADDED.items():
        for name in names if k > fmt else ():
            del TABLE_SCHEMAS[name]
    for name, cols in added_after(fmt).items():
        schema = TABLE_SCHEMAS[name]
        TABLE_SCHEMAS[name] = pa.schema([f for f in schema if f.name not in cols],
                                        metadata=schema.metadata)
    try:
        yield
    finally:
        TABLE_SCHEMAS.update(saved)


def write_golden(root: Path, fmt: int) -> None:
    """A format-``fmt`` catalog at ``root`` holding ``build()`` as version 1, tagged
    ``golden``."""
    layout = CatalogLayout(root.resolve())
    layout.root.mkdir(parents=True)
    commit = build()
    dropped = added_after(fmt)
    rows = [{k: v for k, v in r.items() if k not in dropped.get("sessions", ())}
            for r in commit.sessions]
    frames = {k: v for k, v in commit.frames.items() if k not in dropped.get("frames", ())}
    with schemas_of(fmt):
        # format 1: Delta's default table properties
        create_tables(layout, properties=None if fmt == 1 else DELTA_TABLE_PROPERTIES)
        write_format_file(layout, fmt)
        commit_build(layout, dataclasses.replace(commit, sessions=rows, frames=frames),
                     lock_timeout_s=10.0, format_version=fmt)
        gc.Catalog(layout).tag(1, "golden")  # Catalog() skips the format check open() makes


def write_v1(root: Path) -> None:
    """A format-1 catalog at ``root`` (``write_golden(root, 1)``)."""
    write_golden(root, 1)


def pack(root: Path, archive: Path) -> None:
    """``root`` as a .tar.gz with fixed owners and times (sorted members)."""
    with (archive.open("wb") as raw,
          gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, compresslevel=9) as gz,
          tarfile.open(fileobj=gz, mode="w") as tar):
        for path in sorted(root.rglob("*")):
            if path.name == ".lock":
                continue
            info = tar.gettarinfo(str(path), str(path.relative_to(root)))
            info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
            if path.is_file():
                tar.addfile(info, io.BytesIO(path.read_bytes()))
            else:
                tar.addfile(info)


def unpack(archive: Path, dest: Path) -> Path:
    """Unpack a golden archive into ``dest`` (created); return ``dest``."""
    dest.mkdir(parents=True)
    with tarfile.open(archive) as tar:
        tar.extractall(dest, filter="data")
    return dest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--formats", type=int, nargs="+", default=list(GOLDEN_FORMATS),
                        help="which golden catalogs to write again (their Delta logs and file "
                             "names change, their content does not)")
    parser.add_argument("--unpacked", type=Path, help="also write them unpacked here")
    args = parser.parse_args()
    for fmt in args.formats:
        if fmt not in GOLDEN_FORMATS or fmt > CATALOG_FORMAT_VERSION:
            parser.error(f"format {fmt} has no golden catalog (formats {GOLDEN_FORMATS})")
        if args.unpacked:
            write_golden(args.unpacked / f"v{fmt}", fmt)
        with tempfile.TemporaryDirectory() as tmp:
            write_golden(Path(tmp) / f"v{fmt}", fmt)
            pack(Path(tmp) / f"v{fmt}", archive(fmt))
    v0 = HERE / "catalog_v0"
    shutil.rmtree(v0, ignore_errors=True)
    v0.mkdir()
    stamp = {"format": "graspcap-catalog", "format_version": 0,
             "created_utc": "2026-01-01T00:00:00+00:00"}
    (v0 / "catalog.json").write_text(json.dumps(stamp, indent=2) + "\n")


if __name__ == "__main__":
    main()
