"""Readings/s per sensor and beacon, and the warning when one falls (issue 31): a controller that
starts throttling (heard as strongly, less often) is a WARNING, a beacon that walks out of range
(heard weaker) or stops is INFO, once per drop."""

from __future__ import annotations

import logging

import pytest

from collector.beacon_rates import BIN_S, report_drop
from collector.live_stats import SensorLive
from collector.readings import count_beacons, from_tuples
from collector.store import RunWriter

BEACON = bytes.fromhex("e78f135624ce")
OTHER = bytes.fromhex("aa0000000001")


def feed(live: SensorLive, t0: float, seconds: float, per_s: int, rssi: int, beacon=BEACON):
    """``per_s`` readings a second of ``beacon`` at ``rssi``, one batch every 0.1 s."""
    drops = []
    steps = int(seconds * 10)
    for k in range(steps):
        now = t0 + k / 10
        n = per_s // 10 + (1 if (k % 10) < per_s % 10 else 0)
        rows = from_tuples([(0, 0, beacon, rssi)] * n)
        if len(rows):
            drops += live.add(now, rows, count_beacons(rows))
        drops += live.check(now)
    return drops, t0 + steps / 10


def test_count_beacons() -> None:
    rows = from_tuples([(0, 0, BEACON, -60), (0, 0, OTHER, -70), (0, 0, BEACON, -62)])
    assert count_beacons(rows) == {BEACON: [2, -122], OTHER: [1, -70]}


def test_throttling_is_a_warning_once(caplog: pytest.LogCaptureFixture) -> None:
    live = SensorLive("pi-1")
    drops, t = feed(live, 0.0, 120, 10, -60)
    assert drops == []
    assert live.beacon_rates(t) == {BEACON.hex(): pytest.approx(10.0, abs=0.5)}
    # the same beacon, as strong as before, now heard once a second: the receiver throttles
    drops, t = feed(live, t, 60, 1, -61)
    assert len(drops) == 1
    mac, drop = drops[0]
    assert mac == BEACON
    assert drop.throttled
    assert drop.usual_hz == pytest.approx(10.0, abs=0.5)
    with caplog.at_level(logging.INFO, logger="collector.beacon_rates"):
        report_drop("pi-1", "b827eb4521b4", mac, drop)
    (rec,) = caplog.records
    assert rec.levelno == logging.WARNING
    assert "may have started throttling" in rec.getMessage()
    assert "sensor-agent doctor" in rec.getMessage()
    # it recovers, then throttles again: a second warning
    drops, t = feed(live, t, 60, 10, -60)
    assert drops == []
    drops, t = feed(live, t, 30, 1, -60)
    assert len(drops) == 1


def test_out_of_range_and_silence_are_told_apart(caplog: pytest.LogCaptureFixture) -> None:
    live = SensorLive("pi-1")
    _, t = feed(live, 0.0, 120, 10, -65)
    drops, t = feed(live, t, 30, 1, -90)  # heard rarely and 25 dB weaker: it walked away
    (_, drop), *_ = drops
    assert not drop.throttled
    with caplog.at_level(logging.INFO, logger="collector.beacon_rates"):
        report_drop("pi-1", "s", BEACON, drop)
    assert caplog.records[-1].levelno == logging.INFO
    assert "moved out of its range" in caplog.records[-1].getMessage()

    live = SensorLive("pi-1")
    _, t = feed(live, 0.0, 120, 10, -65)
    drops = live.check(t + 2 * BIN_S)  # not heard at all since
    (_, drop), *_ = drops
    assert drop.rssi is None
    assert not drop.throttled
    assert "not heard at all" in drop.describe("pi-1", "s", BEACON.hex())


def test_a_slow_beacon_is_never_a_drop() -> None:
    """Below 0.5 readings/s there is too little to tell a drop from chance."""
    live = SensorLive("pi-1")
    drops, t = feed(live, 0.0, 300, 0, -60)
    for k in range(0, 300, 3):
        rows = from_tuples([(0, 0, OTHER, -60)])
        drops += live.add(t + k, rows, count_beacons(rows))
    drops += live.check(t + 400)
    assert drops == []


def test_run_yaml_counts_per_beacon_survive_a_restart(tmp_path) -> None:
    w = RunWriter(tmp_path, "r1", "n", 1_795_318_500 * 10**9, {"site": "default"})
    rows = from_tuples([(0, 0, BEACON, -60), (0, 0, OTHER, -70), (0, 0, BEACON, -62)])
    w.append("pi-1", "b827eb4521b4", "x\n", 3, count_beacons(rows))
    w.append("pi-1", "b827eb4521b4", "x\n", 1, count_beacons(rows[:1]))
    st = w.sensors[("pi-1", "b827eb4521b4")]
    assert st.beacons == {BEACON.hex(): 3, OTHER.hex(): 1}
    state = w.state()
    w.close()
    again = RunWriter(tmp_path, "r1", "n", 1_795_318_500 * 10**9, {"site": "default"}, resume=state)
    assert again.sensors[("pi-1", "b827eb4521b4")].beacons == {BEACON.hex(): 3, OTHER.hex(): 1}
    again.close()
