"""Heat maps of a radio map: mean RSSI per grid cell for one sensor, optionally drawn over the
site's floor plan (pixel geometry from its .par). matplotlib with the Agg backend, files only."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from annotator.plots.scale import metre_scale_bar
from bgt_core.formats.devices import MapParams


def plot_mean_rssi(
    path: str | Path,
    xs: np.ndarray,
    ys: np.ndarray,
    cell: float,
    mean: np.ndarray,
    *,
    title: str,
    sensors: dict[str, tuple[float, float]] | None = None,
    highlight: str | None = None,
    fingerprints: np.ndarray | None = None,
    floor_plan: Path | None = None,
    params: MapParams | None = None,
) -> Path:
    """Write a PNG: ``mean[iy, ix]`` (dBm, NaN = no value) on the grid with lower-left corners
    ``xs`` x ``ys``; sensor positions (``highlight`` drawn larger) and fingerprint positions
    marked. With ``floor_plan`` and ``params`` the grid is drawn in map pixels over the image."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = np.asarray(xs, dtype=float)
    ys = np.asarray(ys, dtype=float)
    gx, gy = np.meshgrid(np.append(xs, xs[-1] + cell), np.append(ys, ys[-1] + cell))
    fig, ax = plt.subplots(figsize=(8, 7))
    try:

        def to_plot(x, y):
            return (x, y) if params is None else params.world_to_pixel(x, y)

        if floor_plan is not None and params is not None:
            img = plt.imread(str(floor_plan))
            ax.imshow(img, zorder=0)
            metre_scale_bar(ax, params.parity, img.shape[1], img.shape[0])
        else:
            params = None
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            ax.set_aspect("equal")
        px, py = to_plot(gx, gy)
        masked = np.ma.masked_invalid(np.asarray(mean, dtype=float))
        mesh = ax.pcolormesh(
            px, py, masked, cmap="viridis", alpha=0.75 if params else 1.0, shading="flat", zorder=1
        )
        fig.colorbar(mesh, ax=ax, label="mean RSSI (dBm)")
        if fingerprints is not None and len(fingerprints):
            fx, fy = to_plot(fingerprints[:, 0], fingerprints[:, 1])
            ax.scatter(
                fx,
                fy,
                s=10,
                c="white",
                edgecolors="black",
                linewidths=0.5,
                zorder=2,
                label="fingerprints",
            )
        for mac, (sx, sy) in (sensors or {}).items():
            qx, qy = to_plot(sx, sy)
            big = mac == highlight
            ax.scatter(
                [qx],
                [qy],
                marker="^",
                s=120 if big else 40,
                c="red" if big else "orange",
                edgecolors="black",
                zorder=3,
            )
        ax.set_title(title)
        if fingerprints is not None and len(fingerprints):
            ax.legend(loc="upper right", fontsize="small")
        path = Path(path)
        fig.savefig(path, dpi=100, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path


def plot_beacon_maps(
    path: str | Path,
    xs: np.ndarray,
    ys: np.ndarray,
    cell: float,
    means: dict[str, np.ndarray],
    *,
    title: str,
    positions: dict[str, tuple[float, float]] | None = None,
    names: dict[str, str] | None = None,
) -> Path:
    """Write a PNG with one panel per beacon: its mean RSSI ``means[beacon][iy, ix]`` (dBm) on the
    grid with lower-left corners ``xs`` x ``ys``, on one colour scale, the beacon's position
    marked where ``positions`` knows it. What a receiver on the bundle makes of each wall beacon."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = np.asarray(xs, dtype=float)
    ys = np.asarray(ys, dtype=float)
    gx, gy = np.meshgrid(np.append(xs, xs[-1] + cell), np.append(ys, ys[-1] + cell))
    beacons = sorted(means, key=lambda b: (names or {}).get(b, b))
    values = np.concatenate([np.ravel(means[b]) for b in beacons])
    values = values[np.isfinite(values)]
    lo, hi = np.percentile(values, [2, 98]) if values.size else (-100.0, -40.0)
    cols = min(4, len(beacons))
    rows = -(-len(beacons) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols + 0.8, 3.2 * rows), squeeze=False)
    try:
        mesh = None
        for ax, b in zip(axes.ravel(), beacons, strict=False):
            masked = np.ma.masked_invalid(np.asarray(means[b], dtype=float))
            mesh = ax.pcolormesh(gx, gy, masked, cmap="viridis", vmin=lo, vmax=hi, shading="flat")
            if positions and b in positions:
                bx, by = positions[b]
                ax.scatter([bx], [by], marker="*", s=120, c="red", edgecolors="black", zorder=3)
            ax.set_title((names or {}).get(b, b), fontsize=8)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
        for ax in axes.ravel()[len(beacons) :]:
            ax.set_visible(False)
        if mesh is not None:
            fig.colorbar(mesh, ax=list(axes.ravel()[: len(beacons)]), label="mean RSSI (dBm)")
        fig.suptitle(f"{title} (x, y in m; red star: the beacon)", fontsize=10)
        path = Path(path)
        fig.savefig(path, dpi=90)
    finally:
        plt.close(fig)
    return path
