"""The versioned Parquet + Zarr catalog (readers never need Prefect)."""
