"""Every advertisement, straight from the kernel: the ``mgmt`` scanner backend.

BlueZ's D-Bus API reports an advertiser again only when its RSSI moved by 8 dB or more unless a
discovery filter is set, and the kernel starts discovery with the controller's duplicate filter
on, so many controllers report each address once per scan period. This backend opens the kernel's
Bluetooth management socket instead (the channel bluetoothd itself uses; both can be open at
once), registers an advertisement monitor on each chosen controller (while one is registered the
kernel scans with the duplicate filter off) and turns every DEVICE_FOUND and
ADV_MONITOR_DEVICE_FOUND event into a reading, stamped on arrival.

The socket needs CAP_NET_ADMIN and a kernel with Bluetooth; without them
:func:`open_mgmt_socket` raises :class:`MgmtUnavailable` with one line naming what is missing.
The protocol itself is :mod:`sensor_agent.scanning.mgmt_protocol`; a small ctypes ``bind`` is the
only thing Python's socket module cannot do here (it has no way to choose the HCI channel).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import logging
import socket
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from bgt_core.wire import Reading, WireError, normalize_mac
from sensor_agent.errors import BackendError
from sensor_agent.scanning import mgmt_protocol as mp
from sensor_agent.scanning.adverts import parse_eddystone, parse_ibeacon
from sensor_agent.scanning.base import AdapterInfo, AdvertSink, Clocks, ScannerBackend

log = logging.getLogger(__name__)

AF_BLUETOOTH = getattr(socket, "AF_BLUETOOTH", 31)
BTPROTO_HCI = 1
HCI_CHANNEL_CONTROL = 3
REPLY_TIMEOUT_S = 2.0
# A report seen twice within this time (DEVICE_FOUND and ADV_MONITOR_DEVICE_FOUND for the same
# advertisement, when bluetoothd is discovering too) counts once.
SAME_REPORT_NS = 3_000_000
MAX_PACKET = 4096

# The kernel trusts a management socket (passes advertisements, accepts monitors) when its opener
# holds CAP_NET_ADMIN; CAP_NET_RAW is for the raw and monitor HCI channels, not used here.
CAPABILITIES = "CAP_NET_ADMIN"


class MgmtUnavailable(BackendError):
    """The management socket cannot be used here; the message says why, in one line."""


def open_mgmt_socket() -> socket.socket:
    """A non-blocking socket on the kernel's Bluetooth management channel."""
    try:
        sock = socket.socket(AF_BLUETOOTH, socket.SOCK_RAW, BTPROTO_HCI)
    except OSError as e:
        if e.errno in (errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT, errno.ESOCKTNOSUPPORT):
            raise MgmtUnavailable(
                "no kernel Bluetooth stack (AF_BLUETOOTH sockets are not supported here)"
            ) from None
        if e.errno in (errno.EPERM, errno.EACCES):
            raise MgmtUnavailable(f"the management socket needs {CAPABILITIES}") from None
        raise MgmtUnavailable(f"cannot open a Bluetooth socket: {e.strerror or e}") from None
    addr = struct.pack("<HHH", AF_BLUETOOTH, mp.INDEX_NONE, HCI_CHANNEL_CONTROL)
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.bind(sock.fileno(), addr, len(addr)) != 0:
        code = ctypes.get_errno()
        sock.close()
        if code in (errno.EPERM, errno.EACCES):
            raise MgmtUnavailable(f"the management socket needs {CAPABILITIES}")
        raise MgmtUnavailable(f"cannot bind the management socket: {errno.errorcode.get(code)}")
    sock.setblocking(False)
    return sock


@dataclass
class _Controller:
    index: int
    info: mp.ControllerInfo
    monitor: int | None = None

    @property
    def name(self) -> str:
        return f"hci{self.index}"


