"""The Linux kernel's Bluetooth management protocol, the part the ``mgmt`` scanner speaks.

Pure bytes in, records out; no I/O. Layouts follow BlueZ's ``doc/mgmt-api.txt`` and
``lib/mgmt.h``: every packet is a 6-byte little-endian header (command or event code,
controller index, parameter length) and its parameters. Addresses travel least significant byte
first. A malformed packet is a :class:`MgmtFormatError`; the backend counts and skips it.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

HEADER = struct.Struct("<HHH")
INDEX_NONE = 0xFFFF  # "not about one controller"

# Commands
OP_READ_INDEX_LIST = 0x0003
OP_READ_INFO = 0x0004
OP_ADD_ADV_PATTERNS_MONITOR = 0x0052
OP_REMOVE_ADV_MONITOR = 0x0053

# Events
EV_CMD_COMPLETE = 0x0001
EV_CMD_STATUS = 0x0002
EV_INDEX_ADDED = 0x0004
EV_INDEX_REMOVED = 0x0005
EV_DEVICE_FOUND = 0x0012
EV_ADV_MONITOR_DEVICE_FOUND = 0x002F

STATUS_TEXT = {
    0x00: "success",
    0x01: "unknown command",
    0x03: "failed",
    0x07: "no resources",
    0x0A: "busy",
    0x0B: "rejected",
    0x0C: "not supported",
    0x0D: "invalid parameters",
    0x0F: "not powered",
    0x11: "invalid index",
    0x12: "rfkilled",
    0x14: "permission denied",
}

ADDRESS_TYPES = {0: "bredr", 1: "le-public", 2: "le-random"}
SETTING_POWERED = 1 << 0
SETTING_LE = 1 << 9

# A pattern's value field is always 31 bytes, the longest legacy advertising payload.
PATTERN_VALUE_LEN = 31
# AD types the parser keeps (Core Specification Supplement, part A).
AD_FLAGS = 0x01
AD_SERVICE_DATA_16 = 0x16
AD_SERVICE_DATA_32 = 0x20
AD_SERVICE_DATA_128 = 0x21
AD_MANUFACTURER = 0xFF
_BASE_UUID_TAIL = "-0000-1000-8000-00805f9b34fb"

# The monitor the backend registers: any advertisement with a Flags field of the usual values,
# or Apple's iBeacon prefix. What matters is that a monitor exists: while one is registered the
# kernel scans passively with the controller's duplicate filter off. Controllers without pattern
# offloading (most) pass every advertisement regardless of the patterns.
MATCH_ALL_PATTERNS: tuple[tuple[int, int, bytes], ...] = (
    (AD_FLAGS, 0, b"\x02"),
    (AD_FLAGS, 0, b"\x04"),
    (AD_FLAGS, 0, b"\x05"),
    (AD_FLAGS, 0, b"\x06"),
    (AD_FLAGS, 0, b"\x1a"),
    (AD_FLAGS, 0, b"\x1e"),
    (AD_MANUFACTURER, 0, b"\x4c\x00\x02\x15"),
)


class MgmtFormatError(ValueError):
    """A packet that does not have the layout its code promises."""


@dataclass(frozen=True, slots=True)
class Event:
    code: int
    index: int
    params: bytes


@dataclass(frozen=True, slots=True)
class CommandResult:
    opcode: int
    status: int
    data: bytes

    @property
    def ok(self) -> bool:
        return self.status == 0

    @property
    def status_text(self) -> str:
        return STATUS_TEXT.get(self.status, f"status 0x{self.status:02x}")


@dataclass(frozen=True, slots=True)
class DeviceFound:
    """One advertising report: DEVICE_FOUND, or ADV_MONITOR_DEVICE_FOUND (``monitor`` set)."""

    address: str  # 12 lower-case hex digits, most significant first
    address_type: int
    rssi: int
    flags: int
    ad: bytes  # advertising data (and scan response), AD structures back to back
    monitor: int | None = None


@dataclass(frozen=True, slots=True)
class ControllerInfo:
    address: str
    version: int
    manufacturer: int
    supported: int
    current: int
    name: str

    @property
    def powered(self) -> bool:
        return bool(self.current & SETTING_POWERED)


def command(opcode: int, index: int, params: bytes = b"") -> bytes:
    return HEADER.pack(opcode, index, len(params)) + params


def event(code: int, index: int, params: bytes = b"") -> bytes:
    """An event packet (what the kernel sends; the tests' fake kernel builds them with this)."""
    return HEADER.pack(code, index, len(params)) + params


def parse_event(packet: bytes) -> Event:
    if len(packet) < HEADER.size:
        raise MgmtFormatError(f"{len(packet)}-byte packet: shorter than the 6-byte header")
    code, index, length = HEADER.unpack_from(packet)
    if len(packet) - HEADER.size != length:
        raise MgmtFormatError(
            f"event 0x{code:04x}: header says {length} parameter bytes, packet has "
            f"{len(packet) - HEADER.size}"
        )
    return Event(code, index, bytes(packet[HEADER.size :]))


def parse_command_result(ev: Event) -> CommandResult:
    """A Command Complete (opcode, status, return parameters) or Command Status event."""
    if ev.code not in (EV_CMD_COMPLETE, EV_CMD_STATUS) or len(ev.params) < 3:
        raise MgmtFormatError(f"event 0x{ev.code:04x}: not a command result")
    opcode, status = struct.unpack_from("<HB", ev.params)
    return CommandResult(opcode, status, ev.params[3:])


def _address(raw: bytes) -> str:
    return raw[::-1].hex()


def address_bytes(mac: str) -> bytes:
    """'aabbccddeeff' -> the 6 bytes on the wire (least significant first)."""
    return bytes.fromhex(mac)[::-1]


_FOUND = struct.Struct("<6sBbIH")  # address, type, rssi, flags, AD length


def parse_device_found(ev: Event) -> DeviceFound:
    """DEVICE_FOUND (address, type, RSSI, flags, EIR/AD) or ADV_MONITOR_DEVICE_FOUND (the same
    after a 2-byte monitor handle)."""
    params, monitor = ev.params, None
    if ev.code == EV_ADV_MONITOR_DEVICE_FOUND:
        if len(params) < 2:
            raise MgmtFormatError("monitor device found: no monitor handle")
        (monitor,) = struct.unpack_from("<H", params)
        params = params[2:]
    elif ev.code != EV_DEVICE_FOUND:
        raise MgmtFormatError(f"event 0x{ev.code:04x}: not a device-found event")
    if len(params) < _FOUND.size:
        raise MgmtFormatError(f"device found: {len(params)} bytes, the fixed part is {_FOUND.size}")
    raw, addr_type, rssi, flags, ad_len = _FOUND.unpack_from(params)
    ad = params[_FOUND.size :]
    if len(ad) != ad_len:
        raise MgmtFormatError(f"device found: AD length says {ad_len}, {len(ad)} bytes follow")
    return DeviceFound(_address(raw), addr_type, rssi, flags, bytes(ad), monitor)


def parse_index_list(data: bytes) -> list[int]:
    if len(data) < 2:
        raise MgmtFormatError("index list: no count")
    (n,) = struct.unpack_from("<H", data)
    if len(data) != 2 + 2 * n:
        raise MgmtFormatError(f"index list: {n} controllers, {len(data) - 2} bytes of indexes")
    return list(struct.unpack_from(f"<{n}H", data, 2))


_INFO = struct.Struct("<6sBHII3s249s11s")


def parse_controller_info(data: bytes) -> ControllerInfo:
    if len(data) < _INFO.size:
        raise MgmtFormatError(f"controller info: {len(data)} bytes, expected {_INFO.size}")
    raw, version, manufacturer, supported, current, _, name, _ = _INFO.unpack_from(data)
    text = name.split(b"\0", 1)[0].decode("utf-8", "replace")
    return ControllerInfo(_address(raw), version, manufacturer, supported, current, text)


def monitor_params(patterns: Sequence[tuple[int, int, bytes]] = MATCH_ALL_PATTERNS) -> bytes:
    """Add Advertisement Patterns Monitor's parameters: a count, then per pattern AD type,
    offset, length and a 31-byte value field."""
    if not 1 <= len(patterns) <= 255:
        raise ValueError("a monitor needs 1 to 255 patterns")
    out = bytearray([len(patterns)])
    for ad_type, offset, value in patterns:
        if not 0 < len(value) <= PATTERN_VALUE_LEN or offset + len(value) > PATTERN_VALUE_LEN:
            raise ValueError(f"pattern {value.hex()} at {offset}: outside the 31-byte AD field")
        out += bytes([ad_type, offset, len(value)]) + value.ljust(PATTERN_VALUE_LEN, b"\0")
    return bytes(out)


def parse_ad(ad: bytes) -> tuple[dict[int, bytes], dict[str, bytes]]:
    """Manufacturer data ``{company id: payload}`` and service data ``{uuid: payload}`` of the
    AD structures in ``ad``. A zero length ends the data (padding); a structure running past the
    end is dropped with what follows it."""
    manufacturer: dict[int, bytes] = {}
    service: dict[str, bytes] = {}
    i = 0
    while i < len(ad):
        length = ad[i]
        if length == 0 or i + 1 + length > len(ad):
            break
        kind, body = ad[i + 1], ad[i + 2 : i + 1 + length]
        i += 1 + length
        if kind == AD_MANUFACTURER and len(body) >= 2:
            manufacturer[int.from_bytes(body[:2], "little")] = bytes(body[2:])
        elif kind == AD_SERVICE_DATA_16 and len(body) >= 2:
            uuid16 = int.from_bytes(body[:2], "little")
            service[f"0000{uuid16:04x}{_BASE_UUID_TAIL}"] = bytes(body[2:])
        elif kind == AD_SERVICE_DATA_32 and len(body) >= 4:
            uuid32 = int.from_bytes(body[:4], "little")
            service[f"{uuid32:08x}{_BASE_UUID_TAIL}"] = bytes(body[4:])
        elif kind == AD_SERVICE_DATA_128 and len(body) >= 16:
            h = body[:16][::-1].hex()
            service[f"{h[:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:]}"] = bytes(body[16:])
    return manufacturer, service
