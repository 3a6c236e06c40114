"""Real adapters through BlueZ: one ``BleakScanner`` per adapter, every advertisement reported.

The only module that imports bleak (and talks to BlueZ over D-Bus). Adapters are identified by
the address BlueZ reports in ``org.bluez.Adapter1.Address``; that MAC is the sensor id.
A watchdog restarts a scanner that has gone silent, and counts the restarts for the status.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass

from bleak import BleakScanner
from bleak.args.bluez import OrPattern
from bleak.assigned_numbers import AdvertisementDataType
from bleak.backends.device import BLEDevice
from bleak.backends.scanner import AdvertisementData
from bleak.exc import BleakError
from dbus_fast import BusType, Message, MessageType
from dbus_fast.aio import MessageBus
from dbus_fast.errors import DBusError

from ble_groundtruth.wire import RSSI_MAX, RSSI_MIN, Reading, WireError, normalize_mac
from sensor_agent.errors import BackendError
from sensor_agent.scanning.adverts import parse_eddystone, parse_ibeacon
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, Clocks, ScannerBackend

log = logging.getLogger(__name__)

BLUEZ = "org.bluez"
ADAPTER_IFACE = "org.bluez.Adapter1"
MONITOR_MANAGER_IFACE = "org.bluez.AdvertisementMonitorManager1"
OBJECT_MANAGER_IFACE = "org.freedesktop.DBus.ObjectManager"
NO_BLUEZ = "D-Bus service org.bluez not found; is bluetoothd running?"

# Passive scanning only reports advertisements matching a monitor pattern. Almost every LE
# advertiser sends a Flags field; these three values cover general/limited discoverable and
# LE-only devices (the same choice Home Assistant's scanner makes), plus Apple's iBeacon prefix.
PASSIVE_OR_PATTERNS = [
    OrPattern(0, AdvertisementDataType.FLAGS, b"\x02"),
    OrPattern(0, AdvertisementDataType.FLAGS, b"\x06"),
    OrPattern(0, AdvertisementDataType.FLAGS, b"\x1a"),
    OrPattern(0, AdvertisementDataType.MANUFACTURER_SPECIFIC_DATA, b"\x4c\x00\x02\x15"),
]

WATCHDOG_SILENCE_S = 60.0  # an adapter with nothing heard for this long gets its scanner restarted
WATCHDOG_CHECK_S = 5.0


@dataclass(frozen=True, slots=True)
class BluezAdapter:
    name: str  # "hci0"
    path: str  # "/org/bluez/hci0"
    address: str  # 12 lowercase hex digits
    powered: bool
    alias: str
    passive_capable: bool  # exposes AdvertisementMonitorManager1


async def _managed_objects() -> dict:
    try:
        bus = await MessageBus(bus_type=BusType.SYSTEM).connect()
    except (OSError, ValueError, DBusError) as e:
        raise BackendError(f"cannot connect to the D-Bus system bus ({e}); is dbus running?") from e
    try:
        reply = await bus.call(Message(destination=BLUEZ, path="/", interface=OBJECT_MANAGER_IFACE,
                                       member="GetManagedObjects"))
    finally:
        bus.disconnect()
    if reply.message_type == MessageType.ERROR:
        if reply.error_name in ("org.freedesktop.DBus.Error.ServiceUnknown",
                                "org.freedesktop.DBus.Error.NameHasNoOwner"):
            raise BackendError(NO_BLUEZ)
        detail = reply.body[0] if reply.body else ""
        raise BackendError(f"BlueZ refused GetManagedObjects: {reply.error_name} {detail}".strip())
    return reply.body[0]


async def list_adapters() -> list[BluezAdapter]:
    """Every adapter BlueZ knows, with the address it reports over D-Bus, sorted by name."""
    out = []
    for path, ifaces in (await _managed_objects()).items():
        props = ifaces.get(ADAPTER_IFACE)
        if props is None:
            continue
        try:
            address = normalize_mac(props["Address"].value)
        except (KeyError, WireError):
            log.warning("adapter %s reports no usable Address; skipped", path)
            continue
        out.append(BluezAdapter(
            name=path.rsplit("/", 1)[-1], path=path, address=address,
            powered=bool(props["Powered"].value) if "Powered" in props else False,
            alias=str(props["Alias"].value) if "Alias" in props else "",
            passive_capable=MONITOR_MANAGER_IFACE in ifaces))
    return sorted(out, key=lambda a: a.name)


def select_adapters(found: Sequence[BluezAdapter], wanted: Sequence[str]) -> list[BluezAdapter]:
    """The adapters named (hci0) or addressed (MAC) in ``wanted``; all of them if it is empty."""
    if not found:
        raise BackendError("BlueZ reports no Bluetooth adapter")
    if not wanted:
        return list(found)
    have = ", ".join(f"{a.name} {a.address}" for a in found)
    out = []
    for w in wanted:
        try:
            mac = normalize_mac(w)
        except WireError:
            mac = None
        match = next((a for a in found if a.name == w or a.address == mac), None)
        if match is None:
            raise BackendError(f"adapter {w!r} not found (BlueZ has: {have})")
        if match not in out:
            out.append(match)
    return out


class _AdapterScanner:
    """One adapter's BleakScanner plus what the watchdog needs to know about it."""

    def __init__(self, adapter: BluezAdapter, mode: str, callback) -> None:
        self.adapter = adapter
        self.mode = mode
        self.callback = callback
        self.scanner: BleakScanner | None = None
        self.last_mono_ns: int | None = None
        self.restarts = 0

    def _new_scanner(self) -> BleakScanner:
        bluez: dict = {"adapter": self.adapter.name}
        if self.mode == "passive":
            bluez["or_patterns"] = PASSIVE_OR_PATTERNS
        else:
            # DuplicateData: report every advertisement, not only changes (one reading per advert).
            bluez["filters"] = {"DuplicateData": True}
        return BleakScanner(self.callback, None, self.mode, bluez=bluez)

    async def start(self) -> None:
        self.scanner = self._new_scanner()
        try:
            await self.scanner.start()
        except BleakError as e:
            self.scanner = None
            raise BackendError(f"adapter {self.adapter.name} ({self.adapter.address}): "
                               f"cannot start {self.mode} scanning: {e}") from e

    async def stop(self) -> None:
        scanner, self.scanner = self.scanner, None
        if scanner is not None:
            try:
                await scanner.stop()
            except BleakError as e:  # the adapter may be gone already; nothing left to stop
                log.warning("adapter %s: stopping the scanner failed: %s", self.adapter.name, e)


