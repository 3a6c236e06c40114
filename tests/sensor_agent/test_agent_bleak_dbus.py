"""The bleak backend against python-dbusmock's ``bluez5`` template on a private system bus:
real bleak and dbus-fast code, BlueZ mocked only at its D-Bus interface."""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

pytestmark = [
    pytest.mark.dbus,
    pytest.mark.skipif(
        shutil.which("dbus-daemon") is None,
        reason="dbus-daemon is not installed (needed for a private D-Bus)",
    ),
]

dbus = pytest.importorskip("dbus")
dbusmock = pytest.importorskip("dbusmock")

from bgt_core.wire import IBeacon, Reading  # noqa: E402
from polling import wait_for_async as wait_for  # noqa: E402
from sensor_agent.errors import BackendError  # noqa: E402
from sensor_agent.scanning.bleak_backend import BleakBackend, list_adapters  # noqa: E402

DEVICE_IFACE = "org.bluez.Device1"
BLUEZ_MOCK_IFACE = "org.bluez.Mock"
UUID = "e2c56db5dffb48d2b060d0f5a71096e0"
ENV = "DBUS_SYSTEM_BUS_ADDRESS"
AGENT = [sys.executable, "-c", "from sensor_agent.cli import main; main()"]


@pytest.fixture
def system_bus() -> Iterator[str]:
    """A private system bus (address exported in DBUS_SYSTEM_BUS_ADDRESS while the test runs)."""
    old = os.environ.get(ENV)
    dbusmock.DBusTestCase.start_system_bus()
    try:
        yield os.environ[ENV]
    finally:
        dbusmock.DBusTestCase.tearDownClass()
        if old is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = old


def spawn_bluez(parameters: dict | None = None):
    proc, obj = dbusmock.DBusTestCase.spawn_server_template(
        "bluez5", parameters or {}, stdout=subprocess.DEVNULL, system_bus=True
    )
    return proc, obj


@pytest.fixture
def bluez(system_bus: str) -> Iterator:
    proc, obj = spawn_bluez()
    try:
        yield obj
    finally:
        proc.terminate()
        proc.wait(5)


def ibeacon_md(major: int, minor: int, tx: int = -59) -> dbus.Dictionary:
    payload = (
        b"\x02\x15"
        + bytes.fromhex(UUID)
        + major.to_bytes(2, "big")
        + minor.to_bytes(2, "big")
        + bytes([tx & 0xFF])
    )
    return dbus.Dictionary(
        {dbus.UInt16(0x004C): dbus.Array(payload, signature="y")}, signature="qv"
    )


def device(path: str):
    return dbusmock.DBusTestCase.get_dbus(True).get_object("org.bluez", path)


def test_two_adapters_listed_with_their_dbus_addresses(bluez) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    bluez.AddAdapter("hci1", "pi-b", dbus_interface=BLUEZ_MOCK_IFACE)
    found = asyncio.run(list_adapters())
    assert [(a.name, a.address, a.powered, a.alias) for a in found] == [
        ("hci0", "000102030405", True, "pi-a"),
        ("hci1", "010203040506", True, "pi-b"),
    ]
    assert all(a.passive_capable for a in found)


def add_beacon(bluez, adapter: str) -> str:
    """A beacon device under ``adapter``, with dict-typed advertising properties.

    The template creates ManufacturerData/ServiceData as empty *arrays* (real BlueZ sends a
    dict or omits them), which bleak cannot read; setting empty dicts first makes them BlueZ-like.
    """
    path = bluez.AddDevice(adapter, "E7:8F:13:56:24:CE", "beacon1", dbus_interface=BLUEZ_MOCK_IFACE)
    device(path).UpdateProperties(
        DEVICE_IFACE,
        {
            "ManufacturerData": dbus.Dictionary({}, signature="qv"),
            "ServiceData": dbus.Dictionary({}, signature="sv"),
        },
        dbus_interface=dbusmock.MOCK_IFACE,
    )
    return path


EDDYSTONE_UID = b"\x00\xee" + bytes(range(10)) + bytes.fromhex("aabbccddeeff")


