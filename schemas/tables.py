"""The catalog's contract: Arrow schemas of its tables, the Zarr layout of its arrays, its format.

This module is the single source of truth for what a catalog holds. Writers validate every batch
against these schemas (``graspcap.catalog.validate``); readers cast what they read back to them and
check ``CATALOG_FORMAT_VERSION`` on open. The column names and encodings below are the contract of
``pipeline.md`` ("Columns every version must have"); changing one is a format change and goes into
``docs/data_changelog.md``.

Encodings: a pose ``T_a_b`` is ``fixed_size_list<float64>[16]``, the 4x4 matrix in row-major order
(``p_a = T_a_b @ p_b``); 3D joints are ``[63]`` (21 x 3, metres), 2D joints ``[42]`` (21 x 2,
pixels), both in the 21-keypoint OpenPose/MediaPipe order. Field metadata carries ``unit``,
``shape`` and ``doc``; ``required`` = ``unless_failed`` marks columns that may be null only on a
row whose ``status`` is ``failed``.

Schema evolution: a column added to a table that already holds rows (a migration adds it to the
Delta table, ``graspcap.catalog.migrate``) must be nullable; reading files written before it
existed yields nulls there (``graspcap.catalog.delta.read_files``), so a catalog version pinned
before the migration reads as the current schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import pyarrow as pa

from graspcap.schemas.qa import qa_columns

CATALOG_FORMAT_VERSION = 7
"""Bumped on any change of the tables' columns, their encodings, their Delta table properties or
the Zarr layout (``docs/data_changelog.md``)."""

DELTA_TABLE_PROPERTIES: dict[str, str] = {"delta.enableExpiredLogCleanup": "false"}
"""Properties of every Delta table (format 2 on). Delta deletes log entries older than
``delta.logRetentionDuration`` (30 days) whenever it writes a checkpoint (every 100 commits);
a catalog version pins Delta versions, so that cleanup would make old (tagged) versions
unreadable. With it off, only ``Catalog.vacuum`` removes what a version needs."""

CATALOG_FORMAT_NAME = "graspcap-catalog"


class Status(StrEnum):
    """A session's verdict in the ``sessions`` table."""

    OK = "ok"
    FLAGGED = "flagged"
    FAILED = "failed"


class VersionState(StrEnum):
    """A catalog version's publication state (write-audit-publish, format 7)."""

    PUBLISHED = "published"
    """Readers' default: ``open()`` and ``GraspDataset`` read the newest published version."""
    STAGED = "staged"
    """Committed but not published (its audit failed, or auto-publish was off): readable by
    number, never a reader's default."""
    REJECTED = "rejected"
    """Rejected by hand: readable by number; the next build writes on top of the newest
    version that is not rejected."""


def _f(name: str, type_: pa.DataType, doc: str, *, nullable: bool = False, unit: str = "",
       shape: str = "", required: str = "") -> pa.Field:
    meta = {"doc": doc}
    if unit:
        meta["unit"] = unit
    if shape:
        meta["shape"] = shape
    if required:
        meta["required"] = required
    return pa.field(name, type_, nullable=nullable, metadata=meta)


def _pose(name: str, doc: str, **kw) -> pa.Field:
    return _f(name, pa.list_(pa.float64(), 16), doc, unit="m", shape="4x4 row-major", **kw)


def _result(field: pa.Field) -> pa.Field:
    """A result column: null allowed only when the session failed."""
    meta = dict(field.metadata or {})
    meta[b"required"] = b"unless_failed"
    return field.with_nullable(True).with_metadata(meta)


_STR = pa.string()
_F64 = pa.float64()
_TIME = pa.timestamp("us", tz="UTC")


def _qa(name: str, doc: str, unit: str) -> pa.Field:
    return _f(name, _F64, doc + " Null when not computed.", nullable=True, unit=unit)