class BleakBackend(ScannerBackend):
    name = "bleak"

    def __init__(self, adapters: Sequence[str] = (), scan_mode: str = "active",
                 clocks: Clocks | None = None, watchdog_silence_s: float = WATCHDOG_SILENCE_S) -> None:
        if scan_mode not in ("active", "passive"):
            raise BackendError(f"scan mode must be active or passive, got {scan_mode!r}")
        self.wanted = tuple(adapters)
        self.scan_mode = scan_mode
        self.clocks = clocks or Clocks()
        self.watchdog_silence_s = watchdog_silence_s
        self._scanners: list[_AdapterScanner] = []
        self._sink: AdvertSink | None = None
        self._watchdog: asyncio.Task[None] | None = None

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return tuple(AdapterInfo(s.adapter.name, s.adapter.address, "bleak", s.mode)
                     for s in self._scanners)

    def restarts(self, adapter_mac: str) -> int:
        return next((s.restarts for s in self._scanners if s.adapter.address == adapter_mac), 0)

    async def start(self, sink: AdvertSink) -> None:
        self._sink = sink
        chosen = select_adapters(await list_adapters(), self.wanted)
        if self.scan_mode == "passive":
            lacking = [a.name for a in chosen if not a.passive_capable]
            if lacking:
                raise BackendError(
                    f"passive scanning needs BlueZ's AdvertisementMonitorManager1, which "
                    f"{', '.join(lacking)} lacks (BlueZ >= 5.56 started with --experimental); "
                    "use scan_mode: active")
        for a in chosen:
            if not a.powered:
                log.warning("adapter %s (%s) is powered off; it will hear nothing", a.name, a.address)
            s = _AdapterScanner(a, self.scan_mode, None)
            s.callback = functools.partial(self._on_advert, s)
            self._scanners.append(s)
        try:
            for s in self._scanners:
                await s.start()
                s.last_mono_ns = self.clocks.mono_ns()
                log.info("scanning on %s (%s), %s", s.adapter.name, s.adapter.address, s.mode)
        except BaseException:
            await self.stop()
            raise
        self._watchdog = asyncio.create_task(self._watch(), name="bleak-watchdog")

    def _on_advert(self, s: _AdapterScanner, device: BLEDevice, adv: AdvertisementData) -> None:
        # Stamp first: the reception time is the whole point of the dataset.
        t_ns, mono = self.clocks.wall_ns(), self.clocks.mono_ns()
        s.last_mono_ns = mono
        try:
            beacon = normalize_mac(device.address)
        except WireError:
            return  # not a MAC-shaped address (should not happen with BlueZ)
        rssi = max(RSSI_MIN, min(RSSI_MAX, int(adv.rssi)))
        reading = Reading(t_ns, beacon, rssi, mono, parse_ibeacon(adv.manufacturer_data),
                          parse_eddystone(adv.service_data))
        if self._sink is not None:
            self._sink(s.adapter.address, reading)

    async def _watch(self) -> None:
        """Restart scanners that have been silent too long (BlueZ discovery sometimes stalls)."""
        silence_ns = int(self.watchdog_silence_s * 1e9)
        while True:
            await self.clocks.sleep(min(WATCHDOG_CHECK_S, self.watchdog_silence_s))
            now = self.clocks.mono_ns()
            for s in self._scanners:
                if s.last_mono_ns is not None and now - s.last_mono_ns > silence_ns:
                    log.warning("adapter %s silent for %.0f s; restarting its scanner",
                                s.adapter.name, (now - s.last_mono_ns) / 1e9)
                    await s.stop()
                    try:
                        await s.start()
                    except BackendError as e:
                        log.warning("%s; will retry", e)
                    s.restarts += 1
                    s.last_mono_ns = now

    async def stop(self) -> None:
        if self._watchdog is not None:
            self._watchdog.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watchdog
            self._watchdog = None
        self._sink = None
        for s in self._scanners:
            await s.stop()
