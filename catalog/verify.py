"""Check that a catalog version can be read exactly as committed (``graspcap catalog verify``).

A version needs the Parquet files of each data table at its pinned Delta version and every
array group its ``sessions`` rows reference. ``verify_version`` checks that each of those
files exists and is a readable Parquet file (its footer), and that each group is whole: every
file its manifest lists present with the recorded sha256, the group decodable, and its content
matching its digest (``graspcap.catalog.arrays.verify_group``). What it finds is listed, with
the sessions that reference a damaged group; nothing is repaired. The normal read path checks
less (the manifest of the arrays it reads, not the digest; docs/catalog.md, "Integrity").
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import pyarrow.parquet as pq

from graspcap.catalog.arrays import verify_group
from graspcap.catalog.delta import read_files, table_files
from graspcap.schemas.tables import DATA_TABLES, ZARR_LAYOUT

if TYPE_CHECKING:
    from graspcap.catalog.store import Catalog

VERIFY_THREADS = 4
"""Array groups checked at once (each mostly waits on reading its files)."""


@dataclass(frozen=True)
class Damage:
    """One thing a version needs that is missing or wrong."""

    kind: str
    """``table`` or ``array``."""
    name: str
    """The table's name, or the array group's digest."""
    problem: str
    """What is wrong, naming the file."""
    sessions: tuple[str, ...] = ()
    """Sessions whose rows reference the damaged array group."""
    group_kind: str | None = None
    """The array group's kind (contact, hand_mesh, object_mesh)."""

    def line(self) -> str:
        if self.kind == "table":
            return f"table {self.name}: {self.problem}"
        used = ", ".join(self.sessions) or "-"
        return (f"array {self.group_kind or ''} {self.name}: {self.problem} "
                f"(referenced by session(s) {used})")


@dataclass(frozen=True)
class VerifyReport:
    """What ``verify_version`` checked and found."""

    version: int
    table_files: dict[str, int]
    """Parquet files checked per table."""
    arrays: int
    """Array groups checked."""
    damaged: list[Damage] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.damaged

    def as_dict(self) -> dict:
        return {"version": self.version, "ok": self.ok, "table_files": self.table_files,
                "arrays": self.arrays,
                "damaged": [{"kind": d.kind, "name": d.name, "group_kind": d.group_kind,
                             "problem": d.problem, "sessions": list(d.sessions)}
                            for d in self.damaged]}


def _check_file(cat: Catalog, path: str) -> str | None:
    """What is wrong with one Parquet file of a table (None: nothing)."""
    layout = cat.layout
    fs_path = path if layout.is_local else layout.fs._strip_protocol(path)
    try:
        with layout.fs.open(fs_path, "rb") as fh:
            pq.ParquetFile(fh).metadata  # noqa: B018 - reading the footer is the check
    except FileNotFoundError:
        return f"file {path} is missing"
    except (OSError, ValueError) as exc:  # pyarrow's ArrowInvalid is a ValueError
        return f"file {path} is not a readable Parquet file ({exc})"
    return None


def verify_version(cat: Catalog, version: int | str | None = None) -> VerifyReport:
    """Check every file ``version`` (default: the newest published) needs (module docstring)."""
    v = cat.resolve(version)
    pins = cat._pinned(v)
    damaged: list[Damage] = []
    counts: dict[str, int] = {}
    sessions_ok = True
    session_files: list[str] = []
    for name in DATA_TABLES:
        try:
            files = table_files(cat.layout, name, pins[name])
        except Exception as exc:  # noqa: BLE001 - a damaged Delta log is damage to report
            damaged.append(Damage("table", name, f"Delta version {pins[name]} cannot be "
                                  f"listed ({type(exc).__name__}: {exc})"))
            sessions_ok &= name != "sessions"
            continue
        counts[name] = len(files)
        for path in files:
            problem = _check_file(cat, path)
            if problem:
                damaged.append(Damage("table", name, problem))
                sessions_ok &= name != "sessions"
        if name == "sessions":
            session_files = files

    users: dict[str, tuple[str, list[str]]] = {}
    if sessions_ok:
        cols = ["session_id", *(spec.digest_column for spec in ZARR_LAYOUT.values())]
        rows = read_files("sessions", session_files, cols, cat.layout).to_pylist()
        for kind, spec in ZARR_LAYOUT.items():
            for r in rows:
                if r[spec.digest_column]:
                    users.setdefault(r[spec.digest_column], (kind, []))[1].append(
                        r["session_id"])
    else:
        damaged.append(Damage("table", "sessions", "unreadable at this version, so the array "
                              "groups it references were not checked"))
    digests = sorted(users)
    with ThreadPoolExecutor(max_workers=VERIFY_THREADS) as pool:
        found = list(pool.map(lambda d: verify_group(cat.layout, d, users[d][0]), digests))
    for digest, problems in zip(digests, found, strict=True):
        kind, sessions = users[digest]
        damaged.extend(Damage("array", digest, p, tuple(sorted(sessions)), kind)
                       for p in problems)
    return VerifyReport(v, counts, len(digests), damaged)
