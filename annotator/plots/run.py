"""The run's plots: trajectory on the floor map, RSSI over time with the sync event, RSSI on the path.

Matplotlib ``Figure`` objects only (Agg, no pyplot state), written straight to PNG files. The floor
map of a built-in site is used as background when the experiment's marker map is that site's.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from annotator.plots.scale import metre_scale_bar
from bgt_core.formats.devices import Devices, MapParams, read_dev, read_par
from bgt_core.formats.markers import MarkerPose, read_marker_map
from bgt_core.sites import site_dir

if TYPE_CHECKING:
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class FloorMap:
    """A floor-plan image and its pixel <-> metre conversion."""

    image: np.ndarray
    params: MapParams

    def to_pixels(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        px, py = self.params.world_to_pixel(xy[:, 0], xy[:, 1])
        return np.asarray(px), np.asarray(py)


def builtin_site_for(
    markers: dict[int, MarkerPose], names: tuple[str, ...] = ("tetam",)
) -> str | None:
    """Name of the built-in site whose marker map equals ``markers`` (to 1 mm), else None."""
    for name in names:
        try:
            ref = read_marker_map(site_dir(name) / "marker_positions.dat")
        except FileNotFoundError:
            continue
        if set(ref) == set(markers) and all(
            np.allclose(ref[k].position, markers[k].position, atol=1e-3)
            and np.allclose(ref[k].euler_xyz, markers[k].euler_xyz, atol=1e-3)
            for k in ref
        ):
            return name
    return None


def load_site(name: str) -> tuple[FloorMap, Devices]:
    """Floor map and devices of a built-in site."""
    import matplotlib.image

    d = site_dir(name)
    return (
        FloorMap(matplotlib.image.imread(d / f"{name}.png"), read_par(d / f"{name}.par")),
        read_dev(d / f"{name}.dev"),
    )


def _figure(w: float, h: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(w, h), dpi=110, layout="constrained")


def _floor_axes(ax, floor: FloorMap | None, scale_bar: bool = True) -> None:
    """The floor plan as background (no axes: a metre scale bar instead), or metre axes."""
    if floor is not None:
        ax.imshow(floor.image)
        ax.set_axis_off()
        if scale_bar:
            metre_scale_bar(ax, floor.params.parity, floor.image.shape[1], floor.image.shape[0])
    else:
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(alpha=0.3)


def _xy(floor: FloorMap | None, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(p, dtype=float).reshape(-1, 3)
    return floor.to_pixels(p) if floor is not None else (p[:, 0], p[:, 1])


def _sensor_points(
    ax, floor: FloorMap | None, devices: Devices | None, only: str | None = None
) -> None:
    if devices is None:
        return
    for mac, d in devices.dongles.items():
        if len(d.position) < 2 or (only is not None and mac != only):
            continue
        x, y = _xy(floor, np.array([[*d.position[:2], 0.0]]))
        ax.plot(x, y, "s", ms=6, mfc="white", mec="black")
        # The label goes on the side of the marker that faces the middle of the plan, so a
        # sensor near the plan's edge keeps its label inside the panel.
        left, low = False, False
        if floor is not None:
            height, width = floor.image.shape[:2]
            left, low = bool(x[0] > 0.7 * width), bool(y[0] < 0.15 * height)
        ax.annotate(
            d.alias,
            (x[0], y[0]),
            textcoords="offset points",
            xytext=(-4 if left else 4, -4 if low else 4),
            ha="right" if left else "left",
            va="top" if low else "bottom",
            fontsize=7,
        )


def plot_trajectory_map(
    path: str | Path,
    positions: np.ndarray,
    *,
    floor: FloorMap | None = None,
    devices: Devices | None = None,
    title: str = "Trajectory",
) -> Path:
    """The bundle's path (NaN rows break the line) over the floor map, with the sensors."""
    fig = _figure(7, 7)
    ax = fig.add_subplot()
    _floor_axes(ax, floor)
    x, y = _xy(floor, positions)
    ax.plot(x, y, "-", color="tab:blue", lw=1.2, label="bundle")
    finite = np.isfinite(x) & np.isfinite(y)
    if finite.any():
        first, last = np.flatnonzero(finite)[[0, -1]]
        ax.plot(x[first], y[first], "o", color="tab:green", label="start")
        ax.plot(x[last], y[last], "X", color="tab:red", label="end")
    _sensor_points(ax, floor, devices)
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    path = Path(path)
    fig.savefig(path)
    return path


