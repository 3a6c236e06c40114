"""Shared core of ble-groundtruth: the wire format, dataset file formats and built-in sites."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ble-groundtruth")
except PackageNotFoundError:  # running from a source tree without installing
    __version__ = "0.0.0+unknown"
