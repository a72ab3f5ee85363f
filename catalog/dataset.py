"""A map-style dataset over one catalog version, for training code (no torch import).

``GraspDataset`` items are dicts of numpy arrays: a frame row (``unit="frames"``) or a session row
(``unit="sessions"``) joined with its session's arrays (contact map, refined hand mesh and
joints) and the session's own object mesh (the one its contact map indexes; sessions of one
``object_id`` may carry different meshes). QA's flag reasons and notes (``qa_flags``,
``qa_notes``: lists of strings of any length, which a batch collate cannot stack) are not in
the items:
``session_qa(session_id)`` gives them. Frame items come only from frames whose validity
(catalog format 6) no flag denies: ``hand_used``, ``camera_solved`` and ``object_supported``
each True or null (null: not applicable, not decidable from that frame, or not recorded before
format 6), so a frame with an unused hand detection, an interpolated camera or an object pose
its depth contradicts is left out; ``valid_only=False`` keeps every frame (the reasons are in
the items' ``*_reason`` columns). The dataset pickles as its catalog root, pinned version
and item keys; tables and arrays are opened lazily in whichever process indexes it, so it works
with a torch ``DataLoader`` with workers.

Arrays in items are writable. A frame's or session's row values are the item's own copies; the
session arrays (meshes, contact map, refined hand: ``collate.SESSION_ARRAYS``) are read once
per session and process and shared by that session's items (copy one before changing it in
place); ``mesh_id`` names the object mesh (its digest: :meth:`GraspDataset.mesh`).
:func:`graspcap.catalog.collate.collate_fn` batches items of any objects, session arrays once
per session of the batch.

``images=True`` adds each frame item's colour and depth frame, decoded, with its files and
intrinsics (``images="paths"``: without decoding), read from the session folder the build
recorded (``graspcap.catalog.session_view``: the folder must still exist):
``color`` (h, w, 3) uint8 RGB, ``depth`` (h, w) float32 metres (0: no reading), ``K`` (3, 3),
``image_size`` (2,) int64 (width, height), ``color_path``, ``depth_path`` (absolute paths as
str; ``color_path`` is "" for a session without a colour video).
"""

from __future__ import annotations

from collections import OrderedDict
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from graspcap.catalog.arrays import DamagedArrayError, read_group
from graspcap.catalog.session_view import SessionSource, SessionView, session_dirs
from graspcap.catalog.store import Catalog
from graspcap.catalog.store import open as open_catalog
from graspcap.schemas.tables import FRAMES_SCHEMA, SESSIONS_SCHEMA, Status


class Unit(StrEnum):
    """What one item is."""

    FRAMES = "frames"
    SESSIONS = "sessions"


class Images(StrEnum):
    """What frame items carry of the frame's images (``GraspDataset(images=...)``)."""

    NONE = "none"
    PATHS = "paths"
    """Files, ``K`` and image size, no decoding."""
    DECODED = "decoded"
    """Also the decoded ``color`` and ``depth``."""


class SplitKey(StrEnum):
    """Columns a dataset can be split by without leaking between the parts."""

    PARTICIPANT = "participant"
    OBJECT_ID = "object_id"


_SESSION_FIELDS = ["session_id", "participant", "object_id", "intent", "hand", "status",
                   "steady_from", "T_w_o_stage1", "T_adj", "T_w_p", "T_turntable_o_scan",
                   "hand_scale", "joint_angles_rad", "hand_shape", "joints_w", "joints_fit_w"]
_QA_FIELDS = ["status", "qa_flags", "qa_notes"]
VALIDITY_FLAGS = ("hand_used", "camera_solved", "object_supported")
"""``frames`` columns a frame item needs to be True or null in (``valid_only``)."""
_CACHE_SESSIONS = 64
_CACHE_MESHES = 64
"""Object meshes kept per process, by digest (sessions of one object usually share one; with
a mesh per session, an unbounded cache would hold every session's)."""


def _own(value: Any) -> Any:
    """``value`` as the item's own, writable object (a copy of an array row)."""
    return value.copy() if isinstance(value, np.ndarray) else value