def test_every_rssi_update_delivered_with_its_ibeacon(bluez) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    bluez.AddAdapter("hci1", "pi-b", dbus_interface=BLUEZ_MOCK_IFACE)
    paths = {a: add_beacon(bluez, a) for a in ("hci0", "hci1")}
    got: list[tuple[str, Reading]] = []
    # (adapter, rssi, major, minor) updates, including a repeated RSSI value
    updates = [
        ("hci0", -60, 1, 1),
        ("hci1", -70, 1, 1),
        ("hci0", -61, 1, 2),
        ("hci0", -61, 1, 3),
        ("hci1", -72, 2, 7),
        ("hci0", -65, 3, 9),
    ]

    async def main() -> None:
        backend = BleakBackend((), "active")
        await backend.start(lambda mac, r: got.append((mac, r)))
        assert [(a.name, a.mac, a.mode) for a in backend.adapters] == [
            ("hci0", "000102030405", "active"),
            ("hci1", "010203040506", "active"),
        ]
        t_before = time.time_ns()
        for adapter, rssi, major, minor in updates:
            await asyncio.to_thread(
                device(paths[adapter]).UpdateProperties,
                DEVICE_IFACE,
                {"RSSI": dbus.Int16(rssi), "ManufacturerData": ibeacon_md(major, minor)},
                dbus_interface=dbusmock.MOCK_IFACE,
            )
        # an Eddystone frame arrives as service data
        await asyncio.to_thread(
            device(paths["hci1"]).UpdateProperties,
            DEVICE_IFACE,
            {
                "RSSI": dbus.Int16(-75),
                "ServiceData": dbus.Dictionary(
                    {
                        "0000feaa-0000-1000-8000-00805f9b34fb": dbus.Array(
                            EDDYSTONE_UID, signature="y"
                        )
                    },
                    signature="sv",
                ),
            },
            dbus_interface=dbusmock.MOCK_IFACE,
        )
        await wait_for(lambda: len(got) == len(updates) + 1)
        await backend.stop()
        assert all(t_before <= r.t_ns <= time.time_ns() for _, r in got)

    asyncio.run(main())
    adapter_mac = {"hci0": "000102030405", "hci1": "010203040506"}
    delivered = [(mac, r.beacon, r.rssi, r.ibeacon) for mac, r in got[:-1]]
    assert delivered == [
        (adapter_mac[a], "e78f135624ce", rssi, IBeacon(UUID, major, minor, -59))
        for a, rssi, major, minor in updates
    ]
    mac, last = got[-1]
    assert (mac, last.rssi) == ("010203040506", -75)
    assert last.eddystone is not None
    assert last.eddystone.instance == "aabbccddeeff"
    assert all(r.mono_ns > 0 for _, r in got)


def test_adapter_selection_by_name_or_mac(bluez) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    bluez.AddAdapter("hci1", "pi-b", dbus_interface=BLUEZ_MOCK_IFACE)

    async def main() -> None:
        backend = BleakBackend(["01:02:03:04:05:06"], "active")
        await backend.start(lambda mac, r: None)
        assert [a.name for a in backend.adapters] == ["hci1"]
        await backend.stop()
        with pytest.raises(
            BackendError, match=r"adapter 'hci7' not found \(BlueZ has: hci0 000102030405"
        ):
            await BleakBackend(["hci7"]).start(lambda mac, r: None)

    asyncio.run(main())


def test_passive_scanning_registers_a_monitor(bluez) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)

    async def main() -> None:
        backend = BleakBackend(["hci0"], "passive")
        await backend.start(lambda mac, r: None)
        assert backend.adapters[0].mode == "passive"
        await backend.stop()

    asyncio.run(main())


def test_passive_without_monitor_api_is_a_clear_error(system_bus: str) -> None:
    proc, obj = spawn_bluez({"enable_monitor_api": False})
    try:
        obj.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
        with pytest.raises(
            BackendError,
            match="passive scanning needs BlueZ's AdvertisementMonitorManager1, which hci0 lacks",
        ):
            asyncio.run(BleakBackend(["hci0"], "passive").start(lambda mac, r: None))
    finally:
        proc.terminate()
        proc.wait(5)


def test_adapters_command(bluez, system_bus: str) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    bluez.AddAdapter("hci1", "pi-b", dbus_interface=BLUEZ_MOCK_IFACE)
    r = subprocess.run(
        AGENT + ["adapters"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, ENV: system_bus},
    )
    assert r.returncode == 0, r.stderr
    assert [line.split("\t")[:2] for line in r.stdout.splitlines()] == [
        ["hci0", "000102030405"],
        ["hci1", "010203040506"],
    ]


def test_adapters_command_without_bluez(system_bus: str) -> None:
    r = subprocess.run(
        AGENT + ["adapters"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, ENV: system_bus},
    )
    assert r.returncode == 1
    assert r.stderr.strip() == "D-Bus service org.bluez not found; is bluetoothd running?"


def test_watchdog_restarts_a_silent_scanner(bluez) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    path = add_beacon(bluez, "hci0")
    got: list[Reading] = []

    async def main() -> None:
        backend = BleakBackend(["hci0"], "active", watchdog_silence_s=0.2)
        await backend.start(lambda mac, r: got.append(r))
        await wait_for(lambda: backend.restarts("000102030405") >= 2)
        # still scanning after the restarts: a new advert arrives
        await asyncio.to_thread(
            device(path).UpdateProperties,
            DEVICE_IFACE,
            {"RSSI": dbus.Int16(-50)},
            dbus_interface=dbusmock.MOCK_IFACE,
        )
        await wait_for(lambda: any(r.rssi == -50 for r in got))
        await backend.stop()

    asyncio.run(main())


