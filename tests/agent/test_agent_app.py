"""Agent pieces that need no network: the beacon allowlist and the per-adapter statistics."""

from __future__ import annotations

import pytest

from ble_groundtruth.wire import IBeacon, Reading
from sensor_agent.app import AdapterStats, allowed, new_boot_id
from sensor_agent.config import AllowList

UUID = "e2c56db5dffb48d2b060d0f5a71096e0"


def make_reading(beacon: str = "e78f135624ce", ibeacon: IBeacon | None = None) -> Reading:
    return Reading(1_700_000_000 * 10**9, beacon, -60, 1, ibeacon)


@pytest.mark.parametrize(("allow", "reading", "kept"), [
    (AllowList(), make_reading(), True),
    (AllowList(frozenset({"e78f135624ce"})), make_reading(), True),
    (AllowList(frozenset({"e78f135624cf"})), make_reading(), False),
    (AllowList(ibeacon_uuids=frozenset({UUID})), make_reading(), False),
    (AllowList(ibeacon_uuids=frozenset({UUID})),
     make_reading("aabbccddeeff", IBeacon(UUID, 1, 2, -59)), True),
    (AllowList(ibeacon_uuids=frozenset({UUID})),
     make_reading("aabbccddeeff", IBeacon("0" * 32, 1, 2, -59)), False),
])
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