class MgmtBackend(ScannerBackend):
    name = "mgmt"

    def __init__(
        self,
        adapters: Sequence[str] = (),
        clocks: Clocks | None = None,
        open_socket: Callable[[], socket.socket] = open_mgmt_socket,
        reply_timeout_s: float = REPLY_TIMEOUT_S,
    ) -> None:
        self.wanted = tuple(adapters)
        self.clocks = clocks or Clocks()
        self._open = open_socket
        self.reply_timeout_s = reply_timeout_s
        self._sock: socket.socket | None = None
        self._sink: AdvertSink | None = None
        self._controllers: dict[int, _Controller] = {}
        self._pending: dict[tuple[int, int], asyncio.Future[mp.CommandResult]] = {}
        self._lock = asyncio.Lock()
        self._last: dict[tuple[int, str], tuple[int, int, bytes]] = {}
        self.malformed = 0  # packets skipped: truncated, wrong lengths
        self.duplicates = 0  # the same report twice (two event kinds for one advertisement)
        self.reports = 0

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return tuple(
            AdapterInfo(c.name, c.info.address, "mgmt", "passive")
            for c in self._controllers.values()
        )

    async def start(self, sink: AdvertSink) -> None:
        self._sock = self._open()
        loop = asyncio.get_running_loop()
        loop.add_reader(self._sock.fileno(), self._readable)
        try:
            found = await self._controllers_found()
            for c in self._choose(found):
                await self._register_monitor(c)
                self._controllers[c.index] = c
                if not c.info.powered:
                    log.warning("adapter %s (%s) is powered off", c.name, c.info.address)
                log.info(
                    "scanning on %s (%s) through the management socket", c.name, c.info.address
                )
        except BaseException:
            await self.stop()
            raise
        self._sink = sink

    async def _controllers_found(self) -> list[_Controller]:
        indexes = mp.parse_index_list((await self._call(mp.OP_READ_INDEX_LIST, mp.INDEX_NONE)).data)
        out = []
        for i in indexes:
            info = mp.parse_controller_info((await self._call(mp.OP_READ_INFO, i)).data)
            out.append(_Controller(i, info))
        if not out:
            raise BackendError("the kernel reports no Bluetooth controller")
        return out

    def _choose(self, found: list[_Controller]) -> list[_Controller]:
        if not self.wanted:
            return found
        have = ", ".join(f"{c.name} {c.info.address}" for c in found)
        out: list[_Controller] = []
        for w in self.wanted:
            try:
                mac: str | None = normalize_mac(w)
            except WireError:
                mac = None
            match = next((c for c in found if c.name == w or c.info.address == mac), None)
            if match is None:
                raise BackendError(f"adapter {w!r} not found (the kernel has: {have})")
            if match not in out:
                out.append(match)
        return out

    async def _register_monitor(self, c: _Controller) -> None:
        res = await self._call(
            mp.OP_ADD_ADV_PATTERNS_MONITOR, c.index, mp.monitor_params(), check=False
        )
        if res.status == 0x14:  # an untrusted socket: the opener lacks the capability
            raise MgmtUnavailable(f"the management socket needs {CAPABILITIES} (permission denied)")
        if res.status in (0x01, 0x0C):  # unknown command / not supported: a kernel before 5.10
            raise MgmtUnavailable(
                f"{c.name}: the kernel has no advertisement monitors ({res.status_text}; "
                "Linux 5.10 or later needed)"
            )
        if not res.ok:
            raise BackendError(
                f"{c.name}: adding the advertisement monitor failed: {res.status_text}"
            )
        if len(res.data) < 2:
            raise BackendError(f"{c.name}: the monitor reply holds no handle")
        (c.monitor,) = struct.unpack_from("<H", res.data)

    async def _call(
        self, opcode: int, index: int, params: bytes = b"", *, check: bool = True
    ) -> mp.CommandResult:
        """Send one command and wait for its Command Complete / Status (one at a time)."""
        assert self._sock is not None
        async with self._lock:
            fut: asyncio.Future[mp.CommandResult] = asyncio.get_running_loop().create_future()
            self._pending[(opcode, index)] = fut
            try:
                self._sock.send(mp.command(opcode, index, params))
                res = await asyncio.wait_for(fut, self.reply_timeout_s)
            except TimeoutError:
                raise BackendError(
                    f"the kernel did not answer management command 0x{opcode:04x} within "
                    f"{self.reply_timeout_s:g} s"
                ) from None
            except OSError as e:
                raise BackendError(f"management socket: {e.strerror or e}") from None
            finally:
                self._pending.pop((opcode, index), None)
        if check and not res.ok:
            raise BackendError(f"management command 0x{opcode:04x} failed: {res.status_text}")
        return res

    def _readable(self) -> None:
        sock = self._sock
        while sock is not None:
            try:
                packet = sock.recv(MAX_PACKET)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:
                log.warning("management socket: %s; stopped reading", e.strerror or e)
                self._detach()
                return
            # Stamp first: the reception time is the whole point of the dataset.
            t_ns, mono = self.clocks.wall_ns(), self.clocks.mono_ns()
            if not packet:
                log.warning("management socket closed by the kernel")
                self._detach()
                return
            self._packet(packet, t_ns, mono)

    def _packet(self, packet: bytes, t_ns: int, mono: int) -> None:
        try:
            ev = mp.parse_event(packet)
            if ev.code in (mp.EV_CMD_COMPLETE, mp.EV_CMD_STATUS):
                res = mp.parse_command_result(ev)
                fut = self._pending.get((res.opcode, ev.index))
                if fut is not None and not fut.done():
                    fut.set_result(res)
            elif ev.code in (mp.EV_DEVICE_FOUND, mp.EV_ADV_MONITOR_DEVICE_FOUND):
                self._report(ev, t_ns, mono)
        except mp.MgmtFormatError as e:
            self.malformed += 1
            log.debug("skipped a malformed management packet: %s", e)

    def _report(self, ev: mp.Event, t_ns: int, mono: int) -> None:
        c = self._controllers.get(ev.index)
        if c is None or self._sink is None:
            return
        found = mp.parse_device_found(ev)
        if found.address_type == 0:  # a classic (BR/EDR) inquiry result, not an advertisement
            return
        key = (ev.index, found.address)
        last = self._last.get(key)
        self._last[key] = (mono, found.rssi, found.ad)
        if (
            last is not None
            and mono - last[0] <= SAME_REPORT_NS
            and last[1:] == (found.rssi, found.ad)
        ):
            self.duplicates += 1
            return
        self.reports += 1
        manufacturer, service = mp.parse_ad(found.ad)
        reading = Reading(
            t_ns,
            found.address,
            found.rssi,
            mono,
            parse_ibeacon(manufacturer),
            parse_eddystone(service),
        )
        self._sink(c.info.address, reading)

    def _detach(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(self._sock.fileno())

    async def stop(self) -> None:
        self._sink = None
        sock = self._sock
        if sock is None:
            return
        for c in self._controllers.values():
            if c.monitor is not None:
                with contextlib.suppress(BackendError):
                    await self._call(
                        mp.OP_REMOVE_ADV_MONITOR, c.index, struct.pack("<H", c.monitor), check=False
                    )
                c.monitor = None
        self._detach()
        self._sock = None
        sock.close()
