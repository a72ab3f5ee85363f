"""Valid fake stage outputs for catalog tests: rows and arrays made with numpy, fixed seeds."""

from __future__ import annotations

import zlib
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np
import pyarrow as pa

import graspcap.catalog as gc
from graspcap.catalog import BuildCommit, BuildInfo, ObjectMesh, SessionArrays
from graspcap.schemas.tables import FRAMES_SCHEMA
from graspcap.tasks.core.geometry import from_rotvec
from graspcap.tasks.hand.model import TEMPLATE_BONE_LENGTHS_M

OBJECT_VERTICES = {"mug": 40, "drill": 60, "bowl": 30}


def _pose(rng: np.random.Generator) -> np.ndarray:
    return from_rotvec(rng.normal(size=3) * 0.5, rng.normal(size=3) * 0.2)


def object_mesh(object_id: str) -> ObjectMesh:
    """A deterministic mesh per object id (vertex count from OBJECT_VERTICES)."""
    rng = np.random.default_rng(sum(object_id.encode()))
    n = OBJECT_VERTICES[object_id]
    return ObjectMesh(rng.normal(size=(n, 3)).astype(np.float32) * 0.05,
                      rng.integers(0, n, size=(2 * n, 3)).astype(np.int32))


def session_row(session_id: str, rng: np.random.Generator, *, status: str = "ok",
                build_id: str = "b1") -> dict:
    """One sessions row; ids look like ``p01-mug-use-00`` (participant-object-intent-n)."""
    participant, object_id, intent, _ = session_id.split("-")
    failed = status == "failed"
    row = {
        "session_id": session_id, "participant": participant, "object_id": object_id,
        "intent": intent, "hand": "right", "status": status,
        "error": "register_object: no platter plane in stage1/depth.png" if failed else None,
        "keypoint_backend": None if failed else "openpose_json",
        "keypoint_frames_detected": None if failed else int(rng.integers(10, 40)),
        "steady_from": None if failed else int(rng.integers(0, 30)),
        "hand_scale": None if failed else float(rng.uniform(0.9, 1.1)),
        "joint_angles_rad": None if failed else rng.uniform(-1, 1, 20),
        "joints_w": None if failed else rng.normal(size=(21, 3)) * 0.05,
        "joints_fit_w": None if failed else rng.normal(size=(21, 3)) * 0.05,
        "input_digest": f"{rng.integers(2**62):x}", "code_version": "0.1.0",
        "build_id": build_id, "config_digest": "c" * 64,
    }
    for name in ("T_w_o_stage1", "T_adj", "T_w_p", "T_turntable_o_scan"):
        row[name] = None if failed else _pose(rng)
    for name in ("qa_reproj_rmse_px", "qa_inlier_ratio", "qa_crosscheck_mm",
                 "qa_registration_rmse_mm", "qa_fit_residual_mm", "qa_penetration_max_mm",
                 "qa_penetration_mean_mm", "qa_contact_agreement", "qa_contact_coverage",
                 "qa_window_outlier_share", "qa_crosscheck_camera_deg", "qa_rgbd_discrepancy_mm",
                 "qa_fit_contact_agreement"):
        row[name] = None if failed else float(rng.uniform(0, 2))
    # no draw: the rng's stream stays as it was before format 4
    row["qa_flags"] = None if failed else (["inlier ratio 0.900 < 0.915"]
                                           if status == "flagged" else [])
    row["qa_notes"] = None if failed else (
        ["estimate_adjustment: ambiguous (the pose nearest stage 1 kept)"]
        if object_id == "mug" else [])
    # format 7: the hand's bone lengths (no draw either)
    row["hand_shape"] = None if failed else (row["hand_scale"] * TEMPLATE_BONE_LENGTHS_M).tolist()
    return row


def validity_columns(count: int) -> dict[str, list]:
    """Format 6's per-frame validity of ``count`` frames, a fixed pattern (no draw): frame 1
    of every 4 interpolated with an unused detection; frame 1 of every 3 with depth
    disagreeing, frame 2 of every 3 with an object the depth cannot judge."""
    i = np.arange(count)
    interp, off, hidden = i % 4 == 1, i % 3 == 1, i % 3 == 2
    obj = [None if h else not o for h, o in zip(hidden, off, strict=True)]
    return {
        "camera_reason": ["interpolated from its neighbours: 2 keypoints detected" if k
                          else None for k in interp],
        "hand_used": [not k for k in interp],
        "hand_reason": ["0 of 2 detected keypoints inliers (need 6)" if k else None
                        for k in interp],
        "object_supported": obj,
        "object_reason": [None if v else "too few object pixels visible: 3 of 90 outside the "
                          "hand (need 50; the hand covers it)" if v is None
                          else "depth disagrees: median 21 mm, 4% of 120 pixels within 10 mm"
                          for v in obj],
        "object_depth_agreement": [None if v is None else (0.96 if v else 0.04) for v in obj],
    }


