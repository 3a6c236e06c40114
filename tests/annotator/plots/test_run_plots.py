"""The run's plots read right (issue 30): time in seconds from the capture's start with its
wall-clock start in the title, a legend naming the cover events, the tracked span and each
video's start, a metre scale on the floor plan, a title, and no text outside the figure or its
panel."""

from __future__ import annotations

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text

from annotator.plots.run import load_site, rssi_on_trajectory_figure, rssi_time_figure

T0 = 1_795_773_871.013  # 2026-11-27 10:04:31.013 UTC


def _texts(fig: Figure) -> list[Text]:
    """The figure's visible texts but tick labels (matplotlib keeps the labels of ticks beyond
    the view, undrawn), after a draw that lays them out as savefig does."""
    FigureCanvasAgg(fig).draw()
    ticks = {
        id(label)
        for ax in fig.axes
        for axis in (ax.xaxis, ax.yaxis)
        for tick in axis.get_major_ticks() + axis.get_minor_ticks()
        for label in (tick.label1, tick.label2)
    }
    return [
        t
        for t in fig.findobj(Text)
        if t.get_visible() and t.get_text().strip() and id(t) not in ticks
    ]


def _inside(inner: object, outer: object, slack: float = 1.0) -> bool:
    return bool(
        inner.x0 >= outer.x0 - slack  # type: ignore[attr-defined]
        and inner.y0 >= outer.y0 - slack  # type: ignore[attr-defined]
        and inner.x1 <= outer.x1 + slack  # type: ignore[attr-defined]
        and inner.y1 <= outer.y1 + slack  # type: ignore[attr-defined]
    )


def test_rssi_over_time_names_its_marks_and_its_clock() -> None:
    rng = np.random.default_rng(0)
    sensors = np.array(["000000000101", "000000000102", "b827eb4521b4"] * 40)
    t = T0 + np.sort(rng.uniform(0, 30, sensors.size))
    t[0] = T0  # the capture starts with its first reading
    fig = rssi_time_figure(
        t,
        rng.integers(-90, -60, sensors.size),
        sensors,
        events=[(T0 + 2.1, T0 + 3.5)],
        span=(T0 + 0.2, T0 + 29.0),
        video_starts={"front": T0 + 0.2, "back": T0 + 0.55},
    )
    texts = [x.get_text() for x in _texts(fig)]
    assert fig.get_suptitle().endswith("capture start 2026-11-27 10:04:31.013 UTC")
    assert fig.axes[-1].get_xlabel() == "time since the capture's start (s)"
    legend = fig.legends[0]
    assert [x.get_text() for x in legend.get_texts()] == [
        "cover event used for sync",
        "tracked span (first and last pose)",
        "front video start",
        "back video start",
    ]
    # the first reading is at 0 s on the axis, not at a Unix time
    lo, hi = fig.axes[0].get_xlim()
    assert lo > -5.0
    assert hi < 40.0
    assert not any("1795773871" in x for x in texts)
    box = fig.bbox
    assert all(_inside(x.get_window_extent(), box) for x in _texts(fig))


def test_rssi_on_the_plan_keeps_every_label_in_its_panel_and_has_a_scale() -> None:
    floor, devices = load_site("tetam")
    macs = list(devices.dongles)
    rng = np.random.default_rng(1)
    n = 20 * len(macs)
    positions = np.column_stack([rng.uniform(8, 11, n), rng.uniform(7, 10, n), np.full(n, 1.5)])
    fig = rssi_on_trajectory_figure(
        positions,
        positions,
        rng.integers(-90, -60, n),
        np.array(macs * 20),
        floor=floor,
        devices=devices,
    )
    assert fig.get_suptitle()
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.images]
    assert len(panels) == len(macs)
    for ax in panels:
        texts = _texts(fig)
        mine = [x for x in ax.texts if x.get_text().strip()]
        assert len(mine) == 1  # the panel's own sensor, named
        assert _inside(mine[0].get_window_extent(), ax.bbox), mine[0].get_text()
        scale = [x.get_text() for x in ax.findobj(Text) if x.get_text().endswith(" m")]
        assert scale == ["2 m"]
    assert texts
