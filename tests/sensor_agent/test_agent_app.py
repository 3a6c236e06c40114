"""Agent pieces that need no network: the beacon allowlist and the per-adapter statistics."""

from __future__ import annotations

import pytest

from bgt_core.wire import IBeacon, Reading
from sensor_agent.app import AdapterStats, allowed, new_boot_id
from sensor_agent.config import AllowList

UUID = "e2c56db5dffb48d2b060d0f5a71096e0"


def make_reading(beacon: str = "e78f135624ce", ibeacon: IBeacon | None = None) -> Reading:
    return Reading(1_700_000_000 * 10**9, beacon, -60, 1, ibeacon)


@pytest.mark.parametrize(
    ("allow", "reading", "kept"),
    [
        (AllowList(), make_reading(), True),
        (AllowList(frozenset({"e78f135624ce"})), make_reading(), True),
        (AllowList(frozenset({"e78f135624cf"})), make_reading(), False),
        (AllowList(ibeacon_uuids=frozenset({UUID})), make_reading(), False),
        (
            AllowList(ibeacon_uuids=frozenset({UUID})),
            make_reading("aabbccddeeff", IBeacon(UUID, 1, 2, -59)),
            True,
        ),
        (
            AllowList(ibeacon_uuids=frozenset({UUID})),
            make_reading("aabbccddeeff", IBeacon("0" * 32, 1, 2, -59)),
            False,
        ),
    ],
)
def test_allowlist(allow: AllowList, reading: Reading, kept: bool) -> None:
    assert allowed(allow, reading) is kept


def test_adapter_rate_over_complete_seconds() -> None:
    st = AdapterStats()
    s = 1_000_000_000
    for sec in range(100, 106):  # 20 adverts in each of six seconds
        for i in range(20):
            st.record(sec * s + i * 50_000_000)
    assert st.readings_total == 120
    assert st.rate(106 * s) == 20.0  # seconds 101..105
    assert st.rate(108 * s) == pytest.approx(12.0)  # 103..107: three full seconds
    assert st.rate(200 * s) == 0.0


def test_boot_ids_are_fresh_16_hex() -> None:
    a, b = new_boot_id(), new_boot_id()
    assert a != b
    assert len(a) == 16
    assert int(a, 16) >= 0


class _Collecting:
    """Stands in for the publisher: keeps what the sink passes on."""

    def __init__(self) -> None:
        self.added: list[tuple[str, Reading]] = []

    def add(self, sensor: str, reading: Reading) -> None:
        self.added.append((sensor, reading))


def test_sink_skips_implausible_readings_one_by_one_and_counts_them(caplog) -> None:
    from sensor_agent.app import Agent
    from sensor_agent.config import AgentConfig
    from sensor_agent.scanning.replay import ReplayBackend

    agent = Agent(AgentConfig(agent_id="pi-01"), ReplayBackend(["unused.mbd"]))
    pub = agent._publisher = _Collecting()
    t = 1_700_000_000 * 10**9
    sent = [
        Reading(t, "e78f135624ce", -60, 1),
        Reading(t + 1, "e78f135624ce", 42, 2),
        Reading(t + 2, "e78f135624ce", 127, 3),  # BlueZ's "unknown"
        Reading(5, "e78f135624ce", -61, 4),  # 1970
        Reading(t + 4, "e78f135624ce", -62, 5),
    ]
    for r in sent:
        agent._sink("aa0000000001", r)
    assert [r for _s, r in pub.added] == [sent[0], sent[4]]
    assert agent.readings == 2
    assert agent.bad_readings == 3
    assert agent.stats["aa0000000001"].bad_readings == 3
    warned = [r.getMessage() for r in caplog.records if "implausible" in r.getMessage()]
    assert warned == [
        "adapter aa0000000001: skipped an implausible reading of beacon e78f135624ce "
        "(RSSI 42 dBm out of range); 1 skipped so far"
    ]  # one line a minute
