"""Where everything of a catalog lives, resolved from its root, and its format stamp."""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import cached_property
from pathlib import Path, PurePosixPath
from typing import Any

import fsspec

from graspcap.catalog.errors import CatalogError, CatalogFormatError, writing
from graspcap.schemas.tables import CATALOG_FORMAT_NAME, CATALOG_FORMAT_VERSION

DEFAULT_CATALOG = Path("graspcap-catalog")
"""Where ``graspcap build``, ``status`` and ``serve`` put the catalog unless told: a folder
in the working directory that cannot be mistaken for the source tree's ``catalog/`` package."""


LOCAL_SCHEMES = ("", "file", "local")
"""URL schemes that name a local folder: ``/data/cat``, ``file:///data/cat``."""
DELTA_SCHEMES = ("s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl")
"""Object stores deltalake reads itself (its storage_options take the credentials)."""
MIGRATIONS_FROM = (1, 2, 3, 4, 5, 6)
"""Older formats ``graspcap catalog migrate`` upgrades (``graspcap.catalog.migrate``)."""
PLAIN_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,127}")
"""Session ids used as folder names as they are: the contract's character set, 1-128
characters, not starting with '.' (so never ``.``, ``..`` or a hidden name)."""


def path_name(session_id: str) -> str:
    """A file-system name for ``session_id``, which is data, never a path: an id matching
    :data:`PLAIN_NAME` is its own name; any other (``a/b``, ``../x``, 300 characters, a
    newline or NUL) is its safe characters (at most 40, '/' and the like as '_') then ``~``
    and 24 hex digits of its sha256. ``~`` is outside :data:`PLAIN_NAME`, so an encoded name
    never equals a plain one, and two ids share a name only if their hashes collide."""
    if PLAIN_NAME.fullmatch(session_id):
        return session_id
    readable = re.sub(r"[^A-Za-z0-9._-]", "_", session_id)[:40].lstrip(".")
    digest = hashlib.sha256(session_id.encode("utf-8", "surrogatepass")).hexdigest()[:24]
    return f"{readable}~{digest}"


def child_path(parent: Path, session_id: str) -> Path:
    """``parent / path_name(session_id)``, checked to stay directly inside ``parent``."""
    path = parent / path_name(session_id)
    if path.parent != parent or path.name in ("", ".", ".."):
        raise CatalogError(f"session id {session_id!r} maps to {path}, outside {parent}")
    return path


def parse_uri(uri: str | Path) -> tuple[Path | None, str | None]:
    """``(local folder, None)`` for a path or ``file://`` URL, ``(None, url)`` for an object store.

    Fails for schemes the catalog cannot serve: fsspec's ``memory://`` (deltalake keeps its
    own in-memory store, invisible to fsspec) and anything deltalake has no store for.
    """
    text = str(uri)
    scheme = text.split("://", 1)[0].lower() if "://" in text else ""
    if scheme in LOCAL_SCHEMES:
        local = text.split("://", 1)[1] if scheme else text
        return Path(local).expanduser().resolve(), None
    if scheme in DELTA_SCHEMES:
        return None, text.rstrip("/")
    raise CatalogError(
        f"{text}: catalogs open from a local path, file://, or an object store deltalake "
        f"supports ({', '.join(s + '://' for s in DELTA_SCHEMES)}); {scheme}:// is not one "
        "(memory:// cannot work: deltalake's Delta tables never see fsspec's memory)")


