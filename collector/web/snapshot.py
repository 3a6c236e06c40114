"""What the console page shows, from the collector's status replies: pure functions and a small
history, so the browser gets one compact message a second however many readings arrive."""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from bgt_core.control_messages import CollectorStatus

HISTORY_S = 300  # the scrolling RSSI chart: the last five minutes, one point a second
SILENT_S = 10.0  # a sensor unheard this long turns red


@dataclass
class ConsoleHistory:
    """Per chart line ("agent/sensor beacon", or "agent/sensor"), the last RSSI once a second;
    per stream ("agent/sensor"), when it went quiet."""

    points: dict[str, deque[tuple[float, int | None]]] = field(default_factory=dict)
    quiet_since: dict[str, float] = field(default_factory=dict)

    def add(self, t: float, stream: str, rssi: int | None) -> None:
        d = self.points.get(stream)
        if d is None:
            d = self.points[stream] = deque(maxlen=HISTORY_S)
        d.append((t, rssi))


def stream_name(agent: str, sensor: str) -> str:
    return f"{agent}/{sensor}"


def build_snapshot(
    status: CollectorStatus,
    history: ConsoleHistory,
    *,
    now: float | None = None,
    silent_s: float = SILENT_S,
) -> dict[str, Any]:
    """The page's state: agents and sensors (rate, last RSSI, per-beacon rates, silent or not),
    the beacons seen, the run, the alerts, and this second's RSSI point per sensor (the page
    keeps the history itself). Records this second's points into ``history``."""
    now = time.time() if now is None else now
    agents = []
    beacons: set[str] = set()
    points: dict[str, int | None] = {}
    for agent_id, a in sorted(status.agents.items()):
        sensors = []
        for mac, s in sorted(a.sensors.items()):
            name = stream_name(agent_id, mac)
            age = s.last_seen_age_s
            silent = age is None or age > silent_s
            if silent:
                since = history.quiet_since.setdefault(name, now - (age or 0.0))
            else:
                history.quiet_since.pop(name, None)
                since = None
            rssi = None if silent else s.last_rssi
            # One chart line per sensor and beacon (per sensor when the status has no beacons).
            lines = {
                f"{name} {b}": None if silent else r for b, r in sorted(s.beacon_rssi.items())
            } or {name: rssi}
            for key, value in lines.items():
                history.add(now, key, value)
                points[key] = value
            beacons.update(s.beacons)
            sensors.append(
                {
                    "mac": mac,
                    "rate": s.rate_hz,
                    "last_rssi": s.last_rssi,
                    "age_s": age,
                    "readings": s.readings,
                    "silent": silent,
                    "quiet_since": since,
                    "beacons": dict(s.beacons),
                    "beacon_rssi": dict(s.beacon_rssi),
                }
            )
        agents.append(
            {
                "id": agent_id,
                "alive": a.alive,
                "version": a.version,
                "backend": a.backend,
                "hostname": a.hostname,
                "adapters": list(a.adapters),
                "clock_offset_ms": a.clock_offset_ms,
                "spool_records": a.spool_records,
                "spool_bytes": a.spool_bytes,
                "last_ack_age_s": a.last_ack_age_s,
                "sensors": sensors,
            }
        )
    return {
        "t": now,
        "run": None
        if status.run is None
        else {
            "id": status.run.run_id,
            "name": status.run.name,
            "start": status.run.start,
            "readings": status.run.readings,
            "sensors": status.run.sensors,
            "stopping": status.run.stopping,
        },
        "agents": agents,
        "beacons": sorted(beacons),
        "alerts": alerts(status),
        "points": points,
    }


def alerts(status: CollectorStatus) -> list[str]:
    """One line per condition the operator must know about (as `collector live` shows them)."""
    out = []
    if status.disk_full:
        out.append("the disk of the run is full: nothing new is acknowledged")
    if status.write_errors:
        out.append(f"{status.write_errors} write errors")
    if status.refused_streams.batches:
        out.append(
            f"{status.refused_streams.batches} batches refused over the stream limits "
            f"({', '.join(status.refused_streams.by_agent)})"
        )
    if status.refused_streams.over_quota:
        out.append(
            "batches refused over the per-agent quotas: "
            + ", ".join(f"{k} ({n})" for k, n in status.refused_streams.over_quota.items())
        )
    for mac, names in list(status.shared_sensors.items())[:5]:
        out.append(f"sensor {mac} is published by several agents: {', '.join(names)}")
    if status.unknown_agents:
        out.append(
            f"data from agents without a liveliness token: {', '.join(status.unknown_agents)}"
        )
    if status.run is not None:
        for agent, smp in status.run.clock.items():
            if abs(smp.offset_ms) > 50:
                out.append(f"agent {agent}'s clock is {smp.offset_ms:+.0f} ms off")
    return out
