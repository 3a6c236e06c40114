"""The stream caps and the live per-sensor figures, on their own (collector/admission.py,
collector/live_stats.py)."""

from __future__ import annotations

import pytest

from collector.admission import StreamGate
from collector.config import Limits
from collector.live_stats import RATE_WINDOW_S, SensorLive
from collector.readings import from_tuples


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
    live.add(0.0, from_tuples([(0, 0, bytes(6), -60)] * 10))
    live.add(1.0, from_tuples([(0, 0, bytes(6), -70)] * 5))
    assert live.readings == 15
    assert live.last_rssi == -70
    assert live.rate(1.0) == pytest.approx(15 / RATE_WINDOW_S)
    assert live.rate(RATE_WINDOW_S + 0.5) == pytest.approx(
        5 / RATE_WINDOW_S
    )  # first batch aged out
    assert list(live.rssi)[-1] == -70


def test_per_agent_quotas_refuse_and_count() -> None:
    """limits.agent_readings_per_s (a 10 s token bucket) and agent_mb_per_run (issue 35)."""
    gate = StreamGate(Limits(agent_readings_per_s=10, agent_mb_per_run=1))
    # 100 readings of burst, then 10/s
    assert all(gate.quota("a", 10, 100, 0.0) is None for _ in range(10))
    why = gate.quota("a", 10, 100, 0.0)
    assert why is not None
    assert why.startswith("over limits.agent_readings_per_s (10 readings/s over 10 s)")
    assert gate.quota("b", 10, 100, 0.0) is None  # another agent has its own bucket
    assert gate.quota("a", 10, 100, 1.0) is None  # a second later: 10 more
    assert gate.quota("a", 10, 100, 1.0) is not None
    # the disk quota: 1 MB of run files per agent
    assert gate.quota("c", 1, 1024 * 1024 - 10, 0.0) is None
    why = gate.quota("c", 1, 20, 0.0)
    assert why is not None
    assert "agent_mb_per_run (1 MB in this run)" in why
    assert dict(gate.over_quota) == {"a: rate": 2, "c: disk": 1}


def test_refusals_are_owed_once_with_the_highest_seq() -> None:
    gate = StreamGate(Limits(streams_per_agent=1))
    gate.refuse("a", "boot1", "m2", 3, "stream cap: x")
    gate.refuse("a", "boot1", "m2", 7, "stream cap: x")
    gate.refuse("a", "boot1", "m2", 5, "stream cap: x")
    assert gate.nacks_due == {"a"}
    (key, r), *_ = gate.refusals["a"].items()
    assert key == ("boot1", "m2")
    assert (r.upto, r.reason) == (7, "stream cap: x")
