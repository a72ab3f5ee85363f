"""Errors of the catalog, each with a message that says what to do next."""

from __future__ import annotations


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
