"""Stage results of one session -> catalog rows and arrays (no Prefect here).

Maps the results of ``tasks.pipeline.STAGES`` onto the contract columns of
``graspcap.schemas.tables``. The ``qa_metrics`` stage decides ``status`` (ok, flagged, or
failed with its reasons in ``error``) and fills the ``qa_*`` columns: a metric it could not
compute stays null; ``qa_flags`` and ``qa_notes`` hold its flag reasons and notes.
See ``docs/architecture.md``, "Orchestration".
"""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graspcap.catalog.commit import ObjectMesh, SessionArrays
from graspcap.schemas.qa import qa_columns
from graspcap.schemas.tables import Status
from graspcap.tasks.outputs.frame_validity import FrameValidity
from graspcap.tasks.outputs.qa_metrics import QaReport, qa_metrics

MANIFEST_MAX_BYTES = 1 << 20
"""A failed row reads its identity columns from a ``session.json`` up to this size."""
IDENTITY_COLUMNS = ("participant", "object_id", "intent", "hand")
LABEL_COLUMNS = ("participant", "object_id", "intent")
"""Identity columns no stage reads (``pipeline.LABEL_FIELDS``): taken from the current
``session.json`` (:func:`manifest_labels`), never from a cached stage result."""
QA_COLUMNS = tuple(m.name for m in qa_columns())
"""``qa_<name>`` columns of ``sessions``, filled from ``QaReport.metrics[<name>]``."""
FORMAT_3_QA = tuple(m.column for m in qa_columns() if m.column_format == 3)
NEWEST_COLUMNS = ("keypoint_backend", *FORMAT_3_QA, "qa_flags", "hand_shape")
"""``sessions`` columns formats 2, 3, 4 and 7 added: :func:`predates_columns` reads them."""


def predates_columns(row: Mapping[str, Any]) -> bool:
    """Whether a ``sessions`` row with results was written before format 2's, 3's, 4's or 7's
    columns existed (a migrated catalog's old rows): such a row has no keypoint backend, none
    of format 3's QA metrics (a row written since has ``qa_window_outlier_share`` whenever
    reconstruct_hand ran), no ``qa_flags`` (a row with results always has a list, empty or not)
    or no ``hand_shape`` (a row with results always has one). The build rewrites it, and its
    ``frames`` rows (format 4's ``camera_solved``), from the session's cached stage results."""
    return (row["keypoint_backend"] is None or all(row[c] is None for c in FORMAT_3_QA)
            or row["qa_flags"] is None or row.get("hand_shape") is None)


@dataclass(frozen=True)
class SessionRows:
    """One session's catalog content: its ``sessions`` row, ``frames`` rows and arrays."""

    session: dict[str, Any]
    frames: list[dict[str, Any]]
    arrays: SessionArrays | None
    object_id: str
    object_mesh: ObjectMesh | None


def _flat(a: Any) -> list[float] | None:
    return None if a is None else np.asarray(a, dtype=float).reshape(-1).tolist()


VALIDITY_COLUMNS = ("camera_reason", "hand_used", "hand_reason", "object_supported",
                    "object_reason", "object_depth_agreement")
"""``frames`` columns of format 6 filled from ``PosePropagation.validity`` (beside
``camera_solved``, which reconstruct_hand's ``pose_valid`` gives)."""


def validity_columns(validity: FrameValidity | None, j: int) -> dict[str, Any]:
    """Row ``j``'s :data:`VALIDITY_COLUMNS` (all null without a validity)."""
    if validity is None:
        return dict.fromkeys(VALIDITY_COLUMNS)
    return {c: getattr(validity, c)[j] for c in VALIDITY_COLUMNS}


def qa_report(results: Mapping[str, Any]) -> QaReport:
    """The session's QA verdict and metrics: the ``qa_metrics`` stage's result, or (when the
    DAG has no such stage) computed from the results that are there."""
    return results.get("qa_metrics") or qa_metrics(results)