@dataclass(frozen=True)
class CatalogLayout:
    """Every path of a catalog, from its root: a local folder, or ``url`` on an object store.

    ```
    ROOT/catalog.json                              format stamp
    ROOT/tables/<name>/                            Delta tables (schemas/tables.py)
    ROOT/arrays/<digest[:2]>/<digest>.zarr         content-addressed Zarr v3 groups
    ROOT/arrays/.tmp/                              groups being written (renamed when complete)
    ROOT/.lock                                     writer lock (fcntl.flock)
    ROOT/published.json                            newest published version (recovery's evidence)
    ROOT/vacuum.jsonl                              one line per vacuum: the versions it dropped
    ROOT/pictures/<sha256[:2]>/<sha256>.<png|ply>  QA pictures and contact meshes, by content
    ROOT/reports/<path_name(build_id)>/index.html  a build's report page (graspcap report)
    ```

    Readers go through ``uri``-based paths and ``fs`` (fsspec), so the same code reads a local
    folder and an object store; writers (commit, tag, vacuum, migrate) need a local folder
    (``require_local``): their lock is ``fcntl.flock`` and their arrays are renamed into place.
    """

    root: Path
    """The local folder (for an object store: the URL's path, never used for I/O)."""
    url: str | None = None
    """The object-store URL, None for a local catalog."""
    storage_options: dict[str, str] = field(default_factory=dict, compare=False, hash=False)
    """Credentials and settings for deltalake and fsspec (object stores only)."""

    @classmethod
    def from_uri(cls, uri: str | Path, storage_options: dict[str, str] | None = None
                 ) -> CatalogLayout:
        local, url = parse_uri(uri)
        if local is not None:
            return cls(local)
        return cls(PurePosixPath(url.split("://", 1)[1]), url, dict(storage_options or {}))

    @property
    def is_local(self) -> bool:
        return self.url is None

    @property
    def uri(self) -> str:
        """The root as a string deltalake and fsspec both take."""
        return str(self.root) if self.url is None else self.url

    @cached_property
    def fs(self) -> Any:
        """An fsspec filesystem for the root (``LocalFileSystem`` for a local catalog)."""
        if self.url is None:
            return fsspec.filesystem("file")
        return fsspec.core.url_to_fs(self.url, **self.storage_options)[0]

    def fs_path(self, *parts: str) -> str:
        """A path under the root as ``fs`` names it."""
        base = str(self.root) if self.url is None else self.fs._strip_protocol(self.url)
        return "/".join([base.rstrip("/"), *parts])

    def table_uri(self, name: str) -> str:
        """The Delta table of ``name`` as deltalake takes it (with ``storage_options``)."""
        return f"{self.uri}/tables/{name}"

    def group_fs_path(self, digest: str) -> str:
        """The Zarr group of ``digest`` as ``fs`` names it."""
        return self.fs_path("arrays", digest[:2], f"{digest}.zarr")

    def require_local(self, action: str) -> None:
        """Fail unless the catalog is a local folder (writers need ``flock`` and ``rename``)."""
        if self.url is not None:
            raise CatalogError(
                f"{action} needs a local catalog (its writer lock is fcntl.flock and arrays "
                f"are renamed into place); {self.url} is an object store, which this graspcap "
                "only reads. Write to a local folder and sync it, see docs/architecture.md")

    @property
    def format_file(self) -> Path:
        return self.root / "catalog.json"

    @property
    def lock_file(self) -> Path:
        return self.root / ".lock"

    @property
    def published_file(self) -> Path:
        """The newest version a writer saw published, with its pins: written after each
        ``versions`` row, so recovery can tell a lost row from a killed writer's orphans."""
        return self.root / "published.json"

    @property
    def vacuum_log(self) -> Path:
        """One JSON line per vacuum (time, kept and dropped versions)."""
        return self.root / "vacuum.jsonl"

    @property
    def arrays_dir(self) -> Path:
        return self.root / "arrays"

    @property
    def arrays_tmp(self) -> Path:
        return self.arrays_dir / ".tmp"

    def table(self, name: str) -> Path:
        """The Delta table folder of ``name`` (sessions, frames, builds, versions, tags)."""
        return self.root / "tables" / name

    def array_group(self, digest: str) -> Path:
        """The Zarr group holding the arrays of ``digest`` (a sha256 hex string)."""
        return self.arrays_dir / digest[:2] / f"{digest}.zarr"

    @property
    def pictures_root(self) -> Path:
        return self.root / "pictures"

    def picture_file(self, digest: str, suffix: str) -> Path:
        """A QA picture (or contact mesh) by the sha256 hex ``digest`` of its bytes, e.g.
        ``pictures/3f/3f...e1.png``: content-addressed, so every build's pictures stay (the
        report of an old version still shows its own) and an unchanged session's pictures are
        stored once. Which session and build a file belongs to is in the build records
        (``SessionReport.pictures``)."""
        if not re.fullmatch(r"[0-9a-f]{64}", digest) or suffix not in PICTURE_SUFFIXES:
            raise CatalogError(f"not a picture digest and suffix: {digest!r}, {suffix!r}")
        return self.pictures_root / digest[:2] / f"{digest}{suffix}"

    @property
    def reports_root(self) -> Path:
        return self.root / "reports"

    def report_dir(self, build_id: str) -> Path:
        """The folder of build ``build_id``'s report page (:func:`path_name` of the id)."""
        return child_path(self.reports_root, build_id)

    def report_file(self, build_id: str) -> Path:
        """Build ``build_id``'s report page, a static HTML file that opens from disk."""
        return self.report_dir(build_id) / "index.html"


