"""The role digests of a session, remembered across processes (``SessionRoles``): what its
stage keys are made of, kept under a stamp of every file its manifest names, so a fresh build
keys an unchanged session without listing and resolving its files (``docs/architecture.md``)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from graspcap.flows.cached import session_names
from graspcap.flows.workarea import WorkArea, _atomic_write, is_racy
from graspcap.schemas.session import SessionManifest
from graspcap.tasks.session.load_session import MANIFEST


def manifest_names(manifest: SessionManifest) -> dict[str, list[str]]:
    """The files of ``Session.input_files``, by role, as the manifest names them (relative to
    the session directory, not resolved; a test holds the two equal). Kept here rather than
    beside ``input_files``: ``load_session``'s module is in every stage's code digest, and a
    change there re-runs every stage of every session."""
    grasp = manifest.grasp

    def frames(kind: str) -> list[str]:
        if getattr(grasp, kind) is None:
            return []
        return [grasp.frame_path(kind, i) for i in range(grasp.count)]  # type: ignore[arg-type]

    return {
        "manifest": [MANIFEST],
        "object_mesh": [manifest.object_mesh],
        "stage1": [r for r in (manifest.stage1.depth, manifest.stage1.color) if r is not None],
        "grasp_color": frames("color"),
        "grasp_depth": frames("depth"),
        "grasp_keypoints": frames("keypoints"),
        "scan_thermal": [v.thermal for v in manifest.scan.views],
        "scan_depth": [v.depth for v in manifest.scan.views],
    }


ROLES_MEMO_FORMAT = 1
"""Format of the per-session memos of role digests (``digests/roles-<sha of folder>.json``)."""


def session_stamps(session_dir: Path | str) -> dict[str, list[int]] | None:
    """(device, inode, size, mtime_ns) of every file the session's manifest names, by that
    name, each ``stat`` followed through symbolic links as a stage opening it would: what the
    remembered role digests (:class:`SessionRoles`) are checked against. A file replaced,
    rewritten or reached through a retargeted link has another stamp. None when the manifest
    cannot say, a name is absolute or climbs out, or a file cannot be stat'ed."""
    root = os.path.abspath(session_dir)
    names = session_names(Path(root))
    if names is None:
        return None
    out: dict[str, list[int]] = {}
    try:
        for rel in {n for role in names.values() for n in role}:
            if os.path.isabs(rel) or ".." in rel.split("/"):
                return None
            st = os.stat(os.path.join(root, rel))
            out[rel] = [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns]
    except (OSError, ValueError):
        return None
    return out


class SessionRoles:
    """The role digests (role -> :func:`reads_digest`'s digest of its files) of one session,
    kept across processes in ``digests/roles-<sha of folder>.json`` under the session's
    :func:`session_stamps`: an unchanged session is settled from one small read and one
    ``stat`` a file, without listing its files (resolving ~80-300 paths) or reading its
    per-folder digest memos. ``digests`` starts with what an earlier process left when every
    file has the stamp it had then (empty otherwise), and is filled by :func:`reads_digest`.
    The stamps are taken before any digest is: a file changed in between has another stamp
    next time, so the memo is only ever too old, never wrong."""

    def __init__(self, work: WorkArea, session_dir: Path | str):
        self.work, self.root = work, os.path.abspath(session_dir)
        self.stamps = session_stamps(self.root)
        self.digests: dict[str, str] = self._read()
        self._read_digests = dict(self.digests)

    @property
    def _memo(self) -> Path:
        return self.work.root / "digests" / (
            "roles-" + hashlib.sha256(self.root.encode()).hexdigest()[:32] + ".json")

    def _read(self) -> dict[str, str]:
        if self.stamps is None:
            return {}
        try:
            raw = json.loads(self._memo.read_bytes())
        except (OSError, ValueError):
            return {}
        if not isinstance(raw, dict) or raw.get("format") != ROLES_MEMO_FORMAT \
                or raw.get("session_dir") != self.root or raw.get("stamps") != self.stamps \
                or not isinstance(raw.get("roles"), dict):
            return {}
        return {str(r): d for r, d in raw["roles"].items() if isinstance(d, str)}

    def save(self) -> None:
        """Keep ``digests`` for the next process when they grew. Not for a read-only work
        area, nor while a file is racily fresh (``is_racy``: it may change again within the
        same mtime tick)."""
        if self.stamps is None or self.digests == self._read_digests or self.work.readonly \
                or any(is_racy(stamp[3]) for stamp in self.stamps.values()):
            return
        try:
            _atomic_write(self._memo, json.dumps(
                {"format": ROLES_MEMO_FORMAT, "session_dir": self.root,
                 "stamps": self.stamps, "roles": self.digests}, sort_keys=True).encode())
            self._read_digests = dict(self.digests)
        except OSError:
            pass  # an aid: the next process lists and digests the files again
