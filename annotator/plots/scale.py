"""A metre scale bar for plots drawn on a floor-plan image (pixel axes mean nothing to a reader)."""

from __future__ import annotations

from typing import Any


def metre_scale_bar(ax: Any, metres_per_pixel: float, width_px: int, height_px: int) -> None:
    """Hide the pixel axes of ``ax`` and draw, lower left, a bar of a round number of metres
    (at most a quarter of the plan's width) with its length written under it."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    ax.set_axis_off()
    width_m = width_px * metres_per_pixel
    metres = next((m for m in (10.0, 5.0, 2.0, 1.0, 0.5) if m <= width_m / 4), 0.2)
    bar = AnchoredSizeBar(
        ax.transData,
        metres / metres_per_pixel,
        f"{metres:g} m",
        "lower left",
        pad=0.4,
        borderpad=0.5,
        sep=3,
        frameon=True,
        size_vertical=max(2.0, 0.01 * height_px),
        fontproperties={"size": 7},
    )
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)
