"""Printable ArUco marker pages: one marker per page at true size, drawn as vector rectangles.

The page (figure) size is the paper size in inches and the marker's axes are placed in inches,
so the printed black square is exactly the requested length when printed at 100 %.
"""

from __future__ import annotations

import cv2
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from annotator.errors import ConfigError

INCH = 0.0254
# ISO 216 portrait sizes, metres.
PAPERS = {
    "A4": (0.210, 0.297),
    "A3": (0.297, 0.420),
    "A2": (0.420, 0.594),
    "A1": (0.594, 0.841),
    "A0": (0.841, 1.189),
}
SIDE_MARGIN = 0.012  # printers cannot print to the edge; also the white quiet zone
LABEL_SPACE = 0.055  # below the marker: id line and 10 cm scale bar
SCALE_BAR = 0.100


def parse_ids(text: str) -> list[int]:
    """'0-3,7' -> [0, 1, 2, 3, 7]; ConfigError on anything else."""
    ids: list[int] = []
    bad = ConfigError(f"--ids {text!r}: expected ids and ranges like 0-29 or 0,3,5-7")
    for part in text.split(","):
        lo_text, _, hi_text = part.strip().partition("-")
        try:
            lo = int(lo_text)
            hi = int(hi_text) if hi_text else lo
        except ValueError:
            raise bad from None
        if hi < lo:
            raise bad
        ids.extend(range(lo, hi + 1))
    return list(dict.fromkeys(ids))


def marker_cells(dictionary: str, marker_id: int) -> np.ndarray:
    """Bool grid of black cells, black border included (8x8 for a 6x6 dictionary)."""
    code = getattr(cv2.aruco, dictionary, None)
    if not dictionary.startswith("DICT_") or not isinstance(code, int):
        raise ConfigError(f"unknown ArUco dictionary {dictionary!r} (e.g. DICT_6X6_50)")
    d = cv2.aruco.getPredefinedDictionary(code)
    n_markers = d.bytesList.shape[0]
    if marker_id >= n_markers:
        raise ConfigError(f"marker id {marker_id} is not in {dictionary} (ids 0-{n_markers - 1})")
    cells = d.markerSize + 2
    return cv2.aruco.generateImageMarker(d, marker_id, cells, borderBits=1) < 128


def choose_paper(length: float, paper: str = "auto") -> str:
    """The smallest ISO paper (or the asked one) holding the marker, its margins and labels."""

    def fits(name: str) -> bool:
        w, h = PAPERS[name]
        return length + 2 * SIDE_MARGIN <= w and length + 2 * SIDE_MARGIN + LABEL_SPACE <= h

    if paper.lower() != "auto":
        name = paper.upper()
        if name not in PAPERS:
            raise ConfigError(f"--paper {paper!r}: expected auto or one of {', '.join(PAPERS)}")
        if not fits(name):
            raise ConfigError(
                f"a {length * 1000:.0f} mm marker does not fit on {name}; try a larger --paper"
            )
        return name
    for name in PAPERS:
        if fits(name):
            return name
    raise ConfigError(f"a {length * 1000:.0f} mm marker is larger than A0 paper")


def marker_page(
    marker_id: int, length: float, dictionary: str, paper: str
) -> tuple[Figure, tuple[float, float, float, float]]:
    """One page; returns the figure and the marker's black-square box (left, bottom, w, h) in metres."""
    pw, ph = PAPERS[paper]
    fig = Figure(figsize=(pw / INCH, ph / INCH))
    left = (pw - length) / 2
    bottom = ph - SIDE_MARGIN - 0.01 - length
    ax = fig.add_axes((left / pw, bottom / ph, length / pw, length / ph))
    cells = marker_cells(dictionary, marker_id)
    n = cells.shape[0]
    for r in range(n):
        c = 0
        while c < n:  # one rectangle per horizontal run of black cells
            if not cells[r, c]:
                c += 1
                continue
            start = c
            while c < n and cells[r, c]:
                c += 1
            ax.add_patch(
                Rectangle(
                    (start, n - r - 1),
                    c - start,
                    1,
                    facecolor="black",
                    edgecolor="none",
                    antialiased=False,
                )
            )
    ax.set_xlim(0, n)
    ax.set_ylim(0, n)
    ax.set_axis_off()

    text_y = bottom - 0.018
    fig.text(
        0.5,
        text_y / ph,
        f"ArUco {dictionary}  id {marker_id}   black square {length * 1000:.1f} mm",
        ha="center",
        va="top",
        fontsize=14,
    )
    bar = fig.add_axes(
        ((pw - SCALE_BAR) / 2 / pw, (text_y - 0.030) / ph, SCALE_BAR / pw, 0.004 / ph)
    )
    bar.add_patch(Rectangle((0, 0), 1, 1, facecolor="black", edgecolor="none", antialiased=False))
    bar.set_xlim(0, 1)
    bar.set_ylim(0, 1)
    bar.set_axis_off()
    fig.text(
        0.5,
        (text_y - 0.034) / ph,
        "100 mm: measure this bar; print at 100 % (no 'fit to page')",
        ha="center",
        va="top",
        fontsize=9,
    )
    return fig, (left, bottom, length, length)
