"""A planned path's file, ``path.yaml``: ``waypoints: [[x, y], ...]`` in room metres (what
`annotator simulate` writes for polyline paths and `annotator evaluate --path` reads)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from annotator.errors import ConfigError
from bgt_core.keys import unknown_key


def load_waypoints(path: Path) -> np.ndarray:
    """PATH.yaml: ``waypoints: [[x, y], ...]`` (at least two); ConfigError names what is wrong."""
    from bgt_core.safe_yaml import YamlError, load_file

    try:
        obj = load_file(path)
    except YamlError as e:
        raise ConfigError(f"path: {e}") from None
    if isinstance(obj, dict) and (message := unknown_key(obj, ("waypoints",), str(path))):
        raise ConfigError(message)
    wp = obj.get("waypoints") if isinstance(obj, dict) else None
    try:
        arr = np.array(wp, dtype=float)
    except (TypeError, ValueError):
        arr = np.zeros((0,))
    if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 2 or not np.isfinite(arr).all():
        raise ConfigError(f"{path}: 'waypoints' must be a list of at least two [x, y] pairs")
    if np.any(np.linalg.norm(np.diff(arr, axis=0), axis=1) == 0):
        raise ConfigError(f"{path}: two consecutive waypoints are the same point")
    return arr
