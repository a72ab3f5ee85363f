"""The versioned Parquet + Zarr catalog (readers never need Prefect).

    import graspcap.catalog as gc
    cat = gc.open("CATALOG")
    frames = cat.table("frames", version="paper-v1")      # pyarrow.Table
    values, observed = cat.contactmap("p03-mug-use-01")

Contract (columns, encodings, Zarr layout, format version): ``graspcap.schemas.tables``.
"""

from graspcap.catalog.arrays import DamagedArrayError
from graspcap.catalog.audit import AuditGates
from graspcap.catalog.collate import collate_fn
from graspcap.catalog.commit import BuildCommit, BuildInfo, ObjectMesh, SessionArrays
from graspcap.catalog.dataset import GraspDataset
from graspcap.catalog.errors import (
    CatalogError,
    CatalogFormatError,
    CatalogLockTimeout,
    CatalogSchemaError,
    VersionNotFound,
)
from graspcap.catalog.store import Catalog, open  # noqa: A004
from graspcap.catalog.vacuum import VacuumReport

__all__ = [
    "AuditGates", "BuildCommit", "BuildInfo", "Catalog", "CatalogError", "CatalogFormatError",
    "CatalogLockTimeout", "CatalogSchemaError", "DamagedArrayError", "GraspDataset",
    "ObjectMesh", "SessionArrays", "VacuumReport", "VersionNotFound", "collate_fn", "open",
]
