"""Prefect flows: thin tasks over the pure stages in `graspcap.tasks`."""
