"""What the collector reports: the run.yaml summary written when a run stops, and the status
reply (agents, live per-sensor rates, the active run, counters).

Both are pure functions of frozen views (:class:`StatusView`, :class:`RunView`) that the writer
copies out of its state on its own thread (``Writer.status_view``, ``Writer.run_view``); nothing
here reads the writer, so both can be built and tested from plain values.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from bgt_core.control_messages import (
    AgentLive,
    CollectorStatus,
    RefusedStreams,
    RunStatus,
    SensorRate,
    StreamCounts,
)
from bgt_core.messages import AdapterStatus, AgentStatus, ClockSample
from bgt_core.run_record import AgentEntry, BeaconCount, SensorEntry, iso_utc

STATUS_MAX_STREAMS = 200  # streams listed in a status reply; the rest only counted

StreamKey = tuple[str, str]  # (agent, sensor)


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


@dataclass(frozen=True, slots=True)
class StreamAccount:
    """One (agent, sensor) stream of a run: what was written and what the sequence numbers say."""

    readings: int = 0
    batches: int = 0
    beacons: Mapping[str, int] = field(default_factory=dict)  # readings per beacon MAC (hex)
    gaps: int = 0
    missing: int = 0
    lost: int = 0
    boots: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Counters:
    """The writer's counters, as the status reply and run.yaml state them."""

    discarded_no_run: int = 0
    duplicates_dropped: int = 0
    rejected_payloads: Mapping[str, int] = field(default_factory=dict)
    queue: int = 0
    queue_bytes: int = 0
    write_errors: int = 0
    deferred_batches: int = 0
    queue_overflow: int = 0
    quarantine_dropped: int = 0
    unknown_agents: Mapping[str, int] = field(default_factory=dict)
    restarts: int = 0


@dataclass(frozen=True, slots=True)
class ActiveRun:
    """The active run as a status reply describes it."""

    run_id: str
    name: str
    run_dir: str
    start_ns: int
    readings: int
    sensors: int
    buffered_bytes: int
    disk_full: bool
    open_files: int
    stopping: bool


@dataclass(frozen=True, slots=True)
class StatusView:
    """Everything a status reply is built from, copied at ``now`` (monotonic seconds)."""

    now: float
    alive: Mapping[str, bool]  # agent -> heard lately
    shown: Mapping[StreamKey, SensorRate]  # the streams listed, already at ``now``
    streams_total: int
    infos: Mapping[str, AgentStatus]
    last_acks: Mapping[str, float]  # agent -> monotonic time of the last ack sent to it
    clock: Mapping[str, ClockSample]  # agent -> its latest clock sample
    run: ActiveRun | None
    counters: Counters
    refused: RefusedStreams
    admitted_streams: int
    shared_sensors: Mapping[str, list[str]]


@dataclass(frozen=True, slots=True)
class RunView:
    """Everything run.yaml's summary is built from, copied when the run stops."""

    span_s: float
    streams: Mapping[StreamKey, StreamAccount]
    infos: Mapping[str, AgentStatus]
    clock_log: Mapping[str, tuple[ClockSample, ...]]
    shared_sensors: Mapping[str, list[str]]
    refused: RefusedStreams
    counters: Counters


def refused_streams(
    refused: Counter[str], refused_streams: int, over_quota: Counter[str]
) -> RefusedStreams:
    """Batches refused by the stream caps (total, streams, the 20 worst agents) and by the
    per-agent quotas (the 20 worst)."""
    return RefusedStreams(
        sum(refused.values()),
        refused_streams,
        dict(refused.most_common(20)),
        dict(over_quota.most_common(20)),
    )