SESSIONS_SCHEMA = pa.schema([
    _f("session_id", _STR, "Capture session id, unique within a catalog version."),
    _f("participant", _STR, "Participant id."),
    _f("object_id", _STR, "Object id, a label: sessions of one object may carry different "
       "meshes (each session's own is the group `object_mesh_digest`)."),
    _f("intent", _STR, "Grasp intent (e.g. use, handoff)."),
    _f("hand", _STR, "right or left."),
    _f("status", _STR, "ok, flagged or failed."),
    _f("error", _STR, "Null unless failed: the reason a person can act on.", nullable=True),
    _f("keypoint_backend", _STR, "Backend that produced the session's 2D keypoints "
       "(openpose_json or mediapipe). Null when failed, and on rows written before the "
       "column existed.", nullable=True),
    _f("keypoint_frames_detected", pa.int32(), "Video frames in which that backend found the "
       "hand. Null when failed, and on rows written before the column existed.",
       nullable=True, unit="frames"),
    _result(_f("steady_from", pa.int64(), "First steady video frame index.")),
    _result(_pose("T_w_o_stage1", "Object in the world (colour camera) frame, stage 1.")),
    _result(_pose("T_adj", "Object motion during grasp adjustment, world frame.")),
    _result(_pose("T_w_p", "Palm of the refined hand model in the world frame.")),
    _result(_pose("T_turntable_o_scan", "Object on the platter at angle 0 during the scan.")),
    _result(_f("hand_scale", _F64, "Scale of the kinematic hand model.", unit="1")),
    _result(_f("joint_angles_rad", pa.list_(_F64, 20), "20 joint angles of the hand model.",
               unit="rad", shape="20")),
    _result(_f("joints_w", pa.list_(_F64, 63), "Structure-from-motion joints, before any fit.",
               unit="m", shape="21x3")),
    _result(_f("joints_fit_w", pa.list_(_F64, 63), "Joints of the fitted and refined hand model.",
               unit="m", shape="21x3")),
    *[_qa(m.column, m.column_doc, m.column_unit) for m in qa_columns()],  # schemas/qa.py
    _f("qa_flags", pa.list_(_STR), "Why qa_metrics flagged the session (QaReport.flags): one "
       "reason per flag limit a metric crossed or warning a stage raised, e.g. 'RGB-D result vs "
       "pixels-only optimum 15.62 mm > 12.50 mm'; empty when none (a failed session's failures "
       "are in error). Format 4; null where QA did not run (a stage failed) and on rows written "
       "before.", nullable=True),
    _f("qa_notes", pa.list_(_STR), "What QA noted that changes no verdict (QaReport.notes): an "
       "ambiguous registration of a near-symmetric object (the depth could not decide its pose "
       "about the symmetry axis; the pose nearest stage 1 was kept, so it can be degrees off "
       "about that axis), or a refinement rejected in favour of the stage-3 fit. Empty when "
       "none. Format 4; null where QA did not run and on rows written before.", nullable=True),
    _f("hand_shape", pa.list_(_F64, 20), "The fitted hand's shape: its 20 bone lengths in "
       "metres (hand_scale included), in the skeleton's order (per finger thumb to little: "
       "wrist to the finger's base keypoint, then its three segments; "
       "graspcap.tasks.hand.shape.BONE_NAMES). The model's per-bone factors are hand_shape / "
       "(hand_scale * TEMPLATE_BONE_LENGTHS_M). Format 7; null when failed and on rows "
       "written before.", nullable=True, unit="m", shape="20"),
    _f("input_digest", _STR, "sha256 of the session's input bytes."),
    _f("code_version", _STR, "graspcap version (and git revision) that built the row."),
    _f("build_id", _STR, "Build that wrote the row (see the builds table)."),
    _f("config_digest", _STR, "sha256 of the canonical configs of every stage."),
    _result(_f("contact_digest", _STR, "Zarr group `contact` (values, observed).")),
    _result(_f("hand_mesh_digest", _STR, "Zarr group `hand_mesh` (vertices, faces, joints).")),
    _result(_f("object_mesh_digest", _STR, "Zarr group `object_mesh` (vertices, faces): the "
               "session's own object mesh, which its contact map indexes; content-addressed, "
               "so sessions with the same mesh share one group.")),
], metadata={"table": "sessions", "key": "session_id"})

NOT_RECORDED = "not recorded before format 6"
"""The reason ``graspcap catalog migrate`` writes on the rows a catalog had before format 6, in
the reason columns of :func:`_validity_columns` (their flags stay null)."""


