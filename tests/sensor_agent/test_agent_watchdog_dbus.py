"""The bleak backend's watchdog against python-dbusmock's ``bluez5`` template: a silent adapter's
scanner is restarted and resumes; when restarting does not help the adapter is power-cycled
over D-Bus and found again by its MAC under a new hciN."""

from __future__ import annotations

import asyncio
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

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

from bgt_core.wire import Reading  # noqa: E402
from polling import wait_for_async as wait_for  # noqa: E402
from sensor_agent.scanning.bleak_backend import BleakBackend  # noqa: E402

DEVICE_IFACE = "org.bluez.Device1"
ADAPTER_IFACE = "org.bluez.Adapter1"
BLUEZ_MOCK_IFACE = "org.bluez.Mock"
ENV = "DBUS_SYSTEM_BUS_ADDRESS"
MAC = "000102030405"  # the template derives it from the last digit of hciN: hci0 and hci10 agree


@pytest.fixture
def mock_log(tmp_path: Path) -> Path:
    """Where the mock BlueZ writes one line per call it serves (property Sets included)."""
    return tmp_path / "bluez-mock.log"


@pytest.fixture
def bluez(mock_log: Path) -> Iterator:
    old = os.environ.get(ENV)
    dbusmock.DBusTestCase.start_system_bus()
    with mock_log.open("w") as out:
        proc, obj = dbusmock.DBusTestCase.spawn_server_template(
            "bluez5", {}, stdout=out, system_bus=True
        )
    try:
        yield obj
    finally:
        proc.terminate()
        proc.wait(5)
        dbusmock.DBusTestCase.tearDownClass()
        if old is None:
            os.environ.pop(ENV, None)
        else:
            os.environ[ENV] = old


def add_beacon(bluez, adapter: str) -> str:
    path = bluez.AddDevice(adapter, "E7:8F:13:56:24:CE", "beacon1", dbus_interface=BLUEZ_MOCK_IFACE)
    obj(path).UpdateProperties(
        DEVICE_IFACE,
        {
            "ManufacturerData": dbus.Dictionary({}, signature="qv"),
            "ServiceData": dbus.Dictionary({}, signature="sv"),
        },
        dbus_interface=dbusmock.MOCK_IFACE,
    )
    return path


def obj(path: str):
    return dbusmock.DBusTestCase.get_dbus(True).get_object("org.bluez", path)


async def advert(path: str, rssi: int) -> None:
    await asyncio.to_thread(
        obj(path).UpdateProperties,
        DEVICE_IFACE,
        {"RSSI": dbus.Int16(rssi)},
        dbus_interface=dbusmock.MOCK_IFACE,
    )


def test_silent_adapter_is_restarted_and_resumes(bluez) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    beacon = add_beacon(bluez, "hci0")
    got: list[tuple[str, Reading]] = []

    async def main() -> None:
        backend = BleakBackend(["hci0"], "active", watchdog_silence_s=0.5, power_cycle_after=100)
        await backend.start(lambda mac, r: got.append((mac, r)))
        try:
            await advert(beacon, -60)
            await wait_for(lambda: len(got) == 1)
            assert backend.restarts(MAC) == 0
            await wait_for(lambda: backend.restarts(MAC) >= 1)  # silence -> scanner restarted
            assert backend.power_cycles(MAC) == 0
            await advert(beacon, -61)
            await wait_for(lambda: len(got) == 2)
        finally:
            await backend.stop()

    asyncio.run(main())
    assert [(mac, r.rssi) for mac, r in got] == [(MAC, -60), (MAC, -61)]


def test_adapter_still_silent_is_power_cycled_and_refound_by_mac(bluez, mock_log: Path) -> None:
    bluez.AddAdapter("hci0", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE)
    beacon = add_beacon(bluez, "hci0")
    got: list[tuple[str, Reading]] = []

    async def main() -> None:
        backend = BleakBackend([MAC], "active", watchdog_silence_s=0.5, power_cycle_after=1)
        await backend.start(lambda mac, r: got.append((mac, r)))
        try:
            await advert(beacon, -60)
            await wait_for(lambda: len(got) == 1)
            # The controller falls off the bus and comes back as hci10 with the same address:
            # restarting the scanner on hci0 cannot help; the power-cycle path finds it by MAC.
            await asyncio.to_thread(
                bluez.RemoveAdapterWithDevices, "hci0", dbus_interface=BLUEZ_MOCK_IFACE
            )
            await asyncio.to_thread(
                bluez.AddAdapter, "hci10", "pi-a", dbus_interface=BLUEZ_MOCK_IFACE
            )
            new_beacon = await asyncio.to_thread(add_beacon, bluez, "hci10")
            await wait_for(lambda: backend.power_cycles(MAC) >= 1)
            assert backend.restarts(MAC) >= 1  # a plain restart came first
            await wait_for(lambda: backend.adapters[0].name == "hci10")
            powered = await asyncio.to_thread(
                obj("/org/bluez/hci10").Get,
                ADAPTER_IFACE,
                "Powered",
                dbus_interface="org.freedesktop.DBus.Properties",
            )
            assert bool(powered)  # switched off and on again, not left off
            await asyncio.sleep(0.3)  # let the new scanner settle
            await advert(new_beacon, -70)
            await wait_for(lambda: len(got) >= 2)
        finally:
            await backend.stop()

    asyncio.run(main())
    assert [(mac, r.rssi) for mac, r in got[:2]] == [(MAC, -60), (MAC, -70)]
    sets = [
        line.split(" ", 1)[1]
        for line in mock_log.read_text().splitlines()
        if " Set /org/bluez/" in line
    ]
    assert sets[:2] == [
        "Set /org/bluez/hci10 org.bluez.Adapter1.Powered False",
        "Set /org/bluez/hci10 org.bluez.Adapter1.Powered True",
    ]
