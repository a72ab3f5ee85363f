"""Regenerate the golden catalogs under tests/golden/ (checked in with this script).

    .venv/bin/python tests/golden/make_golden.py

- ``catalog_v0/``: the stamp of a catalog of format 0 (older than any reader here), for the
  "names the way forward" error. A few hundred bytes.

``build()`` and ``expected()`` describe one tiny format-1 build (one session, two frames, a
4-vertex object); tests write it to a temporary catalog. A full format-1 catalog is not checked
in: its Delta logs and Parquet footers (schema metadata repeated per file) come to ~86 KB in 33
files; ``--v1 DIR`` writes one for inspection.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

import graspcap.catalog as gc

HERE = Path(__file__).resolve().parent
SESSION = "p01-cube-use-00"


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


def write_v1(root: Path) -> gc.Catalog:
    """A format-1 catalog at ``root`` holding ``build()`` as version 1, tagged ``golden``."""
    cat = gc.open(root, create=True)
    cat.commit(build())
    cat.tag(1, "golden")
    return cat


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--v1", type=Path, help="also write a format-1 catalog here")
    args = parser.parse_args()
    if args.v1:
        write_v1(args.v1)
    v0 = HERE / "catalog_v0"
    shutil.rmtree(v0, ignore_errors=True)
    v0.mkdir()
    stamp = {"format": "graspcap-catalog", "format_version": 0,
             "created_utc": "2026-01-01T00:00:00+00:00"}
    (v0 / "catalog.json").write_text(json.dumps(stamp, indent=2) + "\n")


if __name__ == "__main__":
    main()
