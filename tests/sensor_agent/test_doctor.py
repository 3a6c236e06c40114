"""`sensor-agent doctor` (issue 31) on simulated backends: an honest one, one throttled the way
BlueZ throttles without a discovery filter (a report only when the RSSI moved 8 dB) and one the
way a controller's duplicate filter does (one report per address per scan period)."""

from __future__ import annotations

import asyncio

import pytest
from typer.testing import CliRunner

from bgt_core.wire import Reading
from sensor_agent.cli import app
from sensor_agent.config import SimulatedConfig
from sensor_agent.doctor import diagnose, figures
from sensor_agent.errors import BackendError
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, ScannerBackend
from sensor_agent.scanning.simulated import SimulatedBackend

SENSORS = ("sensor10", "sensor11")


def simulated() -> SimulatedBackend:
    return SimulatedBackend.from_config(SimulatedConfig(sensors=SENSORS, rate_hz=10.0))


class Throttled(ScannerBackend):
    """A simulated radio behind a filter: ``rssi_step`` drops a report unless its RSSI moved that
    much since the last one passed (BlueZ's RSSI_THRESHOLD); ``period_s`` passes one report per
    address per scan period (a duplicate filter)."""

    name = "throttled"

    def __init__(self, rssi_step: int = 0, period_s: float = 0.0) -> None:
        self.inner = simulated()
        self.rssi_step, self.period_s = rssi_step, period_s
        self._last: dict[tuple[str, str], Reading] = {}

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return self.inner.adapters

    async def start(self, sink: AdvertSink) -> None:
        def filtered(adapter: str, r: Reading) -> None:
            last = self._last.get((adapter, r.beacon))
            if last is not None:
                if self.rssi_step and abs(r.rssi - last.rssi) < self.rssi_step:
                    return
                if self.period_s and r.t_ns - last.t_ns < self.period_s * 1e9:
                    return
            self._last[(adapter, r.beacon)] = r
            sink(adapter, r)

        await self.inner.start(filtered)

    async def stop(self) -> None:
        await self.inner.stop()


class Missing(ScannerBackend):
    name = "missing"

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return ()

    async def start(self, sink: AdvertSink) -> None:
        raise BackendError("D-Bus service org.bluez not found; is bluetoothd running?")

    async def stop(self) -> None:
        pass


def test_figures_per_adapter_and_beacon() -> None:
    rs = [("a", Reading(int(t * 1e9), "b1", rssi, int(t * 1e9))) for t, rssi in
          [(0.0, -60), (0.5, -60), (1.0, -61), (4.0, -61), (4.5, -70)]]  # fmt: skip
    f = figures(rs, 5.0)[("a", "b1")]
    assert (f.reports, f.per_s, f.repeated_share, f.largest_gap_s) == (5, 1.0, 0.5, 3.0)


def test_the_throttled_modes_are_told_apart() -> None:
    modes = [
        ("rssi threshold", lambda: Throttled(rssi_step=8)),
        ("duplicate filter", lambda: Throttled(period_s=10.0)),
        ("honest", simulated),
        ("not here", Missing),
    ]
    d = asyncio.run(diagnose(modes, 3.0))
    by = {m.mode: m for m in d.modes}
    assert d.recommended == "honest"
    assert not by["honest"].throttled
    assert by["honest"].median_rate > 7  # 10 adverts/s, 5 % lost
    assert 0.05 < statistics_share(by["honest"]) < 0.4  # 3 dB noise repeats a value now and then
    assert by["rssi threshold"].throttled
    assert statistics_share(by["rssi threshold"]) == 0.0
    assert by["duplicate filter"].throttled
    assert "org.bluez" in str(by["not here"].error)


def statistics_share(m) -> float:
    return sum(f.repeated_share for f in m.beacons.values()) / len(m.beacons)


def test_every_mode_throttled_is_no_recommendation() -> None:
    d = asyncio.run(diagnose([("dup", lambda: Throttled(period_s=10.0))], 2.0))
    assert d.recommended is None
    assert d.modes[0].throttled


def test_without_bluetooth_one_line_and_exit_1() -> None:
    """This machine: no kernel Bluetooth and no BlueZ."""
    res = CliRunner().invoke(app, ["doctor", "--seconds", "2"])
    if res.exit_code == 0:
        pytest.skip("this machine has Bluetooth")
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    assert lines[0].startswith("no usable Bluetooth here (mgmt: ")
