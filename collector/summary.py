"""What the collector reports: the run.yaml summary written when a run stops, and the status
reply (agents, live per-sensor rates, the active run, counters). Both read the writer's state on
the writer thread."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from bgt_core.control_messages import (
    AgentLive,
    CollectorStatus,
    RefusedStreams,
    RunStatus,
    SensorRate,
    StreamCounts,
)
from bgt_core.messages import AdapterStatus, AgentStatus
from collector.store import RunWriter, iso_utc

if TYPE_CHECKING:
    from collector.writer import Writer

STATUS_MAX_STREAMS = 200  # streams listed in a status reply; the rest only counted


@dataclass(frozen=True, slots=True)
class RunTotals:
    """Sequence accounting of a stopped run, summed over its streams."""

    gaps: int
    missing_batches: int
    lost_batches: int

    def to_dict(self) -> dict[str, int]:
        return {
            "gaps": self.gaps,
            "missing_batches": self.missing_batches,
            "lost_batches": self.lost_batches,
        }


def refused_summary(w: Writer) -> RefusedStreams:
    """Batches refused by the stream caps (total, streams, the 20 worst agents) and by the
    per-agent quotas (the 20 worst)."""
    return RefusedStreams(
        sum(w.gate.refused.values()),
        len(w.gate.refused_streams),
        dict(w.gate.refused.most_common(20)),
        dict(w.gate.over_quota.most_common(20)),
    )


def write_run_yaml(w: Writer, run: RunWriter, reason: str, stop_ns: int) -> RunTotals:
    """Write the final run.yaml of ``run``; returns its gap/missing/lost totals."""
    infos = w.agents.infos()
    agents: dict[str, Any] = {}
    gaps_total = missing_total = lost_total = 0
    per_stream = w.tracker.stream_totals()
    span_s = (stop_ns - run.start_ns) / 1e9
    for (agent_id, sensor), stats in sorted(run.sensors.items()):
        info = infos.get(agent_id) or AgentStatus(agent_id)
        a = agents.setdefault(
            agent_id,
            {
                "hostname": info.hostname,
                "version": info.version,
                "backend": info.backend,
                "boot_ids": [],
                "sensors": {},
            },
        )
        adapter = info.adapter(sensor) or AdapterStatus(None, sensor)
        t = per_stream.get((agent_id, sensor))
        gaps, missing, lost = (t.gaps, t.missing, t.lost) if t else (0, 0, 0)
        for boot in t.boots if t else ():
            if boot not in a["boot_ids"]:
                a["boot_ids"].append(boot)
        gaps_total += gaps
        missing_total += missing
        lost_total += lost
        a["sensors"][sensor] = {
            "adapter": adapter.name,
            "mac": sensor,
            "file": f"rssi/{agent_id}/{sensor}.mbd",
            "backend": adapter.backend if adapter.backend is not None else info.backend,
            "mode": adapter.mode,
            "readings": stats.readings,
            "batches": stats.batches,
            # readings and readings/s over the run per beacon, the most heard first
            "beacons": {
                mac: {"readings": n, "rate_hz": round(n / span_s, 3) if span_s > 0 else None}
                for mac, n in sorted(stats.beacons.items(), key=lambda kv: -kv[1])
            },
            "gaps": gaps,
            "missing_batches": missing,
            "lost_batches": lost,
        }
    for agent, samples in w.clock_log.items():
        known = infos.get(agent)
        agents.setdefault(
            agent,
            {"hostname": None if known is None else known.hostname, "boot_ids": [], "sensors": {}},
        )["clock"] = [smp.to_dict() for smp in samples]
    totals = RunTotals(gaps_total, missing_total, lost_total)
    extra = {
        "layout": "rssi/<agent>/<sensor_mac>.mbd",
        "shared_sensors": run.shared_sensors(),
        "refused_streams": refused_summary(w).to_dict(),
        "stopped_by": reason,
        **totals.to_dict(),
        "duplicates_dropped": w.tracker.duplicates,
        "rejected_payloads": w.inbox.rejects.snapshot(),
        "restarts": w.restarts,
    }
    run.write_yaml(stop_ns=stop_ns, agents=agents, extra=extra)
    return totals


def _count(v: object) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else None


def build_status(w: Writer, now: float) -> CollectorStatus:
    """The status reply (``now`` is monotonic seconds)."""
    alive = w.agents.alive_map()
    sensors: dict[str, dict[str, SensorRate]] = {}
    for a in sorted(alive):
        if len(sensors) >= STATUS_MAX_STREAMS:
            break
        sensors[a] = {}
    # At most STATUS_MAX_STREAMS streams, the most recently heard first; the rest are counted.
    shown = sorted(w.live.items(), key=lambda kv: -kv[1].last_seen)[:STATUS_MAX_STREAMS]
    for (agent, sensor), sl in sorted(shown, key=lambda kv: kv[0]):
        sensors.setdefault(agent, {})[sensor] = SensorRate(
            rate_hz=round(sl.rate(now), 2),
            last_seen_age_s=round(now - sl.last_seen, 3),
            last_rssi=sl.last_rssi,
            readings=sl.readings,
            recent_rssi=tuple(sl.rssi),
            beacons=sl.beacon_rates(now),
            beacon_rssi=sl.beacon_rssi(now),
        )
    infos = w.agents.infos()
    acks = w.agents.last_acks()

    def live(a: str, s: dict[str, SensorRate]) -> AgentLive:
        info = infos.get(a)
        clock = w.clock_log.get(a)
        spool = (info.spool or {}) if info is not None else {}
        ack = acks.get(a)
        return AgentLive(
            alive.get(a, False),
            s,
            None if info is None else info.version,
            None if info is None else info.backend,
            None if info is None else info.hostname,
            ()
            if info is None
            else tuple(f"{x.name or '?'} {x.mac} {x.mode or ''}".strip() for x in info.adapters),
            clock[-1].offset_ms if clock else None,
            _count(spool.get("records")),
            _count(spool.get("bytes")),
            None if ack is None else round(now - ack, 3),
        )

    agents = {a: live(a, s) for a, s in sensors.items()}
    run = None
    r = w.run
    if r is not None:
        run = RunStatus(
            run_id=r.run_id,
            name=r.name,
            run_dir=str(r.dir.resolve()),
            start=iso_utc(r.start_ns),
            readings=r.readings,
            sensors=len(r.sensors),
            stopping=w.stopping is not None,
            restarts=w.restarts,
            buffered_bytes=r.buffered,
            clock={a: v[-1] for a, v in w.clock_log.items() if v},
        )
    inbox = w.inbox
    return CollectorStatus(
        run=run,
        agents=agents,
        discarded_no_run=w.discarded,
        duplicates_dropped=w.tracker.duplicates,
        rejected_payloads=inbox.rejects.snapshot(),
        queue=inbox.data.qsize(),
        write_errors=w.write_errors,
        disk_full=r is not None and r.disk_full,
        deferred_batches=w.deferred,
        queue_overflow=inbox.overflow,
        unknown_agents=dict(Counter(w.unknown_agents).most_common(20)),
        quarantine_dropped=inbox.quarantine_dropped,
        streams=StreamCounts(
            total=len(w.live),
            shown=len(shown),
            admitted=len(w.gate.admitted),
            open_files=0 if r is None else r.open_count,
        ),
        refused_streams=refused_summary(w),
        shared_sensors=dict(list(w.gate.shared_sensors().items())[:50]),
        queue_bytes=inbox.data.bytes,
    )
