"""Real adapters through BlueZ: one ``BleakScanner`` per adapter, every advertisement reported.

The only module that imports bleak (and talks to BlueZ over D-Bus). Adapters are identified by
the address BlueZ reports in ``org.bluez.Adapter1.Address``; that MAC is the sensor id.
A watchdog restarts a scanner that has gone silent; if restarting does not help it power-cycles
the adapter over D-Bus (``Adapter1.Powered``), finding it again by MAC since hciN may change.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from bleak import BleakScanner
from bleak.args.bluez import BlueZScannerArgs, OrPattern
from bleak.assigned_numbers import AdvertisementDataType
from bleak.backends.device import BLEDevice
from bleak.backends.scanner import AdvertisementData
from bleak.exc import BleakError
from dbus_fast import BusType, Message, MessageType, Variant
from dbus_fast.aio import MessageBus
from dbus_fast.errors import DBusError

from bgt_core.wire import Reading, WireError, normalize_mac
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
PASSIVE_OR_PATTERNS: list[OrPattern | tuple[int, AdvertisementDataType, bytes]] = [
    OrPattern(0, AdvertisementDataType.FLAGS, b"\x02"),
    OrPattern(0, AdvertisementDataType.FLAGS, b"\x06"),
    OrPattern(0, AdvertisementDataType.FLAGS, b"\x1a"),
    OrPattern(0, AdvertisementDataType.MANUFACTURER_SPECIFIC_DATA, b"\x4c\x00\x02\x15"),
]

WATCHDOG_SILENCE_S = 60.0  # an adapter with nothing heard for this long gets its scanner restarted
WATCHDOG_CHECK_S = 5.0
POWER_CYCLE_AFTER = 2  # scanner restarts without an advert before the adapter is power-cycled
PROPERTIES_IFACE = "org.freedesktop.DBus.Properties"
# BlueZ answers these while an adapter is busy changing state; they clear by themselves.
RECOVERABLE_ERRORS = frozenset(
    {"org.bluez.Error.InProgress", "org.bluez.Error.NotReady", "org.bluez.Error.Busy"}
)
POWER_RETRIES = 5
POWER_BACKOFF_S = 0.25


@dataclass(frozen=True, slots=True)
class BluezAdapter:
    name: str  # "hci0"
    path: str  # "/org/bluez/hci0"
    address: str  # 12 lowercase hex digits
    powered: bool
    alias: str
    passive_capable: bool  # exposes AdvertisementMonitorManager1


async def _managed_objects() -> dict[str, Any]:
    try:
        bus = await MessageBus(bus_type=BusType.SYSTEM).connect()
    except (OSError, ValueError, DBusError) as e:
        raise BackendError(f"cannot connect to the D-Bus system bus ({e}); is dbus running?") from e
    try:
        reply = await bus.call(
            Message(
                destination=BLUEZ,
                path="/",
                interface=OBJECT_MANAGER_IFACE,
                member="GetManagedObjects",
            )
        )
    finally:
        bus.disconnect()
    if reply.message_type == MessageType.ERROR:
        if reply.error_name in (
            "org.freedesktop.DBus.Error.ServiceUnknown",
            "org.freedesktop.DBus.Error.NameHasNoOwner",
        ):
            raise BackendError(NO_BLUEZ)
        detail = reply.body[0] if reply.body else ""
        raise BackendError(f"BlueZ refused GetManagedObjects: {reply.error_name} {detail}".strip())
    objects: dict[str, Any] = reply.body[0]
    return objects


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
        out.append(
            BluezAdapter(
                name=path.rsplit("/", 1)[-1],
                path=path,
                address=address,
                powered=bool(props["Powered"].value) if "Powered" in props else False,
                alias=str(props["Alias"].value) if "Alias" in props else "",
                passive_capable=MONITOR_MANAGER_IFACE in ifaces,
            )
        )
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

    def __init__(self, adapter: BluezAdapter, mode: str, callback: Any) -> None:
        self.adapter = adapter
        self.mode = mode
        self.callback = callback
        self.scanner: BleakScanner | None = None
        self.last_mono_ns: int | None = None
        self.restarts = 0
        self.power_cycles = 0
        self.silent_restarts = 0  # restarts since the last advertisement

    def _new_scanner(self) -> BleakScanner:
        bluez: BlueZScannerArgs = {"adapter": self.adapter.name}
        if self.mode == "passive":
            bluez["or_patterns"] = PASSIVE_OR_PATTERNS
            return BleakScanner(self.callback, None, "passive", bluez=bluez)
        # DuplicateData: report every advertisement, not only changes (one reading per advert).
        bluez["filters"] = {"DuplicateData": True}
        return BleakScanner(self.callback, None, "active", bluez=bluez)

    async def start(self) -> None:
        self.scanner = self._new_scanner()
        try:
            await self.scanner.start()
        except BleakError as e:
            self.scanner = None
            raise BackendError(
                f"adapter {self.adapter.name} ({self.adapter.address}): "
                f"cannot start {self.mode} scanning: {e}"
            ) from e

    async def stop(self) -> None:
        scanner, self.scanner = self.scanner, None
        if scanner is not None:
            try:
                await scanner.stop()
            except BleakError as e:  # the adapter may be gone already; nothing left to stop
                log.warning("adapter %s: stopping the scanner failed: %s", self.adapter.name, e)


class BleakBackend(ScannerBackend):
    name = "bleak"

    def __init__(
        self,
        adapters: Sequence[str] = (),
        scan_mode: str = "active",
        clocks: Clocks | None = None,
        watchdog_silence_s: float = WATCHDOG_SILENCE_S,
        power_cycle_after: int = POWER_CYCLE_AFTER,
    ) -> None:
        if scan_mode not in ("active", "passive"):
            raise BackendError(f"scan mode must be active or passive, got {scan_mode!r}")
        self.wanted = tuple(adapters)
        self.scan_mode = scan_mode
        self.clocks = clocks or Clocks()
        self.watchdog_silence_s = watchdog_silence_s
        self.power_cycle_after = power_cycle_after
        self._scanners: list[_AdapterScanner] = []
        self._sink: AdvertSink | None = None
        self._watchdog: asyncio.Task[None] | None = None

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return tuple(
            AdapterInfo(s.adapter.name, s.adapter.address, "bleak", s.mode) for s in self._scanners
        )

    def restarts(self, adapter_mac: str) -> int:
        return next((s.restarts for s in self._scanners if s.adapter.address == adapter_mac), 0)

    def power_cycles(self, adapter_mac: str) -> int:
        return next((s.power_cycles for s in self._scanners if s.adapter.address == adapter_mac), 0)

    async def start(self, sink: AdvertSink) -> None:
        self._sink = sink
        chosen = select_adapters(await list_adapters(), self.wanted)
        if self.scan_mode == "passive":
            lacking = [a.name for a in chosen if not a.passive_capable]
            if lacking:
                raise BackendError(
                    f"passive scanning needs BlueZ's AdvertisementMonitorManager1, which "
                    f"{', '.join(lacking)} lacks (BlueZ >= 5.56 started with --experimental); "
                    "use scan_mode: active"
                )
        for a in chosen:
            if not a.powered:
                log.warning(
                    "adapter %s (%s) is powered off; it will hear nothing", a.name, a.address
                )
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
        s.silent_restarts = 0
        try:
            beacon = normalize_mac(device.address)
        except WireError:
            return  # not a MAC-shaped address (should not happen with BlueZ)
        # Passed on as BlueZ reports it: the agent skips and counts an implausible value (BlueZ
        # says 127 for "unknown") instead of a clamp turning it into a plausible-looking one.
        reading = Reading(
            t_ns,
            beacon,
            int(adv.rssi),
            mono,
            parse_ibeacon(adv.manufacturer_data),
            parse_eddystone(adv.service_data),
        )
        if self._sink is not None:
            self._sink(s.adapter.address, reading)

    async def _watch(self) -> None:
        """Restart scanners that have been silent too long (BlueZ discovery sometimes stalls);
        power-cycle the adapter when restarting alone did not bring advertisements back."""
        silence_ns = int(self.watchdog_silence_s * 1e9)
        while True:
            await self.clocks.sleep(min(WATCHDOG_CHECK_S, self.watchdog_silence_s / 2))
            now = self.clocks.mono_ns()
            for s in self._scanners:
                if s.last_mono_ns is None or now - s.last_mono_ns <= silence_ns:
                    continue
                silent_s = (now - s.last_mono_ns) / 1e9
                await s.stop()
                if s.silent_restarts >= self.power_cycle_after:
                    log.warning(
                        "adapter %s (%s) still silent after %d scanner restart(s); "
                        "power-cycling it",
                        s.adapter.name,
                        s.adapter.address,
                        s.silent_restarts,
                    )
                    s.power_cycles += 1
                    s.silent_restarts = 0
                    try:
                        s.adapter = await power_cycle(s.adapter.address, self.clocks)
                    except BackendError as e:
                        log.warning("%s; will retry", e)
                else:
                    log.warning(
                        "adapter %s silent for %.0f s; restarting its scanner",
                        s.adapter.name,
                        silent_s,
                    )
                    s.restarts += 1
                    s.silent_restarts += 1
                try:
                    await s.start()
                except BackendError as e:
                    log.warning("%s; will retry", e)
                s.last_mono_ns = self.clocks.mono_ns()

    async def stop(self) -> None:
        if self._watchdog is not None:
            self._watchdog.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watchdog
            self._watchdog = None
        self._sink = None
        for s in self._scanners:
            await s.stop()


async def _find_by_mac(address: str) -> BluezAdapter | None:
    return next((a for a in await list_adapters() if a.address == address), None)


async def _set_powered(bus: MessageBus, path: str, on: bool, clocks: Clocks) -> None:
    """Properties.Set(Adapter1.Powered), retrying (with backoff) while BlueZ says it is busy."""
    delay = POWER_BACKOFF_S
    for attempt in range(POWER_RETRIES):
        reply = await bus.call(
            Message(
                destination=BLUEZ,
                path=path,
                interface=PROPERTIES_IFACE,
                member="Set",
                signature="ssv",
                body=[ADAPTER_IFACE, "Powered", Variant("b", on)],
            )
        )
        if reply.message_type != MessageType.ERROR:
            return
        if reply.error_name not in RECOVERABLE_ERRORS or attempt == POWER_RETRIES - 1:
            detail = reply.body[0] if reply.body else ""
            raise BackendError(
                f"cannot power {'on' if on else 'off'} adapter {path}: "
                f"{reply.error_name} {detail}".strip()
            )
        log.debug(
            "adapter %s: %s while powering %s; retrying in %.2f s",
            path,
            reply.error_name,
            "on" if on else "off",
            delay,
        )
        await clocks.sleep(delay)
        delay *= 2


async def power_cycle(address: str, clocks: Clocks | None = None) -> BluezAdapter:
    """Power the adapter with this MAC off and on again over D-Bus; returns it as found
    afterwards (its object path, hciN, may have changed). BackendError if it cannot be done."""
    clocks = clocks or Clocks()
    found = await _find_by_mac(address)
    if found is None:
        raise BackendError(f"adapter {address} is not known to BlueZ (unplugged?)")
    try:
        bus = await MessageBus(bus_type=BusType.SYSTEM).connect()
    except (OSError, ValueError, DBusError) as e:
        raise BackendError(f"cannot connect to the D-Bus system bus ({e}); is dbus running?") from e
    try:
        await _set_powered(bus, found.path, False, clocks)
        await _set_powered(bus, found.path, True, clocks)
    finally:
        bus.disconnect()
    again = await _find_by_mac(address)
    if again is None:
        raise BackendError(f"adapter {address} disappeared while being power-cycled")
    if again.name != found.name:
        log.warning("adapter %s is now %s (was %s)", address, again.name, found.name)
    return again
