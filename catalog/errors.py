"""Errors of the catalog, each with a message that says what to do next."""

from __future__ import annotations

import errno
from collections.abc import Iterator
from contextlib import contextmanager


class CatalogError(Exception):
    """Any failure to read or write a catalog."""


class CatalogFormatError(CatalogError):
    """The folder is not a catalog this graspcap can read (another format version)."""


class CatalogSchemaError(CatalogError, ValueError):
    """A batch does not match the table's schema; names the table, the column and the session."""

    def __init__(self, table: str, column: str | None, sessions: list[str], reason: str):
        self.table = table
        self.column = column
        self.sessions = sessions
        where = f"table {table!r}"
        if column is not None:
            where += f", column {column!r}"
        if sessions:
            shown = ", ".join(repr(s) for s in sessions[:3])
            more = f" (+{len(sessions) - 3} more)" if len(sessions) > 3 else ""
            where += f", session {shown}{more}"
        super().__init__(f"{where}: {reason}")


class CatalogLockTimeout(CatalogError):
    """Another writer held the catalog's lock for longer than the timeout."""


class VersionNotFound(CatalogError, KeyError):
    """No such catalog version or tag."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0])


class CatalogDamaged(CatalogError):
    """Files of the catalog are missing or unreadable; ``problems`` has one line per problem.

    Writers stop on it (nothing is guessed or rolled back over it); readers of the versions
    that do not need the damaged files keep working.
    """

    def __init__(self, uri: str, problems: list[str], repair: str):
        self.problems = list(problems)
        self.repair = repair
        super().__init__("\n".join([f"catalog {uri} is damaged: {len(problems)} problem(s)",
                                    *self.problems, f"repair: {repair}"]))


class CatalogDiskFull(CatalogError, OSError):
    """No space left writing a catalog or work-area file (``errno`` ENOSPC); names the path.

    Also an ``OSError``, so handlers of I/O errors see it as one.
    """

    def __init__(self, path: object, detail: str = ""):
        self.path = str(path)
        message = f"disk full writing {self.path}"
        if detail:
            message += f" ({detail})"
        message += ("; nothing of this write was committed and every earlier catalog version "
                    "is intact: free space and run again")
        super().__init__(errno.ENOSPC, message)

    def __str__(self) -> str:  # OSError would prefix "[Errno 28]"
        return str(self.args[1])


def is_disk_full(exc: BaseException) -> bool:
    """True for ENOSPC: an ``OSError`` with that errno, or deltalake's/zarr's wrapped text."""
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return True
    text = str(exc)
    return "No space left on device" in text or "os error 28" in text


@contextmanager
def writing(path: object) -> Iterator[None]:
    """Turn an ENOSPC raised inside the block into ``CatalogDiskFull`` naming ``path``."""
    try:
        yield
    except CatalogDiskFull:
        raise
    except Exception as exc:
        if is_disk_full(exc):
            raise CatalogDiskFull(path, _first_line(exc)) from exc
        raise


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__
