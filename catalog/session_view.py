"""A catalog session's images, and a ContactPose-style view of one session (no torch here).

The catalog holds no images: a session's colour and depth frames stay in the session folder
the build read (``session-format.md``). The folder is recorded in the ``builds`` table, by the
build that wrote the session's row (``parameters_json`` -> ``report.sessions[].session_dir``,
an absolute path), and the frame files, intrinsics and image size are read at access time from
that folder's ``session.json`` (its ``grasp.color`` / ``grasp.depth`` patterns over the frame
index, ``color_camera``, ``depth_scale_m``). So the session folders must still exist at the
path the build read them from for anything here that touches an image or the intrinsics; a
missing folder, manifest or file is an error naming the session, the build and the path.
Sessions moved since the build: ``session_root=`` names a folder that now holds them, each
under its recorded folder's name. Files are not re-hashed against the row's ``input_digest``.

Images come in the ideal pinhole image of ``K`` (the frame every stage's geometry works in):
with a non-zero ``color_camera.dist`` they are resampled (``Camera.undistort_image``: colour
bilinear, depth nearest), untouched otherwise; so ``K`` projects the catalog's camera-frame
points onto them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow.compute as pc

from graspcap.catalog.errors import CatalogError
from graspcap.schemas.session import SessionManifest

# cv2: imported where used, so that importing the catalog (a build's start) stays cheap

if TYPE_CHECKING:
    from graspcap.catalog.store import Catalog

MANIFEST = "session.json"


def session_dirs(catalog: Catalog, version: int, session_root: str | Path | None = None
                 ) -> dict[str, tuple[str, Path | None]]:
    """``{session_id: (build_id, session folder or None)}`` of every session of ``version``:
    the folder the build that wrote the session's row read it from (None where that build
    recorded none, e.g. a catalog committed without ``graspcap build``); with
    ``session_root``, the folder of that name under it instead (sessions moved since)."""
    recorded: dict[str, dict[str, str]] = {}
    for row in catalog.table("builds", version).select(
            ["build_id", "parameters_json"]).to_pylist():
        try:
            report = json.loads(row["parameters_json"] or "{}").get("report") or {}
        except (json.JSONDecodeError, AttributeError):
            report = {}
        recorded[row["build_id"]] = {s["session_id"]: s["session_dir"]
                                     for s in report.get("sessions") or ()
                                     if isinstance(s, dict) and s.get("session_dir")}
    out = {}
    for row in catalog.table("sessions", version).select(["session_id", "build_id"]).to_pylist():
        folder = recorded.get(row["build_id"], {}).get(row["session_id"])
        if folder is not None and session_root is not None:
            folder = Path(session_root) / Path(folder).name
        out[row["session_id"]] = (row["build_id"], None if folder is None else Path(folder))
    return out


@dataclass(frozen=True)
class SessionSource:
    """A session's folder and manifest: its frame files, intrinsics and image decoding."""

    session_id: str
    root: Path
    manifest: SessionManifest

    @classmethod
    def find(cls, session_id: str, build_id: str, root: Path | None,
             version: int) -> SessionSource:
        """The source of ``session_id`` at ``root`` (as recorded by ``build_id``), its manifest
        read and checked now; a ``CatalogError`` naming what is missing."""
        where = f"session {session_id!r} (catalog version {version}, build {build_id!r})"
        if root is None:
            raise CatalogError(f"{where}: the build recorded no session folder (a catalog "
                               "committed without `graspcap build`), so its images cannot be "
                               "found")
        path = root / MANIFEST
        if not path.is_file():
            raise CatalogError(f"{where}: {path} is missing; images are read from the session "
                               "folder the build read, which must still exist at that path "
                               "(moved sessions: pass session_root=, the folder now holding "
                               "them)")
        try:
            manifest = SessionManifest.model_validate(json.loads(path.read_text("utf-8")))
        except (ValueError, OSError) as exc:  # pydantic's ValidationError is a ValueError
            raise CatalogError(f"{where}: {path} does not read as a session manifest: "
                               f"{exc}") from exc
        if manifest.session_id != session_id:
            raise CatalogError(f"{where}: {path} is of session {manifest.session_id!r}; the "
                               "folder was replaced after the build")
        return cls(session_id, root, manifest)

    @property
    def K(self) -> np.ndarray:
        """``(3, 3) float64``: the colour (and aligned depth) camera's intrinsics, pixels."""
        return self.manifest.color_camera.K_array()

    @property
    def dist(self) -> np.ndarray:
        """``(n,) float64``: the colour camera's OpenCV distortion (the images come
        undistorted, see the module docstring)."""
        return self.manifest.color_camera.dist_array()

    @property
    def image_size(self) -> np.ndarray:
        """``(2,) int64``: ``(width, height)`` in pixels."""
        return np.array(self.manifest.color_camera.size, dtype=np.int64)

    def image_filenames(self, frame: int) -> tuple[Path | None, Path]:
        """``(colour, depth)`` files of grasp frame ``frame``; colour is None when the
        manifest has no ``grasp.color`` (keypoints given instead)."""
        grasp = self.manifest.grasp
        if not 0 <= frame < grasp.count:
            raise IndexError(f"session {self.session_id!r}: frame {frame} outside the video's "
                             f"0..{grasp.count - 1} ({self.root / MANIFEST})")
        color = grasp.frame_path("color", frame)
        return (None if color is None else self.root / color,
                self.root / grasp.frame_path("depth", frame))

    def color(self, frame: int) -> np.ndarray:
        """``(h, w, 3) uint8`` RGB of grasp frame ``frame`` (ideal pinhole image of ``K``)."""
        import cv2

        path, _ = self.image_filenames(frame)
        if path is None:
            raise CatalogError(f"session {self.session_id!r}: {self.root / MANIFEST} has no "
                               "grasp.color (the session gave keypoints instead of video)")
        rgb = cv2.cvtColor(self._read(path, cv2.IMREAD_COLOR, np.uint8), cv2.COLOR_BGR2RGB)
        return self._ideal(rgb, nearest=False)

    def depth(self, frame: int) -> np.ndarray:
        """``(h, w) float32`` metres of grasp frame ``frame`` (0: no reading), in the ideal
        pinhole image of ``K``."""
        import cv2

        _, path = self.image_filenames(frame)
        raw = self._read(path, cv2.IMREAD_UNCHANGED, np.uint16)
        depth = raw.astype(np.float32) * np.float32(self.manifest.depth_scale_m)
        return self._ideal(depth, nearest=True)

    def _read(self, path: Path, flags: int, dtype: type) -> np.ndarray:
        import cv2

        image = cv2.imread(str(path), flags) if path.is_file() else None
        if image is None or image.dtype != dtype:
            what = "missing or unreadable" if image is None else f"{image.dtype}, not {dtype}"
            raise CatalogError(f"session {self.session_id!r}: {path} is {what}")
        return image

    def _ideal(self, image: np.ndarray, *, nearest: bool) -> np.ndarray:
        """``image`` resampled into the ideal pinhole image of ``K`` (``dist`` undone), as the
        pipeline's stages read it (``tasks/core/camera.py``, which the catalog does not
        import: the same ``cv2.initUndistortRectifyMap`` with ``newCameraMatrix = K``); as is
        when ``dist`` is zero. ``nearest`` for depth (no values blended across an edge)."""
        import cv2

        dist = self.dist
        if not np.any(dist):
            return image
        K = self.K
        h, w = image.shape[:2]
        map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_32FC1)
        return cv2.remap(image, map_x, map_y, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _rows(column, shape: tuple[int, ...]) -> np.ndarray:
    """A fixed-size list column as ``(n, *shape) float64``."""
    return np.asarray(column.to_pylist(), dtype=float).reshape(-1, *shape)


class SessionView:
    """One session of a catalog version, as ContactPose's ``ContactPose`` object gives it.

    ``frames``: the video frame indices the catalog has rows for (from ``steady_from`` on,
    every frame: the validity flags are in the ``frames`` table). Poses and joints come from
    the catalog; ``K``, ``image_size`` and the image files from the session folder (see the
    module docstring). Units: metres, pixels; ``T_a_b`` maps b into a.
    """

    def __init__(self, catalog: Catalog, session_id: str, version: int | str | None = None,
                 session_root: str | Path | None = None):
        self.version = catalog.resolve(version)
        self.session_id = session_id
        self._session_root = session_root
        self._catalog = catalog
        catalog._session_row(session_id, self.version)  # KeyError naming the version
        frames = catalog.table("frames", self.version, columns=[
            "session_id", "frame", "T_c_o", "joints_c"])
        frames = frames.filter(pc.equal(frames["session_id"], session_id)).sort_by("frame")
        self.frames: list[int] = frames["frame"].to_pylist()
        self._row = {f: i for i, f in enumerate(self.frames)}
        self._T_c_o = _rows(frames["T_c_o"], (4, 4))
        self._joints_c = _rows(frames["joints_c"], (21, 3))

    def __repr__(self) -> str:
        return (f"SessionView({self.session_id!r}, version={self.version}, "
                f"{len(self.frames)} frames)")

    @cached_property
    def source(self) -> SessionSource:
        """The session's folder and manifest (read on first use)."""
        build_id, root = session_dirs(self._catalog, self.version,
                                      self._session_root)[self.session_id]
        return SessionSource.find(self.session_id, build_id, root, self.version)

    def _i(self, frame: int) -> int:
        if frame not in self._row:
            span = f"{self.frames[0]}..{self.frames[-1]}" if self.frames else "none"
            raise KeyError(f"session {self.session_id!r} has no catalog row for frame {frame} "
                           f"in version {self.version} (its frames: {span})")
        return self._row[frame]

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` intrinsics of the colour camera (and the aligned depth), pixels."""
        return self.source.K

    @property
    def image_size(self) -> np.ndarray:
        """``(width, height)`` in pixels."""
        return self.source.image_size

    def object_pose(self, frame: int) -> np.ndarray:
        """``(4, 4)`` ``T_c_o``: the object in frame ``frame``'s camera."""
        return self._T_c_o[self._i(frame)].copy()

    def hand_joints(self, frame: int) -> np.ndarray:
        """``(21, 3)`` joints in frame ``frame``'s camera, metres (OpenPose order)."""
        return self._joints_c[self._i(frame)].copy()

    @cached_property
    def hand_joints_o(self) -> np.ndarray:
        """``(21, 3)`` the refined hand's joints in the object frame (ContactPose's
        ``hand_joints()`` without a frame), metres."""
        return np.array(self._catalog.hand_joints(self.session_id, self.version))

    @cached_property
    def _hand_row(self) -> dict:
        """The session's ``hand_shape`` column of ``sessions``."""
        table = self._catalog.table("sessions", self.version, columns=[
            "session_id", "hand_shape"])
        return table.filter(pc.equal(table["session_id"], self.session_id)).to_pylist()[0]

    @property
    def hand_shape(self) -> np.ndarray | None:
        """``(20,)`` the hand's bone lengths in metres (``sessions.hand_shape``, skeleton
        order; ``graspcap.tasks.hand.shape.BONE_NAMES``), or None on a row written before
        format 7 (the template's proportions) or of a failed session. The hand model's
        parameters: ``graspcap.tasks.hand.shape.bone_scale_from_lengths(hand_shape,
        hand_scale)``, then ``HandModel.mesh(joint_angles_rad, T_w_p, hand_scale,
        bone_scale)`` rebuilds the final hand (the ``sessions`` row's columns)."""
        value = self._hand_row["hand_shape"]
        return None if value is None else np.asarray(value, dtype=float)

    def P(self, frame: int) -> np.ndarray:  # noqa: N802 - ContactPose's name
        """``(3, 4)`` projection of object-frame points into frame ``frame``: ``K @ T_c_o[:3]``
        (ContactPose's ``P``); ``uvw = P @ [x, 1]``, pixels ``uvw[:2] / uvw[2]``."""
        return self.K @ self.object_pose(frame)[:3]

    def projected_hand_joints(self, frame: int) -> np.ndarray:
        """``(21, 2)`` pixels: :meth:`hand_joints` projected with ``K`` (NaN for a joint at or
        behind the camera plane), what ``frames.reproj_err_px`` compares with the detections
        ``frames.joints_2d_px``."""
        joints = self.hand_joints(frame)
        uvw = joints @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = uvw[:, :2] / uvw[:, 2:3]
        uv[joints[:, 2] <= 1e-9] = np.nan
        return uv

    def image_filenames(self, frame: int) -> tuple[Path | None, Path]:
        """``(colour, depth)`` files of frame ``frame`` (colour None without a video)."""
        self._i(frame)
        return self.source.image_filenames(frame)

    def color(self, frame: int) -> np.ndarray:
        """``(h, w, 3) uint8`` RGB of frame ``frame``."""
        self._i(frame)
        return self.source.color(frame)

    def depth(self, frame: int) -> np.ndarray:
        """``(h, w) float32`` metres of frame ``frame``."""
        self._i(frame)
        return self.source.depth(frame)