def run_summary(
    view: RunView, reason: str
) -> tuple[dict[str, AgentEntry], dict[str, Any], RunTotals]:
    """run.yaml's ``agents`` section, its other summary keys (``run_record.SUMMARY_KEYS``), and
    the gap/missing/lost totals."""
    agents: dict[str, AgentEntry] = {}
    gaps_total = missing_total = lost_total = 0
    for (agent_id, sensor), acc in sorted(view.streams.items()):
        info = view.infos.get(agent_id) or AgentStatus(agent_id)
        a = agents.setdefault(
            agent_id,
            AgentEntry(
                hostname=info.hostname,
                version=info.version,
                backend=info.backend,
                boot_ids=[],
                sensors={},
            ),
        )
        adapter = info.adapter(sensor) or AdapterStatus(None, sensor)
        boot_ids = a.setdefault("boot_ids", [])
        for boot in acc.boots:
            if boot not in boot_ids:
                boot_ids.append(boot)
        gaps_total += acc.gaps
        missing_total += acc.missing
        lost_total += acc.lost
        a.setdefault("sensors", {})[sensor] = SensorEntry(
            adapter=adapter.name,
            mac=sensor,
            file=f"rssi/{agent_id}/{sensor}.mbd",
            backend=adapter.backend if adapter.backend is not None else info.backend,
            mode=adapter.mode,
            readings=acc.readings,
            batches=acc.batches,
            # readings and readings/s over the run per beacon, the most heard first
            beacons={
                mac: BeaconCount(
                    readings=n,
                    rate_hz=round(n / view.span_s, 3) if view.span_s > 0 else None,
                )
                for mac, n in sorted(acc.beacons.items(), key=lambda kv: -kv[1])
            },
            gaps=acc.gaps,
            missing_batches=acc.missing,
            lost_batches=acc.lost,
        )
    for agent, samples in view.clock_log.items():
        known = view.infos.get(agent)
        agents.setdefault(
            agent,
            AgentEntry(hostname=None if known is None else known.hostname, boot_ids=[], sensors={}),
        )["clock"] = [smp.to_dict() for smp in samples]
    totals = RunTotals(gaps_total, missing_total, lost_total)
    extra = {
        "layout": "rssi/<agent>/<sensor_mac>.mbd",
        "shared_sensors": dict(view.shared_sensors),
        "refused_streams": view.refused.to_dict(),
        "stopped_by": reason,
        **totals.to_dict(),
        "duplicates_dropped": view.counters.duplicates_dropped,
        "rejected_payloads": dict(view.counters.rejected_payloads),
        "restarts": view.counters.restarts,
    }
    return agents, extra, totals


def _count(v: object) -> int | None:
    return v if isinstance(v, int) and not isinstance(v, bool) and v >= 0 else None


def _agent_live(view: StatusView, agent: str, sensors: dict[str, SensorRate]) -> AgentLive:
    info = view.infos.get(agent)
    clock = view.clock.get(agent)
    spool = (info.spool or {}) if info is not None else {}
    ack = view.last_acks.get(agent)
    return AgentLive(
        view.alive.get(agent, False),
        sensors,
        None if info is None else info.version,
        None if info is None else info.backend,
        None if info is None else info.hostname,
        ()
        if info is None
        else tuple(f"{x.name or '?'} {x.mac} {x.mode or ''}".strip() for x in info.adapters),
        None if clock is None else clock.offset_ms,
        _count(spool.get("records")),
        _count(spool.get("bytes")),
        None if ack is None else round(view.now - ack, 3),
    )


def build_status(view: StatusView) -> CollectorStatus:
    """The status reply: every live agent (at most STATUS_MAX_STREAMS of them listed) with its
    shown streams, the active run and the counters."""
    sensors: dict[str, dict[str, SensorRate]] = {}
    for a in sorted(view.alive):
        if len(sensors) >= STATUS_MAX_STREAMS:
            break
        sensors[a] = {}
    for (agent, sensor), rate in sorted(view.shown.items()):
        sensors.setdefault(agent, {})[sensor] = rate
    agents = {a: _agent_live(view, a, s) for a, s in sensors.items()}
    r = view.run
    c = view.counters
    run = (
        None
        if r is None
        else RunStatus(
            run_id=r.run_id,
            name=r.name,
            run_dir=r.run_dir,
            start=iso_utc(r.start_ns),
            readings=r.readings,
            sensors=r.sensors,
            stopping=r.stopping,
            restarts=c.restarts,
            buffered_bytes=r.buffered_bytes,
            clock=dict(view.clock),
        )
    )
    return CollectorStatus(
        run=run,
        agents=agents,
        discarded_no_run=c.discarded_no_run,
        duplicates_dropped=c.duplicates_dropped,
        rejected_payloads=dict(c.rejected_payloads),
        queue=c.queue,
        write_errors=c.write_errors,
        disk_full=r is not None and r.disk_full,
        deferred_batches=c.deferred_batches,
        queue_overflow=c.queue_overflow,
        unknown_agents=dict(c.unknown_agents),
        quarantine_dropped=c.quarantine_dropped,
        streams=StreamCounts(
            total=view.streams_total,
            shown=len(view.shown),
            admitted=view.admitted_streams,
            open_files=0 if r is None else r.open_files,
        ),
        refused_streams=view.refused,
        shared_sensors=dict(list(view.shared_sensors.items())[:50]),
        queue_bytes=c.queue_bytes,
    )
