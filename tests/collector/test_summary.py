"""The status reply and run.yaml's summary as pure functions of frozen views (collector/summary.py),
built from plain values: no writer, no session."""

from __future__ import annotations

import pytest

from bgt_core.control_messages import RefusedStreams, SensorRate
from bgt_core.messages import AdapterStatus, AgentStatus, ClockSample
from collector.live_stats import RATE_WINDOW_S, SensorLive
from collector.readings import from_tuples
from collector.summary import (
    STATUS_MAX_STREAMS,
    ActiveRun,
    Counters,
    RunView,
    StatusView,
    StreamAccount,
    build_status,
    refused_streams,
    run_summary,
)

A1, S1, S2 = "agent1", "aabbccddee01", "aabbccddee02"
BEACON = "e78f135624ce"


def _rate(n: float) -> SensorRate:
    return SensorRate(
        rate_hz=n,
        last_seen_age_s=0.5,
        last_rssi=-61,
        readings=100,
        recent_rssi=(-60, -61),
        beacons={BEACON: n},
        beacon_rssi={BEACON: -61},
    )


def _view(**over: object) -> StatusView:
    info = AgentStatus(
        A1,
        version="1.2.3",
        backend="bleak",
        hostname="pi-1",
        adapters=(AdapterStatus("hci0", S1, "bleak", "active"),),
        spool={"records": 12, "bytes": 4096},
    )
    base: dict[str, object] = {
        "now": 100.0,
        "alive": {A1: True, "agent2": False},
        "shown": {(A1, S1): _rate(2.0), (A1, S2): _rate(1.5)},
        "streams_total": 2,
        "infos": {A1: info},
        "last_acks": {A1: 99.25},
        "clock": {A1: ClockSample("2026-11-27T20:00:00.000Z", 3.5, 1.2)},
        "run": ActiveRun(
            "r1", "walk-03", "/data/r1", 1_700_000_000_000_000_000, 250, 2, 0, False, 2, False
        ),
        "counters": Counters(discarded_no_run=4, duplicates_dropped=7, restarts=1, queue=3),
        "refused": RefusedStreams(5, 1, {"agent9": 5}, {}),
        "admitted_streams": 2,
        "shared_sensors": {},
    }
    base.update(over)
    return StatusView(**base)  # type: ignore[arg-type]


def test_status_lists_every_live_agent_with_its_streams_and_the_run() -> None:
    st = build_status(_view())
    assert set(st.agents) == {A1, "agent2"}  # a silent agent is listed, without streams
    a = st.agents[A1]
    assert a.alive
    assert set(a.sensors) == {S1, S2}
    assert a.sensors[S1].rate_hz == 2.0
    assert (a.version, a.backend, a.hostname) == ("1.2.3", "bleak", "pi-1")
    assert a.adapters == (f"hci0 {S1} active",)
    assert a.clock_offset_ms == 3.5
    assert (a.spool_records, a.spool_bytes) == (12, 4096)
    assert a.last_ack_age_s == pytest.approx(0.75)
    assert not st.agents["agent2"].alive
    assert st.agents["agent2"].sensors == {}
    assert st.run is not None
    assert (st.run.run_id, st.run.name, st.run.readings, st.run.sensors) == (
        "r1",
        "walk-03",
        250,
        2,
    )
    assert st.run.start == "2023-11-14T22:13:20.000Z"
    assert st.run.restarts == 1
    assert (st.discarded_no_run, st.duplicates_dropped, st.queue) == (4, 7, 3)
    assert (st.streams.total, st.streams.shown, st.streams.admitted) == (2, 2, 2)
    assert st.streams.open_files == 2
    assert st.refused_streams.by_agent == {"agent9": 5}


def test_status_without_a_run_and_with_a_malformed_spool_figure() -> None:
    info = AgentStatus(A1, spool={"records": -3, "bytes": True})  # an agent's bad status reply
    st = build_status(_view(run=None, infos={A1: info}))
    assert st.run is None
    assert not st.disk_full
    assert st.streams.open_files == 0
    assert (st.agents[A1].spool_records, st.agents[A1].spool_bytes) == (None, None)


