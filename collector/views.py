"""Copies of the writer's state for the reports: the frozen views that summary.py's pure
functions build the status reply and run.yaml from. Called on the writer thread, with the
writer's parts (this module never sees the writer itself)."""

from __future__ import annotations

from collections.abc import Mapping

from bgt_core.control_messages import RefusedStreams
from bgt_core.messages import ClockSample
from collector.admission import StreamGate
from collector.agents import AgentBook
from collector.ingest import StreamTracker
from collector.live_stats import SensorLive
from collector.store import RunWriter
from collector.summary import (
    STATUS_MAX_STREAMS,
    ActiveRun,
    Counters,
    RunView,
    StatusView,
    StreamAccount,
    refused_streams,
)


def status_view(
    now: float,
    live: Mapping[tuple[str, str], SensorLive],
    agents: AgentBook,
    clock_log: Mapping[str, list[ClockSample]],
    run: RunWriter | None,
    stopping: bool,
    gate: StreamGate,
    counters: Counters,
) -> StatusView:
    """What a status reply says at ``now`` (monotonic s): the STATUS_MAX_STREAMS streams heard
    most recently, with their rates at ``now``; every other part copied."""
    shown = sorted(live.items(), key=lambda kv: -kv[1].last_seen)[:STATUS_MAX_STREAMS]
    return StatusView(
        now=now,
        alive=agents.alive_map(),
        shown={key: sl.sensor_rate(now) for key, sl in shown},
        streams_total=len(live),
        infos=agents.infos(),
        last_acks=agents.last_acks(),
        clock={a: v[-1] for a, v in clock_log.items() if v},
        run=None
        if run is None
        else ActiveRun(
            run.run_id,
            run.name,
            str(run.dir.resolve()),
            run.start_ns,
            run.readings,
            len(run.sensors),
            run.buffered,
            run.disk_full,
            run.open_count,
            stopping,
        ),
        counters=counters,
        refused=refused_of(gate),
        admitted_streams=len(gate.admitted),
        shared_sensors=gate.shared_sensors(),
    )


def refused_of(gate: StreamGate) -> RefusedStreams:
    """Batches the stream caps and the quotas refused so far."""
    return refused_streams(gate.refused, len(gate.refused_streams), gate.over_quota)


def run_view(
    run: RunWriter,
    stop_ns: int,
    tracker: StreamTracker,
    agents: AgentBook,
    clock_log: Mapping[str, list[ClockSample]],
    refused: RefusedStreams,
    counters: Counters,
) -> RunView:
    """What run.yaml's summary says of ``run`` stopped at ``stop_ns``."""
    totals = tracker.stream_totals()
    streams = {}
    for key, st in run.sensors.items():
        t = totals.get(key)
        streams[key] = (
            StreamAccount(st.readings, st.batches, dict(st.beacons))
            if t is None
            else StreamAccount(
                st.readings, st.batches, dict(st.beacons), t.gaps, t.missing, t.lost, tuple(t.boots)
            )
        )
    return RunView(
        (stop_ns - run.start_ns) / 1e9,
        streams,
        agents.infos(),
        {a: tuple(v) for a, v in clock_log.items()},
        run.shared_sensors(),
        refused,
        counters,
    )
