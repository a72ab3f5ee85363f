"""Pure, Prefect-free pipeline stages: typed records in, typed records out."""