def test_implausible_bluez_rssi_reaches_the_agent_unclamped_and_is_skipped(bluez) -> None:
    """No clamp in the backend (a +42 dBm would become a plausible-looking +20): the agent's
    sink skips and counts the absurd values one by one and passes the rest on."""
    from sensor_agent.app import Agent
    from sensor_agent.config import AgentConfig

    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    path = add_beacon(bluez, "hci0")
    raw: list[int] = []
    kept: list[int] = []

    class Publisher:
        def add(self, _sensor: str, r: Reading) -> None:
            kept.append(r.rssi)

    backend = BleakBackend((), "active")
    agent = Agent(AgentConfig(agent_id="pi-01"), backend)
    agent._publisher = Publisher()

    def sink(mac: str, r: Reading) -> None:
        raw.append(r.rssi)
        agent._sink(mac, r)

    async def main() -> None:
        await backend.start(sink)
        for rssi in (-60, 42, 127, -61):  # 127: BlueZ's "RSSI unknown"
            await asyncio.to_thread(
                device(path).UpdateProperties,
                DEVICE_IFACE,
                {"RSSI": dbus.Int16(rssi)},
                dbus_interface=dbusmock.MOCK_IFACE,
            )
        await wait_for(lambda: len(raw) == 4)
        await backend.stop()

    asyncio.run(main())
    assert raw == [-60, 42, 127, -61]
    assert kept == [-60, -61]
    assert agent.bad_readings == 2
    assert agent.stats["000102030405"].bad_readings == 2


def test_active_scanning_sets_a_discovery_filter(bluez) -> None:
    """Without a discovery filter BlueZ reports an advertiser again only when its RSSI moved by
    8 dB (src/device.c RSSI_THRESHOLD): the filter must be set, with DuplicateData on (issue 31)."""
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)

    async def main() -> None:
        backend = BleakBackend((), "active")
        await backend.start(lambda mac, r: None)
        await backend.stop()

    asyncio.run(main())
    adapter = dbusmock.DBusTestCase.get_dbus(True).get_object("org.bluez", "/org/bluez/hci0")
    calls = adapter.GetMethodCalls("SetDiscoveryFilter", dbus_interface=dbusmock.MOCK_IFACE)
    # set when scanning starts, cleared (an empty filter) when it stops
    assert [len(args[0]) > 0 for _, args in calls] == [True, False]
    _, (arguments,) = calls[0]
    assert bool(arguments["DuplicateData"]) is True
    assert str(arguments["Transport"]) == "le"


def test_auto_falls_back_to_bleak_with_one_line(bluez, caplog) -> None:
    """backend: auto on a machine whose kernel has no Bluetooth (this one): one warning naming
    why, then the D-Bus path scans."""
    from sensor_agent.app import make_backend
    from sensor_agent.config import AgentConfig
    from sensor_agent.scanning.auto import AutoBackend
    from sensor_agent.scanning.base import Clocks
    from sensor_agent.scanning.mgmt_backend import MgmtUnavailable, open_mgmt_socket

    try:
        open_mgmt_socket().close()
        pytest.skip("this machine has a usable management socket")
    except MgmtUnavailable:
        pass
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    backend = make_backend(AgentConfig(agent_id="pi-1"), Clocks())
    assert isinstance(backend, AutoBackend)

    async def main() -> None:
        await backend.start(lambda mac, r: None)
        assert [(a.name, a.backend) for a in backend.adapters] == [("hci0", "bleak")]
        await backend.stop()

    with caplog.at_level("WARNING"):
        asyncio.run(main())
    assert isinstance(backend.active, BleakBackend)
    assert backend.fallback_reason is not None
    assert "no kernel Bluetooth stack" in backend.fallback_reason
    warned = [
        r.getMessage() for r in caplog.records if "management socket unavailable" in r.getMessage()
    ]
    assert len(warned) == 1
    assert "\n" not in warned[0]


def test_demanded_mgmt_exits_with_one_line(system_bus: str, tmp_path) -> None:
    """backend: mgmt where the socket cannot be used: the agent stops with that one line."""
    cfg = tmp_path / "agent.yaml"
    cfg.write_text("agent_id: pi-1\nbackend: mgmt\nconnect: [tcp/127.0.0.1:9]\n")
    proc = subprocess.run(
        [*AGENT, "run", "--config", str(cfg)], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    assert any("no kernel Bluetooth stack" in ln or "CAP_NET_ADMIN" in ln for ln in lines), (
        proc.stderr
    )
    assert "Traceback" not in proc.stderr