def test_status_caps_the_agents_listed_without_streams() -> None:
    alive = {f"agent{i:04d}": True for i in range(STATUS_MAX_STREAMS + 50)}
    st = build_status(_view(alive=alive, shown={}, infos={}, last_acks={}, clock={}))
    assert len(st.agents) == STATUS_MAX_STREAMS


def test_run_summary_per_stream_and_totals() -> None:
    info = AgentStatus(
        A1,
        version="1.2.3",
        backend="bleak",
        hostname="pi-1",
        adapters=(AdapterStatus("hci0", S1, None, "passive"),),
    )
    view = RunView(
        span_s=50.0,
        streams={
            (A1, S1): StreamAccount(
                100, 10, {BEACON: 100}, gaps=1, missing=2, lost=3, boots=("b1",)
            ),
            (A1, S2): StreamAccount(20, 4, {BEACON: 5, "c0ffee000001": 15}, boots=("b1", "b2")),
        },
        infos={A1: info},
        clock_log={A1: (ClockSample("t", 1.0, 2.0),), "agent2": (ClockSample("t", -4.0, 1.0),)},
        shared_sensors={S1: [A1, "agent3"]},
        refused=RefusedStreams(),
        counters=Counters(duplicates_dropped=9, restarts=2, rejected_payloads={"bad_crc": 1}),
    )
    agents, extra, totals = run_summary(view, "requested")
    s1 = agents[A1]["sensors"][S1]
    assert (
        s1["readings"],
        s1["batches"],
        s1["gaps"],
        s1["missing_batches"],
        s1["lost_batches"],
    ) == (
        100,
        10,
        1,
        2,
        3,
    )
    assert s1["file"] == f"rssi/{A1}/{S1}.mbd"
    assert (s1["adapter"], s1["backend"], s1["mode"]) == ("hci0", "bleak", "passive")
    assert s1["beacons"][BEACON] == {"readings": 100, "rate_hz": 2.0}
    s2 = agents[A1]["sensors"][S2]
    assert list(s2["beacons"]) == ["c0ffee000001", BEACON]  # the most heard first
    assert s2["adapter"] is None  # an adapter the agent did not report
    assert agents[A1]["boot_ids"] == ["b1", "b2"]
    assert agents[A1]["clock"] == [{"at": "t", "offset_ms": 1.0, "rtt_ms": 2.0, "chrony": None}]
    assert agents["agent2"]["sensors"] == {}  # clock samples only
    assert (totals.gaps, totals.missing_batches, totals.lost_batches) == (1, 2, 3)
    assert extra["stopped_by"] == "requested"
    assert extra["duplicates_dropped"] == 9
    assert extra["restarts"] == 2
    assert extra["rejected_payloads"] == {"bad_crc": 1}
    assert extra["shared_sensors"] == {S1: [A1, "agent3"]}


def test_refused_streams_keeps_the_twenty_worst() -> None:
    from collections import Counter

    refused = Counter({f"a{i}": i for i in range(1, 31)})
    r = refused_streams(refused, 30, Counter({"a1: rate": 4}))
    assert r.batches == sum(range(1, 31))
    assert r.streams == 30
    assert len(r.by_agent) == 20
    assert min(r.by_agent.values()) == 11
    assert r.over_quota == {"a1: rate": 4}


def test_a_sensor_rate_is_the_live_figures_at_that_time() -> None:
    live = SensorLive(A1)
    live.add(
        10.0,
        from_tuples([(0, 0, bytes.fromhex(BEACON), -70)] * 10),
        {bytes.fromhex(BEACON): [10, -700]},
    )
    r = live.sensor_rate(11.0)
    assert r.rate_hz == pytest.approx(10 / RATE_WINDOW_S, abs=0.01)
    assert r.last_seen_age_s == 1.0
    assert r.last_rssi == -70
    assert r.readings == 10
    assert r.recent_rssi[-1] == -70
    assert r.beacon_rssi == {BEACON: -70}