def _validity_columns() -> list[pa.Field]:
    """Format 6's per-frame validity columns of ``frames`` (``tasks/outputs/frame_validity.py``,
    docs/catalog.md "Per-frame validity"); ``GraspDataset`` keeps no row where a flag is False."""
    why = ("Why not, short and human; null where the flag is True. On rows written before "
           f"format 6 (migrated): {NOT_RECORDED!r}.")
    return [
        _f("camera_reason", _STR, "Why camera_solved is False, e.g. 'interpolated from its "
           f"neighbours: 3 keypoints detected'. {why}", nullable=True),
        _f("hand_used", pa.bool_(), "True where the frame's hand detection was used: at least "
           "min_hand_inliers (6) of its keypoints are inliers of reconstruct_hand's final solve; "
           "False where not (no detection, too few inliers); null outside reconstruct_hand's "
           "window (frames before the steady onset are not part of the static-hand problem and "
           "have no rows) and on rows written before format 6.", nullable=True),
        _f("hand_reason", _STR, "Why hand_used is not True, e.g. 'no detection', '3 of 17 "
           f"detected keypoints inliers (need 6)'. {why}", nullable=True),
        _f("object_supported", pa.bool_(), "True where the frame's depth supports the object "
           "pose T_c_o: of the object's pixels the hand does not cover (model and hand ray cast "
           "at the pose), at least min_agreement (0.5) have a depth reading within depth_tol_m "
           "(10 mm) of the model's; False where fewer do (the pose or the camera is off there); "
           "null where the frame cannot say (fewer than min_pixels such pixels: the hand covers "
           "the object, it is out of view, the depth has holes) and on rows written before "
           "format 6.", nullable=True),
        _f("object_reason", _STR, "Why object_supported is not True, e.g. 'depth disagrees: "
           "median 14 mm, 20% of 310 pixels within 10 mm', 'too few object pixels visible: 12 "
           f"of 240 outside the hand (need 50; the hand covers it)'. {why}", nullable=True),
        _f("object_depth_agreement", _F64, "Share of the judged object pixels whose depth "
           "agrees with the model at T_c_o (what object_supported compares with min_agreement); "
           "null where no verdict was reached and on rows written before format 6.",
           nullable=True, unit="1"),
    ]


FRAMES_SCHEMA = pa.schema([
    _f("session_id", _STR, "Capture session id."),
    _f("frame", pa.int64(), "Video frame index, from steady_from on."),
    _pose("T_w_c", "Virtual camera of the frame in the world frame."),
    _f("camera_solved", pa.bool_(), "True where stage 2 solved the frame's virtual camera from "
       "the frame's own keypoints; False where it interpolated it from its neighbours (too few "
       "detections), so T_w_c, T_c_o, T_c_p and joints_c of that row are interpolated too. "
       "Format 4; null on rows written before.", nullable=True),
    *_validity_columns(),
    _pose("T_c_o", "Object in the frame's camera."),
    _pose("T_c_p", "Palm in the frame's camera."),
    _f("joints_2d_px", pa.list_(_F64, 42), "Observed 2D keypoints.", unit="px", shape="21x2"),
    _f("keypoint_conf", pa.list_(_F64, 21), "Detection confidence, 0 = not detected.",
       unit="1", shape="21"),
    _f("joints_c", pa.list_(_F64, 63), "3D joints in the frame's camera.", unit="m",
       shape="21x3"),
    _f("reproj_err_px", pa.list_(_F64, 21), "Reprojection error per keypoint (NaN if unseen).",
       unit="px", shape="21"),
    _f("build_id", _STR, "Build that wrote the row."),
], metadata={"table": "frames", "key": "session_id,frame"})

_FAILED = pa.struct([pa.field("session_id", _STR, nullable=False),
                     pa.field("error", _STR, nullable=False)])

BUILDS_SCHEMA = pa.schema([
    _f("build_id", _STR, "Build id."),
    _f("catalog_version", pa.int64(), "Catalog version this build committed."),
    _f("time_utc", _TIME, "Commit time."),
    _f("code_version", _STR, "graspcap version (and git revision)."),
    _f("config_digest", _STR, "sha256 of the canonical configs of every stage."),
    _f("parameters_json", _STR, "The build's parameters as canonical JSON."),
    _f("sessions_added", pa.list_(_STR), "Sessions new in this version."),
    _f("sessions_changed", pa.list_(_STR), "Sessions rewritten with different values."),
    _f("sessions_unchanged", pa.list_(_STR), "Sessions the build found up to date."),
    _f("sessions_removed", pa.list_(_STR), "Sessions removed from the catalog."),
    _f("sessions_failed", pa.list_(_FAILED), "Failed sessions with their errors."),
    _f("audit_passed", pa.bool_(), "Whether the version passed the write-audit-publish audit "
       "(null: committed without an audit, or before format 7).", nullable=True),
    _f("audit_reasons", pa.list_(_STR), "Why the audit failed, one gate a line (empty when it "
       "passed).", nullable=True),
    _f("audit_json", _STR, "The audit as canonical JSON: gates, measured values, the "
       "published version it compared against.", nullable=True),
], metadata={"table": "builds", "key": "build_id"})