def plot_rssi_time(path: str | Path, *args: Any, **kwargs: Any) -> Path:
    """:func:`rssi_time_figure` written to ``path`` (PNG)."""
    path = Path(path)
    rssi_time_figure(*args, **kwargs).savefig(path)
    return path


def rssi_time_figure(
    t: np.ndarray,
    rssi: np.ndarray,
    sensor: np.ndarray,
    *,
    events: Sequence[tuple[float, float]] = (),
    span: tuple[float, float] | None = None,
    aliases: dict[str, str] | None = None,
    t0: float | None = None,
    video_starts: dict[str, float] | None = None,
    by: str = "sensor",
) -> Figure:
    """RSSI over time, one panel per sensor (per beacon with ``by="beacon"``: receiver mode), with a legend for what the marks are: shaded, the
    cover events used for sync; dashed, the tracked span's ends; dotted, each video's start.

    ``t`` and the event/span/start times are on the same clock (Unix seconds); the axis shows
    seconds from ``t0`` (default: the capture's start, the first reading), the title its
    wall-clock time in UTC.
    """
    import datetime as dt

    t = np.asarray(t, dtype=float)
    t0 = float(t.min()) if t0 is None and t.size else (t0 or 0.0)
    sensors = sorted(set(np.asarray(sensor).tolist()), key=lambda s: (aliases or {}).get(s, s))
    n = max(len(sensors), 1)
    fig = _figure(9, 1.6 + 1.1 * n)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    starts = sorted((video_starts or {}).items(), key=lambda kv: kv[1])
    colours = ("tab:green", "tab:purple", "tab:brown", "tab:pink")
    for ax, s in zip(axes, sensors, strict=False):
        mine = np.asarray(sensor) == s
        ax.plot(t[mine] - t0, np.asarray(rssi)[mine], ".", ms=1.5, color="tab:blue")
        for i, (a, b) in enumerate(events):
            label = "cover event used for sync" if i == 0 else None
            ax.axvspan(a - t0, b - t0, color="tab:orange", alpha=0.35, lw=0, label=label)
        if span is not None:
            for i, v in enumerate(span):
                label = "tracked span (first and last pose)" if i == 0 else None
                ax.axvline(v - t0, color="gray", ls="--", lw=0.8, label=label)
        for i, (name, v) in enumerate(starts):
            ax.axvline(
                v - t0, color=colours[i % len(colours)], ls=":", lw=1.0, label=f"{name} video start"
            )
        label = (aliases or {}).get(s, s)
        ax.set_ylabel(label, rotation=0, ha="right", va="center", fontsize=7)
        ax.tick_params(labelsize=7)
    axes[-1].set_xlabel("time since the capture's start (s)")
    start = dt.datetime.fromtimestamp(t0, dt.UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
    what = "RSSI at the receiver per beacon" if by == "beacon" else "RSSI of the beacon per sensor"
    fig.suptitle(f"{what} (dBm); capture start {start} UTC", fontsize=10)
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        fig.legend(
            handles, labels, loc="outside lower center", ncols=min(4, len(handles)), fontsize=7
        )
    return fig


def plot_rssi_on_trajectory(path: str | Path, *args: Any, **kwargs: Any) -> Path:
    """:func:`rssi_on_trajectory_figure` written to ``path`` (PNG)."""
    path = Path(path)
    rssi_on_trajectory_figure(*args, **kwargs).savefig(path)
    return path


def rssi_on_trajectory_figure(
    trajectory: np.ndarray,
    positions: np.ndarray,
    rssi: np.ndarray,
    sensor: np.ndarray,
    *,
    floor: FloorMap | None = None,
    devices: Devices | None = None,
    aliases: dict[str, str] | None = None,
    by: str = "sensor",
) -> Figure:
    """One panel per sensor (or per beacon heard, ``by="beacon"``): the labelled reading positions
    coloured by RSSI, over the path."""
    sensors = sorted(set(np.asarray(sensor).tolist()), key=lambda s: (aliases or {}).get(s, s))
    n = max(len(sensors), 1)
    cols = min(4, n)
    rows = -(-n // cols)
    fig = _figure(3.2 * cols + 0.8, 3.2 * rows)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    rssi = np.asarray(rssi, dtype=float)
    vmin, vmax = np.percentile(rssi, [2, 98]) if rssi.size else (-100.0, -40.0)
    sc = None
    tx, ty = _xy(floor, trajectory)
    for ax, s in zip(axes, sensors, strict=False):
        _floor_axes(ax, floor)
        ax.plot(tx, ty, "-", color="0.6", lw=0.6)
        mine = np.asarray(sensor) == s
        x, y = _xy(floor, positions[mine])
        sc = ax.scatter(x, y, c=rssi[mine], s=4, cmap="viridis", vmin=vmin, vmax=vmax)
        _sensor_points(ax, floor, devices, only=s)
        ax.set_title((aliases or {}).get(s, s), fontsize=8)
    for ax in axes[len(sensors) :]:
        ax.set_visible(False)
    if sc is not None:
        fig.colorbar(sc, ax=list(axes[: len(sensors)]), label="RSSI (dBm)", shrink=0.8)
    fig.suptitle(f"RSSI of each labelled reading at its position, one panel per {by}")
    return fig


def write_run_plots(
    out_dir: str | Path,
    *,
    trajectory: np.ndarray,
    t_s: np.ndarray,
    rssi: np.ndarray,
    sensor: np.ndarray,
    labelled: np.ndarray,
    label_positions: np.ndarray,
    events: list[tuple[float, float]],
    span: tuple[float, float] | None,
    markers: dict[int, MarkerPose] | None = None,
    video_starts: dict[str, float] | None = None,
    by: str = "sensor",
) -> dict[str, Path]:
    """The three plots of `annotator run`; the floor map is drawn when the marker map is a built-in site's.

    ``t_s``, ``rssi``, ``sensor`` are the readings labelled (Unix seconds); ``sensor`` holds what
    the panels are per: the sensors (beacon mode), or the beacons heard (``by="beacon"``,
    receiver mode); ``labelled``
    and ``label_positions`` their labels; ``events`` the RSSI cover intervals used for sync;
    ``video_starts`` each camera's first frame on the RSSI clock.
    """
    out = Path(out_dir)
    site = builtin_site_for(markers) if markers else None
    floor, devices = load_site(site) if site else (None, None)
    aliases = {m: d.alias for m, d in devices.dongles.items()} if devices else None
    lab = np.asarray(labelled, dtype=bool)
    paths = {
        "trajectory": plot_trajectory_map(
            out / "trajectory_map.png",
            trajectory,
            floor=floor,
            devices=devices,
            title="Tracked trajectory",
        ),
        "rssi_time": plot_rssi_time(
            out / "rssi_time.png",
            t_s,
            rssi,
            sensor,
            events=events,
            span=span,
            aliases=aliases,
            video_starts=video_starts,
            by=by,
        ),
        "rssi_on_trajectory": plot_rssi_on_trajectory(
            out / "rssi_on_trajectory.png",
            trajectory,
            label_positions[lab],
            np.asarray(rssi)[lab],
            np.asarray(sensor)[lab],
            floor=floor,
            devices=devices,
            aliases=aliases,
            by=by,
        ),
    }
    log.info("plots: %s", ", ".join(str(p) for p in paths.values()))
    return paths
