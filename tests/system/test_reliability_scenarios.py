"""Issue 5 "nothing lost" scenarios, each with real `collector serve` and `sensor-agent run`
processes on loopback Zenoh: faults are injected from outside (kill -9, SIGSTOP, a full tmpfs,
hostile payloads) and the run's rssi files must then hold every reading exactly once.

Sizes here are small so the folder stays within a few minutes; bench/reliability_scenarios.py
runs the same scenarios longer and prints the figures.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from reliability_harness import (
    Result,
    Scale,
    absurd_readings,
    agent_restart,
    collector_outage,
    full_disk,
    fuzz_scenario,
)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

SMALL = Scale(sensors=4, beacons=3, rate_hz=10, duration_s=16, speed=1.0)
# Outlasts a 30 s outage that starts ~4 s in, so readings keep coming while nobody listens.
LONG = Scale(sensors=4, beacons=3, rate_hz=10, duration_s=36, speed=1.0)


def _assert_clean(res: Result) -> None:
    print(res.line())
    assert not res.problems, "\n".join(res.problems)
    t = res.tally
    assert t.expected > 0
    assert (t.lost, t.duplicated, t.unexpected, t.torn) == (0, 0, 0, 0), str(t)


def test_collector_kill9_restarted_after_3s_loses_and_duplicates_nothing(tmp_path: Path) -> None:
    res = collector_outage(tmp_path, SMALL, mode="kill9", outage_s=3.0)
    _assert_clean(res)


def test_collector_unreachable_30s_loses_nothing(tmp_path: Path) -> None:
    # SIGSTOP keeps the process and its sockets but answers nothing: longer than the Zenoh lease,
    # so the agent's session drops, and the stream goes on meanwhile (it outlasts the outage).
    res = collector_outage(tmp_path, LONG, mode="sigstop", outage_s=30.0, fault_at=0.1)
    _assert_clean(res)


def test_collector_killed_and_restarted_after_30s_loses_nothing(tmp_path: Path) -> None:
    # The harder form of "unreachable": the router and its sessions are gone for 30 s, and the
    # restarted collector must pick the same run up from disk and get the gap re-sent.
    res = collector_outage(tmp_path, LONG, mode="kill9", outage_s=30.0, fault_at=0.1)
    _assert_clean(res)


def test_agent_kill9_restart_delivers_its_spool_once(tmp_path: Path) -> None:
    res = agent_restart(tmp_path, SMALL)
    _assert_clean(res)
    assert res.notes["spooled_batches"] > 0


def test_fuzz_on_data_and_control_keys_collector_survives_and_records_valid_stream(
    tmp_path: Path,
) -> None:
    res = fuzz_scenario(
        tmp_path, Scale(sensors=2, beacons=3, rate_hz=10, duration_s=16), n_data=3000, n_queries=200
    )
    _assert_clean(res)


def test_full_disk_collector_pauses_and_resumes_without_corruption(tmp_path: Path) -> None:
    res = full_disk(tmp_path, SMALL, hold_s=4.0, side="collector")
    if "skipped" in res.notes:
        pytest.skip(res.notes["skipped"])
    _assert_clean(res)
    assert res.notes["status_says_full"]


def test_full_disk_under_the_agent_spool_loses_nothing(tmp_path: Path) -> None:
    # The spool cannot write: batches are published unspooled meanwhile, and the agent says so.
    res = full_disk(
        tmp_path,
        Scale(sensors=4, beacons=3, rate_hz=10, duration_s=20),
        hold_s=4.0,
        size="1m",
        side="agent",
    )
    if "skipped" in res.notes:
        pytest.skip(res.notes["skipped"])
    _assert_clean(res)
    assert res.notes["status_says_full"]


def test_readings_with_absurd_timestamps_are_quarantined_not_recorded(tmp_path: Path) -> None:
    # Valid to the wire format (2000..2100) but decades ahead of the collector's clock.
    res = absurd_readings(tmp_path)
    _assert_clean(res)