VERSIONS_SCHEMA = pa.schema([
    _f("version", pa.int64(), "Catalog version, 1, 2, ..."),
    _f("time_utc", _TIME, "Commit time: the row's write is the version's linearisation point."),
    _f("build_id", _STR, "Build that made the version."),
    _f("format_version", pa.int32(), "CATALOG_FORMAT_VERSION of the writer."),
    _f("table_versions", _STR, "JSON {table: Delta version} to read the version at."),
    _f("rows_sessions", pa.int64(), "Rows of the sessions table at this version."),
    _f("rows_frames", pa.int64(), "Rows of the frames table at this version."),
    _f("rows_builds", pa.int64(), "Rows of the builds table at this version."),
    _f("state", _STR, "State at commit: published (readers' default once committed) or staged "
       "(its audit failed, or auto-publish is off); null before format 7 (published). Later "
       "changes are rows of the publications table.", nullable=True),
], metadata={"table": "versions", "key": "version"})

TAGS_SCHEMA = pa.schema([
    _f("tag", _STR, "Tag name; the latest row of a tag wins."),
    _f("version", pa.int64(), "Catalog version the tag points to."),
    _f("time_utc", _TIME, "When the tag was set."),
], metadata={"table": "tags", "key": "tag"})

PUBLICATIONS_SCHEMA = pa.schema([
    _f("version", pa.int64(), "Catalog version whose state changes."),
    _f("state", _STR, "published or rejected (`graspcap catalog publish|reject`)."),
    _f("time_utc", _TIME, "When the state changed; a version's latest row wins."),
    _f("reason", _STR, "Why (given by hand), may be empty."),
], metadata={"table": "publications", "key": "version"})

TABLE_SCHEMAS: dict[str, pa.Schema] = {
    "sessions": SESSIONS_SCHEMA,
    "frames": FRAMES_SCHEMA,
    "builds": BUILDS_SCHEMA,
    "versions": VERSIONS_SCHEMA,
    "tags": TAGS_SCHEMA,
    "publications": PUBLICATIONS_SCHEMA,
}
"""Every Delta table of a catalog, by its folder name under ``tables/``."""

DATA_TABLES = ("sessions", "frames", "builds")
"""Tables whose Delta versions a catalog version pins (the rest are bookkeeping)."""


@dataclass(frozen=True)
class ZarrArraySpec:
    """One array of a Zarr group: dtype, symbolic shape, chunk rows along axis 0, unit."""

    dtype: np.dtype
    shape: tuple[int | str, ...]
    """Symbolic shape: ints are fixed, a name (``n``, ``m``) must agree within the group."""
    chunk_rows: int
    unit: str
    doc: str
    compressed: bool = True
    """zstd (zarr's default) when True; False stores raw bytes (decoding then needs no worker
    thread: the contact map, read once per training item, reads ~25 % faster)."""


@dataclass(frozen=True)
class ZarrGroupSpec:
    """A content-addressed Zarr v3 group, referenced from ``sessions`` by ``digest_column``."""

    digest_column: str
    arrays: dict[str, ZarrArraySpec]
    doc: str


_ROWS = 65536

ZARR_LAYOUT: dict[str, ZarrGroupSpec] = {
    "contact": ZarrGroupSpec("contact_digest", {
        "values": ZarrArraySpec(np.dtype("float32"), ("n",), _ROWS, "1",
                                "Contact in [0, 1] per object vertex, mesh file order.",
                                compressed=False),
        "observed": ZarrArraySpec(np.dtype("bool"), ("n",), _ROWS, "",
                                  "True where a thermal view saw the vertex.", compressed=False),
    }, "Per session: the contact map on the object mesh."),
    "hand_mesh": ZarrGroupSpec("hand_mesh_digest", {
        "vertices": ZarrArraySpec(np.dtype("float32"), ("n", 3), _ROWS, "m",
                                  "Refined hand surface vertices, object frame."),
        "faces": ZarrArraySpec(np.dtype("int32"), ("m", 3), _ROWS, "",
                               "Triangles, indices into vertices."),
        "joints": ZarrArraySpec(np.dtype("float64"), (21, 3), 21, "m",
                                "Refined hand joints, object frame, 21-keypoint order."),
    }, "Per session: the refined hand (vertices and joints in the object's frame)."),
    "object_mesh": ZarrGroupSpec("object_mesh_digest", {
        "vertices": ZarrArraySpec(np.dtype("float32"), ("n", 3), _ROWS, "m",
                                  "Object mesh vertices, object frame, file order."),
        "faces": ZarrArraySpec(np.dtype("int32"), ("m", 3), _ROWS, "",
                               "Triangles, indices into vertices."),
    }, "Per session: its object's mesh (content-addressed: sessions with the same mesh share "
       "one group, sessions of one object_id may have different ones)."),
}
"""Array groups by kind. Group path: ``arrays/<digest[:2]>/<digest>.zarr``."""


def required_unless_failed(schema: pa.Schema) -> list[str]:
    """Names of the columns that may be null only on a failed row."""
    return [f.name for f in schema if (f.metadata or {}).get(b"required") == b"unless_failed"]