PICTURE_SUFFIXES = (".png", ".ply")
"""File types of the content-addressed pictures (``CatalogLayout.picture_file``)."""


def write_format_file(layout: CatalogLayout, version: int = CATALOG_FORMAT_VERSION) -> None:
    """Stamp a catalog as format ``version`` (atomically: temp file, then rename)."""
    layout.require_local("stamping a catalog")
    stamp = {
        "format": CATALOG_FORMAT_NAME,
        "format_version": version,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    tmp = layout.format_file.with_suffix(".json.tmp")
    try:
        with writing(layout.format_file):
            tmp.write_text(json.dumps(stamp, indent=2) + "\n")
            os.replace(tmp, layout.format_file)
    finally:
        tmp.unlink(missing_ok=True)


FORMAT_FILE_MAX_BYTES = 1 << 16
FORMAT_REPAIR = ("write it again: " + json.dumps({"format": CATALOG_FORMAT_NAME,
                                                  "format_version": CATALOG_FORMAT_VERSION})
                 + " (with the format_version the catalog's versions table lists last)")


def read_format(layout: CatalogLayout) -> dict:
    """The stamp in ``catalog.json``, or ``CatalogFormatError`` when it is missing or unreadable."""
    path = layout.fs_path("catalog.json")
    try:
        data = layout.fs.cat_file(path)
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise CatalogFormatError(
            f"{layout.uri} is not a graspcap catalog (no catalog.json); "
            "`graspcap build ... --catalog` creates one there (in Python: "
            "graspcap.catalog.open(..., create=True))") from None
    except OSError as exc:
        raise CatalogFormatError(f"{path} cannot be read: {exc}") from None
    if len(data) > FORMAT_FILE_MAX_BYTES:
        raise CatalogFormatError(f"{path} is {len(data)} bytes, not a catalog stamp (a few "
                                 f"hundred bytes of JSON): {FORMAT_REPAIR}")
    try:
        stamp = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise CatalogFormatError(f"{path} is not UTF-8 text (byte {exc.start}): "
                                 f"{FORMAT_REPAIR}") from None
    except (json.JSONDecodeError, RecursionError) as exc:
        raise CatalogFormatError(f"{path} is not valid JSON ({exc}): {FORMAT_REPAIR}") from None
    if not isinstance(stamp, dict) or stamp.get("format") != CATALOG_FORMAT_NAME:
        found = stamp.get("format") if isinstance(stamp, dict) else stamp
        raise CatalogFormatError(
            f"{path}: format is {str(found)[:100]!r}, expected {CATALOG_FORMAT_NAME!r}")
    if type(stamp.get("format_version")) is not int:  # bool is an int too
        raise CatalogFormatError(
            f"{path}: format_version is {str(stamp.get('format_version'))[:100]!r}, expected an "
            "integer")
    return stamp


def check_format(layout: CatalogLayout) -> dict:
    """Read ``catalog.json`` and fail with the way forward unless this graspcap reads it."""
    stamp = read_format(layout)
    found = stamp["format_version"]
    if found == CATALOG_FORMAT_VERSION:
        return stamp
    if found < CATALOG_FORMAT_VERSION and found in MIGRATIONS_FROM:
        raise CatalogFormatError(
            f"catalog {layout.uri} was written by catalog format {found}; this graspcap reads "
            f"format {CATALOG_FORMAT_VERSION}. Migrate it with `graspcap catalog migrate "
            f"{layout.uri}` (in place; `--out NEW` upgrades a copy instead; what changed: "
            f"docs/data_changelog.md), or read it with the graspcap release that wrote "
            f"format {found}")
    if found < CATALOG_FORMAT_VERSION:
        raise CatalogFormatError(
            f"catalog {layout.uri} was written by catalog format {found}, which no graspcap "
            f"release migrates (formats {list(MIGRATIONS_FROM)} migrate); rebuild it from its "
            "sessions with `graspcap build SESSIONS --catalog NEW` (docs/data_changelog.md)")
    raise CatalogFormatError(
        f"catalog {layout.uri} was written by catalog format {found}, newer than this "
        f"graspcap reads (format {CATALOG_FORMAT_VERSION}); upgrade graspcap "
        "(`pip install -U graspcap`) to read it (docs/data_changelog.md lists the formats)")