def _shape(field: pa.Field) -> tuple[int, ...] | None:
    """The per-row shape of a fixed-size list column from its ``shape`` metadata."""
    if not pa.types.is_fixed_size_list(field.type):
        return None
    text = (field.metadata or {}).get(b"shape", b"").decode().split(" ")[0]
    return tuple(int(d) for d in text.split("x")) if text else (field.type.list_size,)


def _columns(table: pa.Table, schema: pa.Schema) -> dict[str, np.ndarray]:
    """Each column as a numpy array with the per-row shape of the schema, rows first."""
    out = {}
    for name in table.column_names:
        col = table[name].combine_chunks()
        shape = _shape(schema.field(name))
        if shape is None:
            out[name] = col.to_numpy(zero_copy_only=False)
        else:
            k = col.type.list_size
            flat = col.values.to_numpy(zero_copy_only=False)[col.offset * k:
                                                             (col.offset + len(col)) * k]
            out[name] = flat.reshape(len(col), *shape)
    return out


_FILTERS = {"status": "status", "object_id": "objects", "participant": "participants",
            "intent": "intents"}


def _known(sessions: pa.Table, column: str, allowed: Any, version: int) -> list[str]:
    """``allowed`` (a value or values of ``column``) as a list; a ``ValueError`` naming any
    value no session of the version has (a typo would otherwise give an empty dataset) and the
    known ones. Statuses are checked against the schema's, not the version's."""
    values = [allowed] if isinstance(allowed, str) else list(allowed)
    known = (sorted(s.value for s in Status) if column == "status"
             else sorted(set(sessions[column].drop_null().to_pylist())))
    unknown = [v for v in values if v not in known]
    if unknown:
        raise ValueError(f"GraspDataset({_FILTERS[column]}=...): no session of catalog version "
                         f"{version} has {column} {' or '.join(map(repr, unknown))}; known: "
                         f"{', '.join(known)}")
    return values


