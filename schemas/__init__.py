"""Contracts: the capture-session manifest, catalog table schemas, Zarr layout, format versions."""