def session_rows(results: Mapping[str, Any], *, labels: Mapping[str, str], input_digest: str,
                 code_version: str, build_id: str, config_digest: str) -> SessionRows:
    """Rows and arrays of a session whose stages all completed (``results`` by stage name).
    ``labels``: the session's ``participant``, ``object_id`` and ``intent`` from its current
    ``session.json`` (:func:`manifest_labels`): no stage reads them, so ``load_session``'s
    result does not hold them and a label edit re-writes the rows without running a stage."""
    from graspcap.tasks.hand.final import final_hand, final_pose

    session = results["load_session"]
    m = session.manifest
    detected = results["detect_keypoints"].summary()  # which backend, frames with a hand
    kp = results["detect_keypoints"].keypoints  # (n_frames, 21, 3)
    sfm = results["reconstruct_hand"]
    fit = results["fit_hand"]
    refined = results.get("refine_grasp")
    T_w_p, angles_rad, joints_hand_w = final_pose(fit, refined)
    T_w_o1 = results["register_object"].T_w_o
    T_adj = results["estimate_adjustment"].T_adj
    scan = results.get("register_scan")
    T_turntable_o = None if scan is None else scan.T_turntable_o_scan
    contact = results.get("build_contactmap")
    qa = qa_report(results)
    row = {
        "session_id": m.session_id, **{c: labels[c] for c in LABEL_COLUMNS},
        "hand": str(m.hand),
        "status": Status(qa.verdict).value, "error": qa.error,
        "keypoint_backend": str(detected["backend"]),
        "keypoint_frames_detected": int(detected["frames_with_hand"]),
        "steady_from": int(results["select_steady"].steady_from),
        "T_w_o_stage1": _flat(T_w_o1), "T_adj": _flat(T_adj), "T_w_p": _flat(T_w_p),
        "T_turntable_o_scan": _flat(T_turntable_o),
        "hand_scale": float(fit.scale), "joint_angles_rad": _flat(angles_rad),
        "hand_shape": _flat(fit.bone_lengths_m),
        "joints_w": _flat(sfm.joints_w), "joints_fit_w": _flat(joints_hand_w),
        **{f"qa_{name}": qa.metrics.get(name) for name in QA_COLUMNS},
        "qa_flags": list(qa.flags), "qa_notes": list(qa.notes),
        "input_digest": input_digest, "code_version": code_version, "build_id": build_id,
        "config_digest": config_digest,
    }
    prop = results["propagate_poses"]
    cam_index = {int(f): i for i, f in enumerate(sfm.frames)}
    # the cameras the frame's poses used: stage 2's, or where the object was tracked in the
    # frame's depth the camera that pose defines (so T_c_o = inv(T_w_c) @ T_adj @ T_w_o_stage1)
    T_w_c = sfm.T_w_c if prop.T_w_c is None else None
    frames = []
    for j, f in enumerate(np.asarray(prop.frame_indices, dtype=int)):
        i = cam_index.get(int(f))
        camera = prop.T_w_c[j] if T_w_c is None else (T_w_c[i] if i is not None else None)
        frames.append({
            "session_id": m.session_id, "frame": int(f),
            "T_w_c": _flat(camera) if camera is not None else [float("nan")] * 16,
            # False: reconstruct_hand interpolated this camera (too few detections), or has none
            "camera_solved": bool(sfm.pose_valid[i]) if i is not None else False,
            **validity_columns(prop.validity, j),
            "T_c_o": _flat(prop.T_c_o[j]), "T_c_p": _flat(prop.T_c_p[j]),
            "joints_2d_px": _flat(kp[f, :, :2]), "keypoint_conf": _flat(kp[f, :, 2]),
            "joints_c": _flat(prop.joints_c[j]), "reproj_err_px": _flat(prop.reproj_err_px[j]),
            "build_id": build_id,
        })
    V, F = session.read_mesh()
    # refine_grasp's hand when it ran, else fit_hand's moved into the object
    hand = final_hand(fit, refined, results["estimate_adjustment"].T_w_o)
    arrays = SessionArrays(
        contact=np.zeros(len(V), np.float32) if contact is None else contact.contact,
        observed=np.zeros(len(V), bool) if contact is None else contact.observed,
        hand_vertices=np.asarray(hand.vertices_o, np.float32),
        hand_faces=np.asarray(hand.faces, np.int32), joints=np.asarray(hand.joints_o, np.float64),
    )
    mesh = ObjectMesh(V.astype(np.float32), F.astype(np.int32))
    return SessionRows(row, frames, arrays, labels["object_id"], mesh)


def manifest_labels(session_dir: Path) -> dict[str, str]:
    """The label columns (:data:`LABEL_COLUMNS`) of a session from its current
    ``session.json``; raises ``ValueError`` naming the file and field when one is not a
    non-empty string (``load_session`` checked them; the file changed since)."""
    from graspcap.schemas.session import DEFAULT_LIMITS
    from graspcap.tasks.session.files import load_json

    raw = load_json(Path(session_dir) / "session.json", DEFAULT_LIMITS.max_manifest_bytes,
                    DEFAULT_LIMITS.max_json_depth)
    raw = raw if isinstance(raw, dict) else {}
    out = {}
    for c in LABEL_COLUMNS:
        value = raw.get(c)
        if not isinstance(value, str) or not value:
            raise ValueError(f"{Path(session_dir) / 'session.json'}: field {c}: "
                             f"{value!r} is not a non-empty string")
        out[c] = value
    return out


def _read_manifest(session_dir: Path) -> dict[str, Any]:
    """The parsed ``session.json`` as far as it can be read ({} otherwise): a regular file of
    a sane size only, never a FIFO, a device, a 10 GB file."""
    raw: Any = {}
    path = Path(session_dir) / "session.json"
    try:
        st = os.stat(path)
        if stat.S_ISREG(st.st_mode) and st.st_size <= MANIFEST_MAX_BYTES:
            raw = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError):
        raw = {}
    return raw if isinstance(raw, dict) else {}


def failed_row(session_dir: Path, session_id: str, error: str, *, input_digest: str,
               code_version: str, build_id: str, config_digest: str) -> dict[str, Any]:
    """The ``sessions`` row of a session that failed: identity from its manifest as far as it
    can be read, every result column null, ``error`` the reason. ``qa_flags`` and ``qa_notes``
    are null too: ``qa_metrics`` needs every data stage, so it never ran on such a session (a
    session QA failed gets :func:`session_rows`, with its flags and notes)."""
    raw = _read_manifest(Path(session_dir))
    from graspcap.schemas.tables import SESSIONS_SCHEMA

    row: dict[str, Any] = {name: None for name in SESSIONS_SCHEMA.names}
    row.update({c: str(raw.get(c) or "unknown") for c in IDENTITY_COLUMNS})
    row.update(session_id=session_id, status=Status.FAILED.value, error=error,
               input_digest=input_digest, code_version=code_version, build_id=build_id,
               config_digest=config_digest)
    for col in ("contact_digest", "hand_mesh_digest", "object_mesh_digest"):
        row.pop(col)
    return row
