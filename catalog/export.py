"""Export one catalog version as plain files a collaborator reads with pyarrow (or a CSV reader).

``OUT/`` gets, for the version:

- ``sessions``, ``frames``, ``builds``: the tables in the catalog schema (Parquet keeps the
  fixed-size lists and the field metadata with units; CSV writes every list cell as JSON text);
- ``contact``, ``hand_mesh``, ``object_mesh``: one row per Zarr group the version's sessions
  reference, keyed by ``digest`` (join on ``sessions.contact_digest`` etc.); arrays become list
  columns (``vertices`` a list of ``[x, y, z]``, ``faces`` a list of ``[i, j, k]``);
- ``report.html`` and ``pictures/<session>/``: the version's report page
  (``catalog/report_page.py``) beside copies of every session's QA pictures and contact mesh
  (``keypoints.png``, ``reprojection.png``, ``contact.png``, ``strip.png``, ``contact.ply``);
- ``manifest.json``: catalog, version, build, tags, format, files and row counts;
- ``README.md``: the dataset card (``catalog/card.py``: objects, participants, intents, QA
  summary, conventions, units of every column, licence, citation of the method);
- ``stats.json``: normalisation statistics of every numeric column of ``sessions`` and
  ``frames`` and of every array kind (``catalog/stats.py``).

``fmt="lerobot"`` writes a LeRobot v3.0-style layout instead (``catalog/lerobot.py``: Parquet
data, ``meta/info.json``, episodes, tasks, ``meta/stats.json``) with the same ``README.md``.

Every array group is checked against its digest as it is read: a damaged one fails the export
naming the group, the file and the sessions that reference it. Everything is written under
``OUT.partial/`` and renamed to ``OUT`` when complete.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from graspcap.catalog.arrays import DamagedArrayError, array_digest, read_group
from graspcap.catalog.card import DEFAULT_LICENCE, render_card
from graspcap.catalog.errors import CatalogError
from graspcap.catalog.layout import path_name
from graspcap.catalog.lerobot import DEFAULT_FPS, FEATURE_DOCS, feature_specs, write_lerobot
from graspcap.catalog.stats import array_stats, table_stats
from graspcap.schemas.tables import CATALOG_FORMAT_VERSION, DATA_TABLES, ZARR_LAYOUT

if TYPE_CHECKING:
    from graspcap.catalog.store import Catalog

_CSV_BATCH_ROWS = 20_000


class ExportFormat(StrEnum):
    """File format of an export."""

    PARQUET = "parquet"
    CSV = "csv"
    LEROBOT = "lerobot"


@dataclass(frozen=True)
class ExportReport:
    """What ``export_version`` wrote."""

    out: Path
    version: int
    rows: dict[str, int]
    """Rows per written file stem (tables and array kinds)."""
    bytes: int


def _array_type(a: np.ndarray) -> pa.DataType:
    item = pa.from_numpy_dtype(a.dtype)
    return pa.list_(item) if a.ndim == 1 else pa.list_(pa.list_(item, a.shape[1]))


def _as_list_array(arrays: list[np.ndarray]) -> pa.Array:
    """(n_i,) or (n_i, k) numpy arrays as one list column (nested fixed lists for 2-D)."""
    first = arrays[0]
    flat = np.concatenate([a.reshape(-1) for a in arrays])
    values = pa.array(flat, type=pa.from_numpy_dtype(first.dtype))
    if first.ndim == 2:
        values = pa.FixedSizeListArray.from_arrays(values, first.shape[1])
    offsets = np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), values, type=_array_type(first))


def _read_checked(catalog: Catalog, kind: str, digest: str, sessions: pa.Table,
                  column: str) -> dict[str, np.ndarray]:
    """The whole group ``digest``, its content checked against the digest (an export reads
    every array anyway, so this also covers groups written before format 5's manifests); a
    damaged group fails naming it and the sessions that reference it."""
    try:
        arrays = read_group(catalog.layout, digest, tuple(ZARR_LAYOUT[kind].arrays))
        if array_digest(kind, arrays) != digest:
            raise DamagedArrayError(digest, f"array group {digest}: its content does not "
                                    "match its digest (an altered or missing chunk)")
    except DamagedArrayError as exc:
        users = [r["session_id"] for r in sessions.select(["session_id", column]).to_pylist()
                 if r[column] == digest]
        raise DamagedArrayError(digest, f"cannot export {kind} of session(s) "
                                f"{', '.join(users)}: {exc}", array=exc.array,
                                file=exc.file) from exc
    return arrays


def _array_tables(catalog: Catalog, version: int) -> dict[str, pa.Table]:
    """One table per Zarr group kind: ``digest`` plus the group's arrays as list columns."""
    sessions = catalog.table("sessions", version)
    out = {}
    for kind, spec in ZARR_LAYOUT.items():
        digests = sorted(set(sessions[spec.digest_column].drop_null().to_pylist()))
        groups = [_read_checked(catalog, kind, d, sessions, spec.digest_column)
                  for d in digests]
        columns = {"digest": pa.array(digests, pa.string())}
        for name, a_spec in spec.arrays.items():
            if not groups:
                dims = len(a_spec.shape)
                empty = np.zeros((0,) * dims if dims == 1 else (0, a_spec.shape[-1]),
                                 a_spec.dtype)
                columns[name] = pa.array([], _array_type(empty))
            else:
                columns[name] = _as_list_array([g[name] for g in groups])
        out[kind] = pa.table(columns)
    return out


def _is_list(type_: pa.DataType) -> bool:
    return pa.types.is_list(type_) or pa.types.is_fixed_size_list(type_)


def _write_csv(table: pa.Table, path: Path) -> None:
    """CSV with every list cell as JSON text, written in batches."""
    schema = pa.schema([pa.field(f.name, pa.string() if _is_list(f.type) else f.type)
                        for f in table.schema])
    with pacsv.CSVWriter(path, schema) as writer:
        for batch in table.to_batches(max_chunksize=_CSV_BATCH_ROWS):
            cols = [pa.array([None if v is None else json.dumps(v) for v in col.to_pylist()],
                             pa.string()) if _is_list(field.type) else col
                    for field, col in zip(table.schema, batch.columns, strict=True)]
            writer.write_batch(pa.RecordBatch.from_arrays(cols, schema=schema))


def _write_report(catalog: Catalog, v: int, partial: Path) -> int:
    """``report.html`` and ``pictures/<session>/<name>`` (copies of the catalog's pictures of
    version ``v``'s sessions); the number of pictures copied."""
    from graspcap.catalog.report_page import gather, render

    data = gather(catalog, v)
    copied: dict[str, str] = {}
    for entry in data.sessions:
        for name, rel in entry.pictures.items():
            dest = f"pictures/{path_name(entry.session_id)}/{name}"
            (partial / dest).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(catalog.layout.root / rel, partial / dest)
            copied[rel] = dest
    (partial / "report.html").write_text(render(data, copied.__getitem__), encoding="utf-8")
    return len(copied)


def _version_info(catalog: Catalog, v: int) -> dict:
    versions = catalog.versions()
    return versions.to_pylist()[versions["version"].to_pylist().index(v)]


def _frame_counts(frames: pa.Table) -> dict[str, int]:
    counts = frames["session_id"].value_counts().to_pylist()
    return {c["values"]: c["counts"] for c in counts}


def _stats(tables: dict[str, pa.Table], v: int) -> dict:
    """``stats.json``: per table its numeric quantities, per array kind its arrays."""
    arrays: dict[str, dict] = {}
    for kind, spec in ZARR_LAYOUT.items():
        units = {name: a.unit for name, a in spec.arrays.items()}
        arrays.update(array_stats(kind, tables[kind], units))
    return {"version": v, "format_version": CATALOG_FORMAT_VERSION,
            "sessions": table_stats(tables["sessions"]), "frames": table_stats(tables["frames"]),
            "arrays": arrays}


def _write_lerobot(catalog: Catalog, v: int, partial: Path, licence: str, fps: float
                   ) -> tuple[dict[str, int], int]:
    """The LeRobot layout and its card; rows per kind and bytes."""
    sessions, frames = catalog.table("sessions", v), catalog.table("frames", v)
    rows = write_lerobot(sessions, frames, fps, partial)
    files = sorted(str(p.relative_to(partial)) for p in partial.rglob("*") if p.is_file())
    note = (f"LeRobot v3.0-style layout (`meta/info.json`: fps {fps:g}): one episode per "
            "session with frames (failed sessions have none), `episode_index` in session_id "
            "order; `meta/episodes/` maps each episode to its session, object, participant, "
            "intent and status, and gives its hand's scale and shape (`hand_scale`, "
            "`hand_shape`: 20 bone lengths, m). Poses are 16 float64, the row-major 4x4.")
    card = render_card(catalog_uri=catalog.layout.uri, version=v, info=_version_info(catalog, v),
                       sessions=sessions, frame_counts=_frame_counts(frames),
                       schemas={"sessions": sessions.schema, "frames": frames.schema},
                       files=[*files, "README.md"], licence=licence, layout_note=note,
                       features=feature_specs(), feature_docs=FEATURE_DOCS)
    (partial / "README.md").write_text(card, encoding="utf-8")
    size = sum(p.stat().st_size for p in partial.rglob("*") if p.is_file())
    return rows, size


def _write_all(catalog: Catalog, v: int, partial: Path, fmt: ExportFormat, licence: str
               ) -> tuple[dict[str, int], int]:
    """Write every file of the export into ``partial``; return rows per stem and bytes."""
    tables = {name: catalog.table(name, v) for name in DATA_TABLES}
    tables.update(_array_tables(catalog, v))
    rows, files = {}, {}
    for stem, table in tables.items():
        path = partial / f"{stem}.{fmt.value}"
        if fmt is ExportFormat.PARQUET:
            pq.write_table(table, path, compression="zstd")
        else:
            _write_csv(table, path)
        rows[stem] = table.num_rows
        files[stem] = path.name
    pictures = _write_report(catalog, v, partial)
    info = _version_info(catalog, v)
    manifest = {
        "catalog": catalog.layout.uri, "version": v, "build_id": info["build_id"],
        "tags": info["tags"], "committed_utc": info["time_utc"].isoformat(),
        "format_version": CATALOG_FORMAT_VERSION, "file_format": fmt.value,
        "exported_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "files": files, "rows": rows, "report": "report.html", "card": "README.md",
        "stats": "stats.json",
        "pictures": {"folder": "pictures/<session>/", "files": pictures},
        "join": {kind: f"sessions.{spec.digest_column} = {kind}.digest"
                 for kind, spec in ZARR_LAYOUT.items()},
        "encodings": "poses: 16 float64, row-major 4x4, p_a = T_a_b @ p_b; joints: 63 "
                     "(21 x 3, m); 2D joints: 42 (21 x 2, px); arrays in the object frame (m)",
    }
    (partial / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    (partial / "stats.json").write_text(json.dumps(_stats(tables, v), indent=2) + "\n")
    note = ("One file per table (`sessions`, `frames`, `builds`) in the catalog's schema and "
            "one per array kind (`contact`, `hand_mesh`, `object_mesh`: one row per group, "
            "join on `sessions.<kind>_digest = <kind>.digest`); `manifest.json` lists them "
            "with their row counts; `report.html` is the version's QA report page."
            + (" CSV cells of list columns are JSON text." if fmt is ExportFormat.CSV else ""))
    card = render_card(catalog_uri=catalog.layout.uri, version=v, info=info,
                       sessions=tables["sessions"], frame_counts=_frame_counts(tables["frames"]),
                       schemas={name: tables[name].schema for name in DATA_TABLES},
                       files=[*files.values(), "manifest.json", "stats.json", "report.html",
                              "pictures/<session>/", "README.md"],
                       licence=licence, layout_note=note)
    (partial / "README.md").write_text(card, encoding="utf-8")
    size = sum(p.stat().st_size for p in partial.rglob("*") if p.is_file())
    return rows, size


def export_version(catalog: Catalog, version: int | str | None, out: str | Path,
                   fmt: ExportFormat | str = ExportFormat.PARQUET, *,
                   licence: str = DEFAULT_LICENCE, fps: float = DEFAULT_FPS) -> ExportReport:
    """Write ``version`` of ``catalog`` to the new folder ``out`` (module docstring);
    ``licence`` goes into the card, ``fps`` (the grasp videos' frame rate, which the catalog
    does not record) into the LeRobot layout's timestamps."""
    fmt = ExportFormat(fmt)
    if not fps > 0:
        raise CatalogError(f"fps must be > 0, got {fps}")
    v = catalog.resolve(version)
    out = Path(out).expanduser().resolve()
    if out.exists():
        raise CatalogError(f"{out} exists; export writes a new folder")
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        if fmt is ExportFormat.LEROBOT:
            rows, size = _write_lerobot(catalog, v, partial, licence, fps)
        else:
            rows, size = _write_all(catalog, v, partial, fmt, licence)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    partial.rename(out)
    return ExportReport(out, v, rows, size)
