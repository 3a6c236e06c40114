"""Fingerprint histograms as pure array code: RSSI counts per bin, normalisation, and binning of
position-annotated (moving) readings into grid cells. No file I/O here (see annotator.io.radio_data).

Binning follows ``numpy.histogram`` on the edges, as the published .hst files were made: bins are
half-open ``[e_k, e_k+1)`` except the last, which is closed, and readings outside ``[e_0, e_K]``
are dropped before normalising.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

_NAME = re.compile(
    r"^(?P<alias>.+?)_(?P<x>-?\d+(?:\.\d+)?)_(?P<y>-?\d+(?:\.\d+)?)"
    r"_(?P<z>-?\d+(?:\.\d+)?)\.mbd$"
)


def rssi_edges(lo: int = -100, hi: int = -20) -> np.ndarray:
    """Edges ``lo, lo+1, ..., hi``: one bin per integer dBm (``hi - lo`` bins)."""
    if hi <= lo:
        raise ValueError(f"empty RSSI range {lo}:{hi}")
    return np.arange(lo, hi + 1, dtype=float)


def parse_range(text: str) -> tuple[int, int]:
    """``'-100:-20'`` -> ``(-100, -20)``."""
    lo, sep, hi = text.partition(":")
    try:
        a, b = int(lo), int(hi if sep else "")
    except ValueError:
        raise ValueError(
            f"bins must be 'LO:HI' in integer dBm, e.g. -100:-20, got {text!r}"
        ) from None
    if b <= a:
        raise ValueError(f"bins {text!r}: HI must be greater than LO")
    return a, b


def counts(rssi: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Readings per bin (int64, ``len(edges) - 1`` entries); out-of-range readings are not counted."""
    c, _ = np.histogram(np.asarray(rssi, dtype=float), bins=edges)
    return c.astype(np.int64)


def normalise(c: np.ndarray) -> np.ndarray:
    """Counts -> probabilities summing to 1 along the last axis; all-NaN where there is nothing
    to normalise (an explicit gap rather than a histogram of zeros)."""
    c = np.asarray(c, dtype=float)
    total = c.sum(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, c / np.where(total > 0, total, 1.0), np.nan)


def histogram(rssi: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Normalised histogram of one sensor's readings of one beacon (NaN if none fall in range)."""
    return normalise(counts(rssi, edges))


def parse_fingerprint_name(name: str) -> tuple[str, tuple[float, float, float]]:
    """``'sensor10_12.95_16.80_1.85.mbd'`` -> ``('sensor10', (12.95, 16.8, 1.85))``."""
    m = _NAME.match(name)
    if not m:
        raise ValueError(f"{name}: expected '<alias>_<x>_<y>_<z>.mbd'")
    return m["alias"], (float(m["x"]), float(m["y"]), float(m["z"]))


@dataclass(frozen=True, slots=True)
class CellBins:
    """Readings grouped by grid cell: ``cell[i]`` is the (ix, iy) index of reading i (-1 when
    its position is unknown), ``centres`` the centre of each occupied cell."""

    cell: np.ndarray  # (N, 2) int64
    keys: np.ndarray  # (M, 2) int64 unique occupied cells, sorted by (iy, ix)
    inverse: np.ndarray  # (N,) index into keys, -1 for readings without a position


def bin_to_cells(xy: np.ndarray, cell: float, origin: tuple[float, float] = (0.0, 0.0)) -> CellBins:
    """Assign each (x, y) to the grid cell ``floor((p - origin) / cell)``. NaN positions get -1."""
    if not cell > 0:
        raise ValueError(f"cell size must be positive, got {cell}")
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    ok = np.isfinite(xy).all(axis=1)
    idx = np.full((len(xy), 2), -1, dtype=np.int64)
    # the tiny epsilon keeps a point that sits exactly on a boundary (0.5 m at 0.5 m cells) in the
    # upper cell despite 0.1 + 0.4 style rounding
    idx[ok] = np.floor((xy[ok] - np.asarray(origin)) / cell + 1e-9).astype(np.int64)
    inverse = np.full(len(xy), -1, dtype=np.int64)
    if ok.any():
        keys, inv = np.unique(idx[ok][:, ::-1], axis=0, return_inverse=True)
        keys = keys[:, ::-1]
        inverse[ok] = inv.ravel()
    else:
        keys = np.zeros((0, 2), dtype=np.int64)
    return CellBins(idx, keys, inverse)


def cell_counts(
    rssi: np.ndarray, group: np.ndarray, n_groups: int, edges: np.ndarray
) -> np.ndarray:
    """Counts per group and bin, ``(n_groups, len(edges) - 1)``; readings with group -1 or outside
    the bin range are ignored. Same bin rule as :func:`counts`."""
    rssi = np.asarray(rssi, dtype=float)
    group = np.asarray(group, dtype=np.int64)
    k = len(edges) - 1
    b = np.searchsorted(edges, rssi, side="right") - 1
    b = np.where(rssi == edges[-1], k - 1, b)  # last bin closed, as numpy.histogram
    ok = (group >= 0) & (b >= 0) & (b < k)
    out = np.zeros((n_groups, k), dtype=np.int64)
    np.add.at(out, (group[ok], b[ok]), 1)
    return out
