"""Finding capture sessions under roots, and the folders beside them that are not sessions."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

MANIFEST = "session.json"

NOT_A_SESSION = "not a session: no session.json"
"""What ``graspcap validate`` says of a folder in :attr:`Discovery.not_sessions`."""


@dataclass(frozen=True)
class Discovery:
    """What :func:`discover` found under the roots."""

    sessions: list[Path]
    """Session directories (holding ``session.json``), sorted, without duplicates."""
    not_sessions: list[Path]
    """Folders without ``session.json`` and without a session below them that sit beside
    sessions (their parent holds a session at or below it): most likely a session whose
    manifest is missing. A folder holding other sessions' parents is not one, nor anything
    inside a reported folder, nor a folder whose name starts with ``.``; sorted."""


def discover(roots: Sequence[Path]) -> Discovery:
    """Session directories at or below ``roots``, and the folders among them that are not
    sessions (see :class:`Discovery`).

    A directory holding ``session.json`` is a session (nothing below it is searched);
    otherwise its subdirectories are. A root without sessions (or that is not a directory)
    contributes nothing.
    """
    found: dict[Path, Path] = {}
    walked: list[tuple[Path, Path]] = []  # (directory, its root), directories without manifest
    for root in map(Path, roots):
        for current, dirs, files in os.walk(root):
            if MANIFEST in files:
                found.setdefault(Path(current).resolve(), Path(current))
                dirs.clear()
            else:
                walked.append((Path(current), root))
            dirs.sort()
    holding: set[Path] = set()  # directories with a session at or below them
    for session in found.values():
        holding.update(session.parents)
    lonely = {d for d, root in walked
              if d != root and d not in holding and d.parent in holding
              and not d.name.startswith(".")}
    not_sessions = {d.resolve(): d for d in lonely}
    for real in list(not_sessions):
        if real in found:
            del not_sessions[real]
    return Discovery(sorted(found.values()), sorted(not_sessions.values()))


def discover_sessions(roots: Sequence[Path]) -> list[Path]:
    """Session directories at or below ``roots``, sorted and without duplicates
    (:attr:`Discovery.sessions` of :func:`discover`)."""
    return discover(roots).sessions
