"""Errors a stage raises on purpose, with a reason a person can act on."""

from __future__ import annotations


class StageError(Exception):
    """A deterministic failure (bad input, a solver that cannot converge).

    Never retried: running the same stage on the same input fails the same way.
    The message names the session, file and field where they are known.
    """

    def __init__(self, stage: str, reason: str, *, session: str | None = None):
        self.stage = stage
        self.reason = reason
        self.session = session
        where = f"session {session}: " if session else ""
        super().__init__(f"{where}{stage}: {reason}")
