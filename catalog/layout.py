"""Where everything of a catalog lives, resolved from its root, and its format stamp."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from graspcap.catalog.errors import CatalogFormatError
from graspcap.schemas.tables import CATALOG_FORMAT_NAME, CATALOG_FORMAT_VERSION

DEFAULT_CATALOG = Path("graspcap-catalog")
"""Where ``graspcap build``, ``status`` and ``serve`` put the catalog unless told: a folder
in the working directory that cannot be mistaken for the source tree's ``catalog/`` package."""


@dataclass(frozen=True)
class CatalogLayout:
    """Every path of a catalog, from its root (a local folder; fsspec URLs are a later step).

    ```
    ROOT/catalog.json                              format stamp
    ROOT/tables/<name>/                            Delta tables (schemas/tables.py)
    ROOT/arrays/<digest[:2]>/<digest>.zarr         content-addressed Zarr v3 groups
    ROOT/arrays/.tmp/                              groups being written (renamed when complete)
    ROOT/.lock                                     writer lock (fcntl.flock)
    ```
    """

    root: Path

    @property
    def format_file(self) -> Path:
        return self.root / "catalog.json"

    @property
    def lock_file(self) -> Path:
        return self.root / ".lock"

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


def write_format_file(layout: CatalogLayout) -> None:
    """Stamp a new catalog (atomically: temp file, then rename)."""
    stamp = {
        "format": CATALOG_FORMAT_NAME,
        "format_version": CATALOG_FORMAT_VERSION,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    tmp = layout.format_file.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(stamp, indent=2) + "\n")
    os.replace(tmp, layout.format_file)


def check_format(layout: CatalogLayout) -> dict:
    """Read ``catalog.json`` and fail with the way forward unless this graspcap reads it."""
    path = layout.format_file
    if not path.is_file():
        raise CatalogFormatError(
            f"{layout.root} is not a graspcap catalog (no catalog.json); "
            "open it with create=True to make a new one")
    try:
        stamp = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CatalogFormatError(f"{path} is not valid JSON: {exc}") from exc
    if stamp.get("format") != CATALOG_FORMAT_NAME:
        raise CatalogFormatError(
            f"{path}: format is {stamp.get('format')!r}, expected {CATALOG_FORMAT_NAME!r}")
    found = stamp.get("format_version")
    if found == CATALOG_FORMAT_VERSION:
        return stamp
    if isinstance(found, int) and found < CATALOG_FORMAT_VERSION:
        raise CatalogFormatError(
            f"catalog {layout.root} was written by catalog format {found}; this graspcap reads "
            f"format {CATALOG_FORMAT_VERSION}. Migrate it with `graspcap catalog migrate "
            f"{layout.root}` (what changed: docs/data_changelog.md), or read it with the "
            f"graspcap release that wrote format {found}")
    if isinstance(found, int):
        raise CatalogFormatError(
            f"catalog {layout.root} was written by catalog format {found}, newer than this "
            f"graspcap reads (format {CATALOG_FORMAT_VERSION}); upgrade graspcap "
            "(`pip install -U graspcap`) to read it (docs/data_changelog.md lists the formats)")
    raise CatalogFormatError(f"{path}: format_version is {found!r}, expected an integer")
