"""The stream caps and the live per-sensor figures, on their own (collector/admission.py,
collector/live_stats.py)."""

from __future__ import annotations

import pytest

from collector.admission import StreamGate
from collector.config import Limits
from collector.live_stats import RATE_WINDOW_S, SensorLive


def test_gate_admits_up_to_the_caps_and_counts_refusals() -> None:
    gate = StreamGate(Limits(streams_per_agent=2, streams_total=3))
    assert gate.admit("a", "m1", 0.0)
    assert gate.admit("a", "m2", 0.0)
    assert not gate.admit("a", "m3", 0.0)  # the agent's cap
    assert gate.admit("b", "m1", 0.0)
    assert not gate.admit("c", "m9", 0.0)  # the total cap
    assert gate.admitted == {("a", "m1"), ("a", "m2"), ("b", "m1")}
    assert dict(gate.refused) == {"a": 1, "c": 1}
    assert gate.refused_streams == {("a", "m3"), ("c", "m9")}
    assert gate.shared_sensors() == {"m1": ["a", "b"]}


def test_live_rate_counts_the_last_window() -> None:
    live = SensorLive("a")
    live.add(0.0, [(0, 0, b"", -60)] * 10)
    live.add(1.0, [(0, 0, b"", -70)] * 5)
    assert live.readings == 15
    assert live.last_rssi == -70
    assert live.rate(1.0) == pytest.approx(15 / RATE_WINDOW_S)
    assert live.rate(RATE_WINDOW_S + 0.5) == pytest.approx(
        5 / RATE_WINDOW_S
    )  # first batch aged out
    assert list(live.rssi)[-1] == -70
