"""Regenerate the golden catalogs under tests/golden/ (checked in with this script).

    .venv/bin/python tests/golden/make_golden.py

- ``catalog_v0/``: the stamp of a catalog of format 0 (never released, no migration leads from
  it), for the "rebuild it" error. A few hundred bytes.
- ``catalog_v1.tar.gz``: a real catalog of format 1, the format before the current one:
  ``build()`` committed as version 1 and tagged ``golden``, written by today's commit code with
  format 1's differences (Delta tables without ``DELTA_TABLE_PROPERTIES``, no
  ``FORMAT_2_COLUMNS``, stamp and versions row saying 1; docs/data_changelog.md). Unpacked it
  is ~86 KB in 33 files (Delta logs, and Parquet footers repeating the schema's docs), packed
  ~15 KB. Tests unpack it into a temporary
  folder: opening fails naming ``graspcap catalog migrate``, migrating makes it readable.

``build()`` and ``expected()`` describe the tiny build (one session, two frames, a 4-vertex
object), nothing random; ``--v1 DIR`` also writes the format-1 catalog unpacked for inspection.
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
from graspcap.schemas.tables import TABLE_SCHEMAS

HERE = Path(__file__).resolve().parent
SESSION = "p01-cube-use-00"
FORMAT_2_COLUMNS = {"sessions": ("keypoint_backend", "keypoint_frames_detected")}
"""Columns format 2 added (docs/data_changelog.md): a format-1 catalog's tables lack them."""


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
        "joints_fit_w": e["joints"], "input_digest": "0" * 64, "code_version": "golden",
        "build_id": "golden-1", "config_digest": "1" * 64,
        **dict.fromkeys(["qa_reproj_rmse_px", "qa_inlier_ratio", "qa_crosscheck_mm",
                         "qa_registration_rmse_mm", "qa_fit_residual_mm",
                         "qa_penetration_max_mm", "qa_penetration_mean_mm",
                         "qa_contact_agreement", "qa_contact_coverage"], 0.5),
    }
    frames = {
        "session_id": [SESSION] * 2, "frame": np.array([3, 4]), "T_w_c": np.stack([e["T"]] * 2),
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
def format_1_schemas() -> Iterator[None]:
    """Within: ``TABLE_SCHEMAS`` without ``FORMAT_2_COLUMNS`` (the writer code reads it at call
    time), so today's create and commit code writes format 1's columns."""
    saved = dict(TABLE_SCHEMAS)
    for name, cols in FORMAT_2_COLUMNS.items():
        schema = TABLE_SCHEMAS[name]
        TABLE_SCHEMAS[name] = pa.schema([f for f in schema if f.name not in cols],
                                        metadata=schema.metadata)
    try:
        yield
    finally:
        TABLE_SCHEMAS.update(saved)


def write_v1(root: Path) -> None:
    """A format-1 catalog at ``root`` holding ``build()`` as version 1, tagged ``golden``."""
    layout = CatalogLayout(root.resolve())
    layout.root.mkdir(parents=True)
    commit = build()
    rows = [{k: v for k, v in r.items() if k not in FORMAT_2_COLUMNS["sessions"]}
            for r in commit.sessions]
    with format_1_schemas():
        create_tables(layout, properties=None)  # format 1: Delta's default table properties
        write_format_file(layout, 1)
        commit_build(layout, dataclasses.replace(commit, sessions=rows), lock_timeout_s=10.0,
                     format_version=1)
        gc.Catalog(layout).tag(1, "golden")  # Catalog() skips the format check open() makes


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
    parser.add_argument("--v1", type=Path, help="also write the format-1 catalog here")
    args = parser.parse_args()
    if args.v1:
        write_v1(args.v1)
    with tempfile.TemporaryDirectory() as tmp:
        write_v1(Path(tmp) / "v1")
        pack(Path(tmp) / "v1", HERE / "catalog_v1.tar.gz")
    v0 = HERE / "catalog_v0"
    shutil.rmtree(v0, ignore_errors=True)
    v0.mkdir()
    stamp = {"format": "graspcap-catalog", "format_version": 0,
             "created_utc": "2026-01-01T00:00:00+00:00"}
    (v0 / "catalog.json").write_text(json.dumps(stamp, indent=2) + "\n")


if __name__ == "__main__":
    main()
