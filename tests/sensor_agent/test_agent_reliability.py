"""The agent's no-loss path on real Zenoh sessions over loopback: the spool is written before a
batch is published, acknowledged batches leave it, the floor tells the collector what will never
come again, unacknowledged batches are re-sent after an outage, and the clock queryable answers."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

from agent_testing import FakeCollector
from bgt_core import wire
from bgt_core.wire import Reading
from bgt_core.zenoh_config import SessionSpec, build_config
from full_disk import QuotaFiles
from polling import wait_for
from sensor_agent.app import Agent
from sensor_agent.clockhealth import parse_chronyc_tracking
from sensor_agent.config import AgentConfig, SpoolConfig
from sensor_agent.publisher import CACHE_SAMPLES, Publisher, stream_id
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, ScannerBackend
from sensor_agent.spool import Spool

SENSOR = "b827eb4521b4"
BOOT = "00112233aabbccdd"
T = 1_700_000_000 * 10**9


def make_reading(i: int) -> Reading:
    return Reading(T + i * 1000, "e78f135624ce", -40 - i % 60, i + 1)


def router(endpoint: str) -> zenoh.Session:
    return zenoh.open(build_config(SessionSpec(mode="router", listen=[endpoint])))


def client(endpoint: str) -> zenoh.Session:
    return zenoh.open(build_config(SessionSpec(mode="client", connect=[endpoint])))


class RecordingSpool(Spool):
    """A real spool that also remembers which seqs it accepted, to check the order of events."""

    def __init__(self, *a, **kw) -> None:
        super().__init__(*a, **kw)
        self.appended: set[int] = set()

    def append(self, stream: str, seq: int, payload: bytes) -> bool:
        ok = super().append(stream, seq, payload)
        if ok:
            self.appended.add(seq)
        return ok


def test_batches_are_spooled_before_publish_and_leave_it_when_acked(
    endpoint: str, tmp_path: Path
) -> None:
    r = router(endpoint)
    seen: list[tuple[int, bool]] = []
    lock = threading.Lock()
    spool = RecordingSpool(tmp_path / "spool", 1 << 20)

    def on_sample(sample: zenoh.Sample) -> None:
        b = wire.from_wire(sample.payload.to_bytes())
        with lock:  # already on disk when it reaches the wire?
            seen.append((b.seq, b.seq in spool.appended))

    sub = r.declare_subscriber(wire.data_selector("lab"), on_sample)
    c = client(endpoint)
    pub = Publisher(c, site="lab", agent_id="pi-01", boot_id=BOOT, wall_ns=lambda: T, spool=spool)
    sid = stream_id(BOOT, SENSOR)
    try:
        for i in range(8):
            pub.add(SENSOR, make_reading(i))
            assert pub.flush() == 1
        wait_for(lambda: len(seen) == 8)
        assert seen == [(i, True) for i in range(8)]
        assert [q for _s, q, _p in spool.pending()] == list(range(8))
        # the spooled bytes are exactly what was published
        assert [wire.from_wire(p).readings for _s, _q, p in spool.pending()] == [
            (make_reading(i),) for i in range(8)
        ]

        r.put(wire.ack_key("lab", "pi-01"), wire.to_json({"boot": BOOT, "streams": {SENSOR: 4}}))
        wait_for(lambda: spool.lowest_pending(sid) == 5)
        assert [q for _s, q, _p in spool.pending()] == [5, 6, 7]
        assert spool.stats().records == 3
        assert pub.unacked() == {SENSOR: (7, 4)}
        r.put(wire.ack_key("lab", "pi-01"), wire.to_json({"boot": BOOT, "streams": {SENSOR: 7}}))
        wait_for(lambda: spool.lowest_pending(sid) is None)
        assert list(spool.pending()) == []
        assert pub.unacked() == {}
    finally:
        pub.close()
        spool.close()
        c.close()
        sub.undeclare()
        r.close()


def test_floor_without_spool_is_the_oldest_unacked_batch_still_in_memory(endpoint: str) -> None:
    r = router(endpoint)
    sub = r.declare_subscriber(wire.data_selector("lab"))
    c = client(endpoint)
    pub = Publisher(c, site="lab", agent_id="pi-01", boot_id=BOOT, wall_ns=lambda: T)
    got: list[wire.Batch] = []

    def drain() -> None:
        while (s := sub.try_recv()) is not None:
            got.append(wire.from_wire(s.payload.to_bytes()))

    try:
        for i in range(3):
            pub.add(SENSOR, make_reading(i))
            pub.flush()
        wait_for(lambda: len(got) == 3, poll=drain)
        assert [(b.seq, b.floor) for b in got] == [(0, 0), (1, 0), (2, 0)]
        r.put(wire.ack_key("lab", "pi-01"), wire.to_json({"boot": BOOT, "streams": {SENSOR: 1}}))
        wait_for(lambda: pub.acked() == {SENSOR: 1})
        pub.add(SENSOR, make_reading(3))
        pub.flush()
        wait_for(lambda: len(got) == 4, poll=drain)
        assert (got[3].seq, got[3].floor) == (3, 2)  # 0 and 1 acknowledged: never sent again
        # Unacknowledged batches beyond the memory ring are gone for good: the floor says so.
        n = CACHE_SAMPLES + 10
        for i in range(4, 4 + n):
            pub.add(SENSOR, make_reading(i))
            pub.flush()
        wait_for(lambda: len(got) == 4 + n, poll=drain)
        last = got[-1]
        assert last.seq == 3 + n
        assert last.floor == last.seq - CACHE_SAMPLES  # the ring holds the 600 before it
        floors = [b.floor for b in got]
        assert floors == sorted(floors)
    finally:
        pub.close()
        c.close()
        sub.undeclare()
        r.close()


def test_floor_skips_batches_dropped_from_a_full_spool(tmp_path: Path) -> None:
    spool = Spool(tmp_path / "spool", 8192, segment_bytes=1024, fsync_interval_s=None)
    pub = Publisher(site="lab", agent_id="pi-01", boot_id=BOOT, wall_ns=lambda: T, spool=spool)
    sid = stream_id(BOOT, SENSOR)
    try:
        for i in range(200):  # ~100 bytes each: far more than 8 KiB
            pub.add(SENSOR, make_reading(i))
            pub.flush()
        st = spool.stats()
        assert st.dropped_oldest > 0
        pending = list(spool.pending())
        lowest = pending[0][1]
        assert lowest == spool.lowest_pending(sid) > 0
        assert [q for _s, q, _p in pending] == list(range(lowest, 200))
        # every spooled batch states the floor of its time: its stream's oldest batch on disk
        floors = [wire.from_wire(p).floor for _s, _q, p in pending]
        assert floors == sorted(floors)
        assert all(f <= q for f, (_s, q, _p) in zip(floors, pending, strict=True))
        assert floors[-1] > 0
        assert not pub.attached  # no session: everything was built and spooled regardless
        assert pub.unacked() == {SENSOR: (199, -1)}
    finally:
        spool.close()


class TickBackend(ScannerBackend):
    """A finite source: ``n`` readings of one sensor, one every ``period_s``."""

    name = "tick"

    def __init__(self, n: int, period_s: float) -> None:
        self.n = n
        self.period_s = period_s
        self._done = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return (AdapterInfo("tick0", SENSOR, "simulated", "simulated"),)

    async def start(self, sink: AdvertSink) -> None:
        async def run() -> None:
            for i in range(self.n):
                sink(SENSOR, make_reading(i))
                await asyncio.sleep(self.period_s)
            self._done.set()

        self._task = asyncio.create_task(run())

    async def stop(self) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()

    async def wait_finished(self) -> None:
        await self._done.wait()


def tick_config(endpoint: str, spool_dir: Path | None) -> AgentConfig:
    return AgentConfig(
        agent_id="pi-01",
        site="lab",
        connect=(endpoint,),
        backend="simulated",
        batch_ms=20,
        spool=SpoolConfig(spool_dir, 1),
        ack_timeout_s=30.0,
    )


async def poll_until(col: FakeCollector, cond: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        col.poll()
        assert time.monotonic() < deadline, "condition not met in time"
        await asyncio.sleep(0.01)
    col.poll()


def readings_of(batches: list[wire.Batch]) -> set[int]:
    return {r.t_ns for b in batches for r in b.readings}


@pytest.mark.slow
def test_outage_of_the_router_loses_nothing(endpoint: str, tmp_path: Path) -> None:
    """The router (collector) goes away mid-run and comes back empty-handed on the same port:
    the spool re-sends what the first one never acknowledged; every reading arrives."""
    n = 250
    agent = Agent(
        tick_config(endpoint, tmp_path / "spool"), TickBackend(n, 0.02), boot_id=BOOT, resend_s=1.0
    )

    async def main() -> tuple[list[wire.Batch], list[wire.Batch], bool]:
        col = FakeCollector(endpoint, "lab")
        task = asyncio.create_task(agent.run())
        try:
            await poll_until(col, lambda: len(readings_of(col.batches)) >= 40)
        finally:
            col.close()
        first = col.batches
        await asyncio.sleep(1.5)  # the outage: the source keeps producing
        assert not task.done()
        col = FakeCollector(endpoint, "lab")
        try:
            await poll_until(col, task.done, timeout_s=60)
            result = await task
        finally:
            col.close()
        return first, col.batches, result.acknowledged

    first, second, acknowledged = asyncio.run(main())
    assert acknowledged
    expected = {make_reading(i).t_ns for i in range(n)}
    assert readings_of(first) | readings_of(second) == expected
    assert readings_of(first) != expected  # the outage really cut something off
    seqs = {b.seq for b in first + second}
    assert seqs == set(range(max(seqs) + 1))  # one stream, numbered without gaps
    # the second collector started from nothing: the floor let it acknowledge without seq 0
    assert min(b.seq for b in second) > 0
    assert agent.readings == n
    assert agent.status()["resent"] > 0


def test_router_absent_at_start_then_appears(endpoint: str, tmp_path: Path) -> None:
    """No router when the agent starts: it records into the spool, connects when the router
    comes, and everything arrives."""
    n = 60
    agent = Agent(
        tick_config(endpoint, tmp_path / "spool"), TickBackend(n, 0.01), boot_id=BOOT, resend_s=0.5
    )

    async def main() -> tuple[list[wire.Batch], bool]:
        task = asyncio.create_task(agent.run())
        await asyncio.sleep(1.0)
        assert not task.done()
        col = FakeCollector(endpoint, "lab")
        try:
            await poll_until(col, task.done, timeout_s=60)
            return col.batches, (await task).acknowledged
        finally:
            col.close()

    batches, acknowledged = asyncio.run(main())
    assert acknowledged
    assert readings_of(batches) == {make_reading(i).t_ns for i in range(n)}


def test_clock_queryable_four_timestamps(endpoint: str) -> None:
    r = router(endpoint)
    c = client(endpoint)
    wall = iter(range(T + 100, T + 10**6, 7))
    chrony = {"system_time_offset_s": 1.5e-05, "stratum": 3}
    pub = Publisher(
        c,
        site="lab",
        agent_id="pi-01",
        boot_id=BOOT,
        wall_ns=lambda: next(wall),
        chrony=lambda: chrony,
    )
    key = wire.agent_clock_key("lab", "pi-01")
    try:

        def ask(payload: bytes):
            deadline = time.monotonic() + 10
            while True:
                replies = list(r.get(key, payload=payload, timeout=2.0))
                if replies or time.monotonic() > deadline:
                    return replies
                time.sleep(0.05)

        replies = ask(wire.to_json({"t1": T}))
        assert len(replies) == 1
        msg = wire.from_json(replies[0].ok.payload.to_bytes())
        assert msg["t1"] == T
        assert T + 100 <= msg["t2"] < msg["t3"]  # stamped at receipt, then at reply
        assert msg["chrony"] == chrony
        bad = ask(wire.to_json({"t1": "soon"}))
        assert bad[0].err is not None
        assert "t1 must be an integer" in bad[0].err.payload.to_string()
    finally:
        pub.close()
        c.close()
        r.close()


TRACKING = """\
Reference ID    : C0A80101 (192.168.1.1)
Stratum         : 3
Ref time (UTC)  : Sun Nov 22 03:40:00 2026
System time     : 0.000012345 seconds slow of NTP time
Last offset     : -0.000005678 seconds
RMS offset      : 0.000023456 seconds
Frequency       : 12.345 ppm fast
Residual freq   : -0.001 ppm
Skew            : 0.012 ppm
Root delay      : 0.001234567 seconds
Root dispersion : 0.000456789 seconds
Update interval : 64.2 seconds
Leap status     : Normal
"""


def test_chronyc_tracking_parsed() -> None:
    got = parse_chronyc_tracking(TRACKING)
    assert got == {
        "ref_id": "C0A80101 (192.168.1.1)",
        "stratum": 3,
        "system_time_offset_s": pytest.approx(-1.2345e-05),  # slow = behind NTP time
        "last_offset_s": pytest.approx(-5.678e-06),
        "rms_offset_s": pytest.approx(2.3456e-05),
        "frequency_ppm": pytest.approx(12.345),
        "root_delay_s": pytest.approx(0.001234567),
        "root_dispersion_s": pytest.approx(0.000456789),
        "leap_status": "Normal",
    }
    fast = parse_chronyc_tracking(TRACKING.replace("seconds slow", "seconds fast"))
    assert fast["system_time_offset_s"] == pytest.approx(1.2345e-05)


def test_chronyc_tracking_partial_or_garbage() -> None:
    got = parse_chronyc_tracking("506 Cannot talk to daemon\n")
    assert set(got.values()) == {None}
    got = parse_chronyc_tracking(
        "Stratum : x\nSystem time : nope\nLeap status : Not synchronised\n"
    )
    assert (got["stratum"], got["system_time_offset_s"], got["leap_status"]) == (
        None,
        None,
        "Not synchronised",
    )


def test_full_disk_under_the_spool_still_publishes_and_can_resend(
    endpoint: str, tmp_path: Path
) -> None:
    """Spool writes fail: batches are still published, kept in memory for re-sending, counted,
    and the floor still covers them; what was spooled before the disk filled stays intact."""
    r = router(endpoint)
    sub = r.declare_subscriber(wire.data_selector("lab"))
    c = client(endpoint)
    spool = Spool(tmp_path / "spool", 1 << 20, files=QuotaFiles(2000), fsync_interval_s=None)
    t = [0]
    pub = Publisher(
        c,
        site="lab",
        agent_id="pi-01",
        boot_id=BOOT,
        wall_ns=lambda: T,
        mono_ns=lambda: t[0],
        spool=spool,
        resend_s=5.0,
    )
    got: list[wire.Batch] = []

    def drain() -> None:
        while (s := sub.try_recv()) is not None:
            got.append(wire.from_wire(s.payload.to_bytes()))

    try:
        for i in range(40):  # ~110 bytes a record: the disk fills after ~17 of them
            pub.add(SENSOR, make_reading(i))
            pub.flush()
        wait_for(lambda: len(got) == 40, poll=drain)
        assert [b.seq for b in got] == list(range(40))
        st = spool.stats()
        assert st.disk_full
        assert st.unspooled > 0
        on_disk = [q for _s, q, _p in spool.pending()]
        assert on_disk == list(range(len(on_disk)))  # whole records only, from seq 0
        assert len(on_disk) + st.unspooled == 40
        assert {b.floor for b in got} == {0}  # nothing acknowledged, everything still held
        # No ack for 5 s: everything is sent again, from the spool and from memory.
        got.clear()
        t[0] += 6 * 10**9
        assert pub.resend_due() == 40
        wait_for(lambda: len(got) == 40, poll=drain)
        assert sorted(b.seq for b in got) == list(range(40))
        r.put(wire.ack_key("lab", "pi-01"), wire.to_json({"boot": BOOT, "streams": {SENSOR: 39}}))
        wait_for(lambda: pub.unacked() == {})
        assert list(spool.pending()) == []
        t[0] += 6 * 10**9
        assert pub.resend_due() == 0
    finally:
        pub.close()
        spool.close()
        c.close()
        sub.undeclare()
        r.close()


def test_resend_waits_for_silence_and_backs_off_while_nothing_is_acknowledged(
    endpoint: str,
) -> None:
    r = router(endpoint)
    c = client(endpoint)
    t = [0]
    pub = Publisher(
        c,
        site="lab",
        agent_id="pi-01",
        boot_id=BOOT,
        wall_ns=lambda: T,
        mono_ns=lambda: t[0],
        resend_s=5.0,
    )
    s = 10**9
    try:
        wait_for(pub.connected)
        for i in range(3):
            pub.add(SENSOR, make_reading(i))
            pub.flush()
        t[0] = 4 * s
        assert pub.resend_due() == 0  # in flight, not yet overdue
        t[0] = 5 * s
        assert pub.resend_due() == 3
        t[0] = 14 * s
        assert pub.resend_due() == 0  # no ack came: the next pass waits twice as long
        t[0] = 15 * s
        assert pub.resend_due() == 3
        # Nothing has travelled yet, so the agent's ack subscription may not have reached the
        # router when the first ack is put: say it again until it arrives (acks are idempotent).
        ack = wire.to_json({"boot": BOOT, "streams": {SENSOR: 0}})
        wait_for(
            lambda: pub.acked() == {SENSOR: 0},  # progress: back to 5 s, 2 batches left
            poll=lambda: r.put(wire.ack_key("lab", "pi-01"), ack),
        )
        t[0] = 19 * s
        assert pub.resend_due() == 0
        t[0] = 20 * s
        assert pub.resend_due() == 2
    finally:
        pub.close()
        c.close()
        r.close()
