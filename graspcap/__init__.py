"""graspcap: markerless grasp capture sessions -> a versioned training dataset."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("graspcap")
except PackageNotFoundError:  # pragma: no cover - running from an uninstalled tree
    __version__ = "0+unknown"