class GraspDataset:
    """Frames (or sessions) of one catalog version, filtered, as dicts of numpy arrays.

    Parameters
    ----------
    catalog : Catalog or a catalog path
    version : catalog version or tag; None pins the latest at construction
    unit : "frames" (one item per frame row) or "sessions"
    status, objects, participants, intents : keep only sessions with these values (None = all;
        a value no session of the version has raises ``ValueError`` naming the known ones)
    valid_only : frame items only from frames none of whose :data:`VALIDITY_FLAGS` is False
        (True or null: see the module docstring); False keeps every frame. Sessions as items
        are not filtered by it.
    images : False, True (= "decoded") or "paths": the frame's images in frame items (see
        the module docstring); needs ``unit="frames"`` and the session folders.
    session_root : where the session folders are now, when they moved since the build: each
        is looked up under it by its recorded folder's name (None: where the build read it).
    """

    def __init__(self, catalog: Catalog | str | Path, version: int | str | None = None,
                 unit: str = "frames", status: tuple[str, ...] = ("ok",),
                 objects: list[str] | None = None, participants: list[str] | None = None,
                 intents: list[str] | None = None, valid_only: bool = True,
                 images: bool | str = False, session_root: str | Path | None = None):
        self._catalog = catalog if isinstance(catalog, Catalog) else open_catalog(catalog)
        self.version = self._catalog.resolve(version)
        self.unit = Unit(unit)
        self.valid_only = valid_only
        choice = {True: "decoded", False: "none"}.get(images, images)
        if choice not in set(Images):
            raise ValueError(f"GraspDataset(images={images!r}): one of True, False, 'paths'")
        self.images = Images(choice)
        self.session_root = None if session_root is None else str(session_root)
        if self.images is not Images.NONE and self.unit is not Unit.FRAMES:
            raise ValueError(f"GraspDataset(images={images!r}): images are per frame; "
                             "use unit='frames'")
        sessions = every = self._catalog.table("sessions", self.version)
        for col, allowed in (("status", status), ("object_id", objects),
                             ("participant", participants), ("intent", intents)):
            if allowed is not None:
                allowed = _known(every, col, allowed, self.version)
                sessions = sessions.filter(pc.is_in(sessions[col],
                                                    pa.array(allowed, pa.string())))
        self._session_meta = {r["session_id"]: r for r in sessions.select(
            ["session_id", "participant", "object_id", "intent", *_QA_FIELDS]).to_pylist()}
        self.session_ids = sorted(self._session_meta)
        self._keys = self._item_keys()
        self._state: dict | None = None

    def _item_keys(self) -> list[tuple[str, int]]:
        if self.unit is Unit.SESSIONS:
            return [(s, -1) for s in self.session_ids]
        frames = self._frames_table(["session_id", "frame"])
        return list(zip(frames["session_id"].to_pylist(), frames["frame"].to_pylist(),
                        strict=True))

    def _frames_table(self, columns: list[str] | None = None) -> pa.Table:
        """The dataset's frame rows (``columns``, None = all), sorted by session and frame:
        the item keys and the items' frame columns both come from here, in the same order."""
        read = columns
        if columns is not None and self.valid_only:
            read = list(dict.fromkeys([*columns, *VALIDITY_FLAGS]))
        frames = self._catalog.table("frames", self.version, columns=read)
        keep = pc.is_in(frames["session_id"], pa.array(self.session_ids, pa.string()))
        if self.valid_only:
            for flag in VALIDITY_FLAGS:  # null: not applicable or not recorded, kept
                keep = pc.and_(keep, pc.fill_null(frames[flag], True))
        frames = frames.filter(keep)
        if columns is not None:
            frames = frames.select(columns)
        return frames.sort_by([("session_id", "ascending"), ("frame", "ascending")])

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_state"] = None
        return state

    def __len__(self) -> int:
        return len(self._keys)

    def _load(self) -> dict:
        """Open tables in this process (first use, or first use in a worker)."""
        if self._state is None:
            sessions = self._catalog.table("sessions", self.version)
            sessions = sessions.filter(pc.is_in(sessions["session_id"],
                                                pa.array(self.session_ids, pa.string())))
            scols = _columns(sessions.select(_SESSION_FIELDS), SESSIONS_SCHEMA)
            srow = {s: i for i, s in enumerate(scols["session_id"])}
            state = {"sessions": scols, "srow": srow, "arrays": OrderedDict(),
                     "objects": OrderedDict(), "sources": {}}
            if self.unit is Unit.FRAMES:
                frames = self._frames_table()
                state["frames"] = _columns(frames.drop_columns(["build_id"]), FRAMES_SCHEMA)
            self._state = state
        return self._state

    def _session_arrays(self, session_id: str) -> dict[str, np.ndarray]:
        cache = self._load()["arrays"]
        if session_id in cache:
            cache.move_to_end(session_id)
            return cache[session_id]
        cat, v = self._catalog, self.version
        try:
            contact, observed = cat.contactmap(session_id, v)
            hand_v, hand_f = cat.hand_mesh(session_id, v)
            joints = cat.hand_joints(session_id, v)
            digest = cat._digest(session_id, v, "object_mesh_digest")
            objects = self._load()["objects"]  # by mesh digest: each session has its own
            if digest in objects:
                objects.move_to_end(digest)
            else:
                objects[digest] = cat.object_mesh(session_id=session_id, version=v)
                if len(objects) > _CACHE_MESHES:
                    objects.popitem(last=False)
        except DamagedArrayError as exc:  # say whose item it is
            raise DamagedArrayError(exc.digest, f"session {session_id!r} (catalog version "
                                    f"{v}): {exc}", array=exc.array, file=exc.file) from exc
        obj_v, obj_f = objects[digest]
        arrays = {"contact": contact, "contact_observed": observed, "hand_vertices": hand_v,
                  "hand_faces": hand_f, "hand_joints_o": joints,
                  "object_vertices": obj_v, "object_faces": obj_f}
        arrays = {k: a if a.flags.writeable else np.array(a) for k, a in arrays.items()}
        arrays["mesh_id"] = digest
        cache[session_id] = arrays
        if len(cache) > _CACHE_SESSIONS:
            cache.popitem(last=False)
        return arrays

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} items")
        index %= len(self)
        state = self._load()
        session_id, _ = self._keys[index]
        i = state["srow"][session_id]
        item = {name: _own(col[i]) for name, col in state["sessions"].items()}
        if self.unit is Unit.FRAMES:
            item.update({name: _own(col[index]) for name, col in state["frames"].items()})
        item.update(self._session_arrays(session_id))
        if self.images is not Images.NONE:
            item.update(self._images(session_id, int(item["frame"])))
        return item

    def _source(self, session_id: str) -> SessionSource:
        state = self._load()
        sources = state["sources"]
        if session_id not in sources:
            if "dirs" not in state:  # the builds table, read once per process
                state["dirs"] = session_dirs(self._catalog, self.version, self.session_root)
            build_id, root = state["dirs"][session_id]
            sources[session_id] = SessionSource.find(session_id, build_id, root, self.version)
        return sources[session_id]

    def _images(self, session_id: str, frame: int) -> dict[str, Any]:
        source = self._source(session_id)
        color, depth = source.image_filenames(frame)
        out = {"K": source.K, "image_size": source.image_size,
               "color_path": "" if color is None else str(color), "depth_path": str(depth)}
        if self.images is Images.DECODED:
            out["color"] = source.color(frame)
            out["depth"] = source.depth(frame)
        return out

    def session_arrays(self, session_id: str) -> dict[str, Any]:
        """The arrays every item of ``session_id`` shares (``collate.SESSION_ARRAYS``) and its
        ``mesh_id``; shared with the items, so copy an array before changing it in place."""
        if session_id not in self._session_meta:
            raise KeyError(f"session {session_id!r} is not in this dataset (catalog version "
                           f"{self.version}, {len(self.session_ids)} sessions)")
        return dict(self._session_arrays(session_id))

    def mesh(self, mesh_id: str) -> tuple[np.ndarray, np.ndarray]:
        """The object mesh ``mesh_id`` (an item's ``mesh_id``): vertices (n, 3) float32 in the
        object frame (m), faces (m, 3) int32."""
        objects = self._load()["objects"]
        if mesh_id not in objects:
            g = read_group(self._catalog.layout, mesh_id, ("vertices", "faces"))
            return g["vertices"], g["faces"]
        return objects[mesh_id]

    def session(self, session_id: str) -> SessionView:
        """The ContactPose-style view of ``session_id`` at the dataset's version
        (``Catalog.session``)."""
        return SessionView(self._catalog, session_id, self.version, self.session_root)

    def session_qa(self, session_id: str) -> dict[str, Any]:
        """``status``, ``qa_flags`` and ``qa_notes`` of a session of the dataset: why QA flagged
        it, and what it noted without a verdict (e.g. an ambiguous registration of a
        near-symmetric object, whose pose about its axis may be off). The lists are None on a
        row written before format 4."""
        meta = self._session_meta[session_id]
        return {k: meta[k] for k in _QA_FIELDS}

    def _subset(self, session_ids: list[str]) -> GraspDataset:
        keep = set(session_ids)
        sub = object.__new__(GraspDataset)
        sub.__dict__.update(self.__getstate__())
        sub.session_ids = [s for s in self.session_ids if s in keep]
        sub._session_meta = {s: self._session_meta[s] for s in sub.session_ids}
        sub._keys = [k for k in self._keys if k[0] in keep]
        return sub

    def split_by(self, key: str = "participant", holdout: list[str] = ()
                 ) -> tuple[GraspDataset, GraspDataset]:
        """(rest, held out): sessions whose ``key`` value is in ``holdout`` go to the second."""
        key = SplitKey(key)
        held = [s for s, m in self._session_meta.items() if m[key] in set(holdout)]
        rest = [s for s in self.session_ids if s not in set(held)]
        return self._subset(rest), self._subset(held)