def frame_rows(session_id: str, rng: np.random.Generator, count: int, *,
               build_id: str = "b1") -> dict[str, np.ndarray | list]:
    """``count`` frames as columns (poses (count, 4, 4), joints (count, 21, 3), ...)."""
    return {
        "session_id": [session_id] * count, "frame": np.arange(count, dtype=np.int64) + 5,
        "T_w_c": np.stack([_pose(rng) for _ in range(count)]),
        "camera_solved": np.arange(count) % 4 != 1,  # no draw: the rng's stream stays as it was
        **validity_columns(count),
        "T_c_o": np.stack([_pose(rng) for _ in range(count)]),
        "T_c_p": np.stack([_pose(rng) for _ in range(count)]),
        "joints_2d_px": rng.uniform(0, 640, (count, 21, 2)),
        "keypoint_conf": rng.uniform(0, 1, (count, 21)),
        "joints_c": rng.normal(size=(count, 21, 3)),
        "reproj_err_px": rng.uniform(0, 3, (count, 21)),
        "build_id": [build_id] * count,
    }


def session_arrays(object_id: str, rng: np.random.Generator) -> SessionArrays:
    n = OBJECT_VERTICES[object_id]
    return SessionArrays(
        contact=rng.uniform(0, 1, n).astype(np.float32), observed=rng.uniform(size=n) > 0.2,
        hand_vertices=rng.normal(size=(25, 3)).astype(np.float32) * 0.05,
        hand_faces=rng.integers(0, 25, size=(40, 3)).astype(np.int32),
        joints=rng.normal(size=(21, 3)) * 0.05)


class GeneratedArrays(Mapping[str, SessionArrays]):
    """Each session's arrays made afresh on every read, as a build's work-area spill reads them
    (``flows.workarea.Spill``, without the disk): the contact map of its object's mesh and a
    hand mesh of ``vertices`` vertices and ``faces`` faces, seeded by the session id.
    ``objects``: the object id by session id."""

    def __init__(self, objects: Mapping[str, str], vertices: int, faces: int):
        self.objects, self.vertices, self.faces = dict(objects), vertices, faces

    def __getitem__(self, sid: str) -> SessionArrays:
        rng = np.random.default_rng(zlib.crc32(sid.encode()))
        n, v = OBJECT_VERTICES[self.objects[sid]], self.vertices
        return SessionArrays(
            contact=rng.uniform(0, 1, n).astype(np.float32), observed=np.ones(n, bool),
            hand_vertices=rng.normal(size=(v, 3)).astype(np.float32),
            hand_faces=rng.integers(0, v, size=(self.faces, 3)).astype(np.int32),
            joints=rng.normal(size=(21, 3)))

    def __iter__(self) -> Iterator[str]:
        return iter(self.objects)

    def __len__(self) -> int:
        return len(self.objects)


def make_build(session_ids: list[str], *, seed: int, build_id: str = "b1", frames: int = 3,
               failed: tuple[str, ...] = (), remove: tuple[str, ...] = ()) -> BuildCommit:
    """A valid BuildCommit for ``session_ids`` (those in ``failed`` fail, without arrays)."""
    rng = np.random.default_rng(seed)
    rows, cols, arrays = [], [], {}
    for sid in session_ids:
        status = "failed" if sid in failed else "ok"
        rows.append(session_row(sid, rng, status=status, build_id=build_id))
        if status != "failed":
            cols.append(frame_rows(sid, rng, frames, build_id=build_id))
            arrays[sid] = session_arrays(rows[-1]["object_id"], rng)
    frame_cols = {k: np.concatenate([c[k] for c in cols]) if cols else []
                  for k in FRAMES_SCHEMA.names}
    objects = {r["object_id"]: object_mesh(r["object_id"]) for r in rows
               if r["status"] != "failed"}
    info = BuildInfo(build_id=build_id, code_version="0.1.0", config_digest="c" * 64,
                     parameters={"seed": seed})
    return BuildCommit(build=info, sessions=rows, frames=frame_cols, session_arrays=arrays,
                       object_meshes=objects, remove=remove)


# --- a small committed catalog to damage (tests/catalog/test_catalog_damage*.py) ----------

DAMAGE_IDS = [["p01-mug-use-00", "p02-drill-use-00"], ["p03-bowl-use-00"], ["p04-mug-use-00"]]
DATA_TABLES = ("sessions", "frames", "builds")


def commit_three(root: Path) -> gc.Catalog:
    """A new catalog at ``root`` with three committed versions (:data:`DAMAGE_IDS`)."""
    cat = gc.open(root, create=True)
    for i, ids in enumerate(DAMAGE_IDS):
        assert cat.commit(make_build(ids, seed=i + 1, build_id=f"b{i + 1}")) == i + 1
    return cat


def snapshot(cat: gc.Catalog, version: int) -> dict[str, pa.Table]:
    """The data tables of ``version``."""
    return {name: cat.table(name, version) for name in DATA_TABLES}


def log_entry(root: Path, table: str, n: int) -> Path:
    """The Delta log entry ``n`` of ``table``."""
    return root / "tables" / table / "_delta_log" / f"{n:020d}.json"


def delta_logs(root: Path) -> list[str]:
    """Every Delta log file of the catalog: what a writer would add to."""
    return sorted(str(p.relative_to(root)) for p in root.glob("tables/*/_delta_log/*"))


def assert_reads_back(root: Path, snapshots: dict[int, dict[str, pa.Table]]) -> None:
    """Every version of ``snapshots`` reads back identically from a fresh ``open``."""
    fresh = gc.open(root)
    for version, tables in snapshots.items():
        for name, table in snapshot(fresh, version).items():
            assert table.equals(tables[name]), (version, name)
