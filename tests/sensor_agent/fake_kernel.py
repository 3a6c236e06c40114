"""A fake kernel on the far end of a socket pair, speaking the Bluetooth management protocol byte
for byte (layouts from BlueZ's doc/mgmt-api.txt): it answers the commands the ``mgmt`` backend
sends and sends the advertising reports a test asks for."""

from __future__ import annotations

import asyncio
import socket
import struct

OP_READ_INDEX_LIST, OP_READ_INFO = 0x0003, 0x0004
OP_ADD_MONITOR, OP_REMOVE_MONITOR = 0x0052, 0x0053
EV_COMPLETE, EV_STATUS, EV_FOUND, EV_MONITOR_FOUND = 0x0001, 0x0002, 0x0012, 0x002F


def packet(code: int, index: int, params: bytes = b"") -> bytes:
    return struct.pack("<HHH", code, index, len(params)) + params


def ibeacon_ad(major: int, minor: int, tx: int = -59) -> bytes:
    flags = b"\x02\x01\x06"
    body = (
        b"\xff\x4c\x00\x02\x15"
        + bytes(range(16))
        + major.to_bytes(2, "big")
        + minor.to_bytes(2, "big")
        + bytes([tx & 0xFF])
    )
    return flags + bytes([len(body)]) + body


def device_found(
    index: int, mac: str, rssi: int, ad: bytes, *, addr_type: int = 2, monitor: int | None = None
) -> bytes:
    params = struct.pack("<6sBbIH", bytes.fromhex(mac)[::-1], addr_type, rssi, 0, len(ad)) + ad
    if monitor is None:
        return packet(EV_FOUND, index, params)
    return packet(EV_MONITOR_FOUND, index, struct.pack("<H", monitor) + params)


class FakeKernel:
    """``controllers``: index -> (MAC, powered). ``monitor_status`` answers Add Advertisement
    Patterns Monitor (0 = success; 0x14 = permission denied, an untrusted socket)."""

    def __init__(self, controllers: dict[int, tuple[str, bool]], monitor_status: int = 0) -> None:
        self.controllers = controllers
        self.monitor_status = monitor_status
        self.agent_end, self.end = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self.agent_end.setblocking(False)
        self.end.setblocking(False)
        self.commands: list[tuple[int, int, bytes]] = []  # (opcode, index, parameters) received
        self.monitors: dict[int, int] = {}  # handle -> controller index
        self._next_handle = 1

    def attach(self) -> None:
        asyncio.get_running_loop().add_reader(self.end.fileno(), self._command)

    def detach(self) -> None:
        asyncio.get_running_loop().remove_reader(self.end.fileno())
        self.end.close()

    def open_socket(self) -> socket.socket:
        """What the backend calls instead of opening the real management socket."""
        return self.agent_end

    def send(self, data: bytes) -> None:
        self.end.send(data)

    def _complete(self, opcode: int, index: int, status: int, data: bytes = b"") -> None:
        code = EV_COMPLETE if status == 0 else EV_STATUS
        self.send(packet(code, index, struct.pack("<HB", opcode, status) + data))

    def _command(self) -> None:
        try:
            raw = self.end.recv(4096)
        except BlockingIOError:
            return
        if not raw:
            return
        opcode, index, length = struct.unpack_from("<HHH", raw)
        params = raw[6:]
        assert len(params) == length, "the backend sent a command with a wrong length"
        self.commands.append((opcode, index, params))
        if opcode == OP_READ_INDEX_LIST:
            ids = sorted(self.controllers)
            self._complete(opcode, index, 0, struct.pack(f"<H{len(ids)}H", len(ids), *ids))
        elif opcode == OP_READ_INFO and index in self.controllers:
            mac, powered = self.controllers[index]
            info = struct.pack(
                "<6sBHII3s249s11s",
                bytes.fromhex(mac)[::-1],
                9,
                0x000F,
                0x3FFFF,
                (1 if powered else 0) | (1 << 9),
                b"\0\0\0",
                f"pi hci{index}".encode(),
                b"",
            )
            self._complete(opcode, index, 0, info)
        elif opcode == OP_ADD_MONITOR:
            if self.monitor_status:
                self._complete(opcode, index, self.monitor_status)
                return
            handle, self._next_handle = self._next_handle, self._next_handle + 1
            self.monitors[handle] = index
            self._complete(opcode, index, 0, struct.pack("<H", handle))
        elif opcode == OP_REMOVE_MONITOR:
            (handle,) = struct.unpack_from("<H", params)
            self.monitors.pop(handle, None)
            self._complete(opcode, index, 0, params)
        else:
            self._complete(opcode, index, 0x01 if index in self.controllers else 0x11)
