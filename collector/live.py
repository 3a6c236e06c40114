"""`collector live`: a terminal view of every sensor (rate, last RSSI, RSSI sparkline), refreshed
from the collector's status query."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from rich import box
from rich.console import Group, JustifyMethod
from rich.live import Live
from rich.table import Table
from rich.text import Text

from bgt_core.control_messages import CollectorStatus

BARS = "▁▂▃▄▅▆▇█"
RSSI_LO, RSSI_HI = -100, -30
SPARK_WIDTH = 20  # most recent readings shown per sensor


def sparkline(values: Sequence[int | float], lo: float = RSSI_LO, hi: float = RSSI_HI) -> str:
    """One character per value, clipped to [lo, hi]: stronger signal = taller bar. A value that
    is not a number (a garbled status) is drawn as a space rather than failing the view."""
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | float) or v != v:
            out.append(" ")
            continue
        f = (min(max(v, lo), hi) - lo) / (hi - lo)
        out.append(BARS[min(len(BARS) - 1, int(f * len(BARS)))])
    return "".join(out)


def render(reply: CollectorStatus | Mapping[str, Any]) -> Group:
    """The live view of a status reply (typed, or as decoded from JSON)."""
    status = reply if isinstance(reply, CollectorStatus) else CollectorStatus.from_dict(reply)
    run = status.run
    head = Text(
        f"run {run.run_id}: {run.readings} readings written"
        if run
        else "no run active (readings are counted, not written)",
        style="bold green" if run else "yellow",
    )
    agents = status.agents
    table = Table(expand=False, box=box.SIMPLE_HEAD, show_edge=False)
    widths = {"agent": max([len(a) for a in agents] + [5]), "sensor": 12, "seen": 5}
    columns: tuple[tuple[str, JustifyMethod], ...] = (
        ("agent", "left"),
        ("sensor", "left"),
        ("alive", "center"),
        ("rate/s", "right"),
        ("RSSI", "right"),
        ("seen", "right"),
        ("readings", "right"),
    )
    for col, just in columns:
        table.add_column(col, justify=just, no_wrap=True, min_width=widths.get(col, len(col)))
    # Per beacon, the most heard first: a sensor whose rate for a beacon sags stands out.
    table.add_column("beacons/s", no_wrap=True, overflow="ellipsis", max_width=26)
    # The sparkline gives way first when the terminal is narrow.
    table.add_column("recent RSSI", no_wrap=True, overflow="crop", max_width=SPARK_WIDTH)
    for agent, a in sorted(agents.items()):
        alive = "[green]yes" if a.alive else "[red]no"
        if not a.sensors:
            table.add_row(agent, "-", alive, "", "", "", "", "", "")
        for mac, s in sorted(a.sensors.items()):
            age = s.last_seen_age_s
            table.add_row(
                agent,
                mac,
                alive,
                f"{s.rate_hz:.1f}",
                "" if s.last_rssi is None else str(s.last_rssi),
                f"{age:.1f}s" if age is not None else "",
                str(s.readings),
                "  ".join(f"{b[-4:]} {r:.1f}" for b, r in list(s.beacons.items())[:3]),
                sparkline(list(s.recent_rssi[-SPARK_WIDTH:])),
            )
    rejected = dict(status.rejected_payloads)
    bad = rejected.pop("bad_reading", 0)
    foot = Text(
        f"rejected payloads: {sum(rejected.values())}  bad readings skipped: {bad}  "
        f"duplicates dropped: {status.duplicates_dropped}",
        style="dim",
    )
    return Group(head, *_alerts(status), table, foot)


def _alerts(status: CollectorStatus) -> list[Text]:
    """Conditions an operator must act on (or know about), one line each."""
    out = []
    if status.disk_full:
        out.append(
            Text(
                "DISK FULL: rows are held in memory and not acknowledged until space returns",
                style="bold red",
            )
        )
    if status.write_errors:
        out.append(
            Text(f"{status.write_errors} failed writes (see the collector's log)", style="red")
        )
    if status.run is not None and status.run.restarts:
        out.append(
            Text(
                f"run resumed after {status.run.restarts} unclean collector stop(s)", style="yellow"
            )
        )
    streams = status.streams
    if streams.total > streams.shown:
        out.append(
            Text(
                f"{streams.total - streams.shown} more streams not shown ({streams.total} in all)",
                style="yellow",
            )
        )
    refused = status.refused_streams
    if refused.batches:
        worst = ", ".join(f"{a} ({n})" for a, n in refused.by_agent.items())
        out.append(
            Text(
                f"{refused.batches} batches of {refused.streams} streams refused "
                f"over the stream limits: {worst}",
                style="red",
            )
        )
    if refused.over_quota:
        worst = ", ".join(f"{k} ({n})" for k, n in list(refused.over_quota.items())[:5])
        out.append(
            Text(
                f"{sum(refused.over_quota.values())} batches refused over the per-agent quotas "
                f"(limits.agent_readings_per_s / agent_mb_per_run): {worst}",
                style="red",
            )
        )
    for mac, names in list(status.shared_sensors.items())[:5]:
        out.append(
            Text(
                f"sensor {mac} is published by several agents: {', '.join(names)} "
                "(kept as separate streams)",
                style="yellow",
            )
        )
    if status.unknown_agents:
        out.append(
            Text(
                "data from agents without a liveliness token: "
                f"{', '.join(sorted(status.unknown_agents))}",
                style="yellow",
            )
        )
    return out


def run_live(
    fetch: Callable[[], dict[str, Any]], *, interval_s: float = 0.5, duration_s: float | None = None
) -> None:
    """Redraw until Ctrl-C (or for duration_s, used by tests and demos)."""
    end = None if duration_s is None else time.monotonic() + duration_s
    with Live(render(fetch()), refresh_per_second=4, screen=False) as live:
        try:
            while end is None or time.monotonic() < end:
                time.sleep(interval_s)
                live.update(render(fetch()))
        except KeyboardInterrupt:
            pass
