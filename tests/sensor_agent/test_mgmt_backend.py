"""The ``mgmt`` scanner backend (issue 31) against a fake kernel that speaks the Bluetooth
management protocol byte for byte: the monitor it registers, every report delivered with its own
RSSI and iBeacon, malformed packets skipped and counted, and one clear line where the socket
cannot be used."""

from __future__ import annotations

import asyncio
import struct
import time

import pytest

from bgt_core.wire import IBeacon, Reading
from polling import wait_for_async as wait_for
from sensor_agent.errors import BackendError
from sensor_agent.scanning import mgmt_protocol as mp
from sensor_agent.scanning.mgmt_backend import MgmtBackend, MgmtUnavailable, open_mgmt_socket
from tests.sensor_agent.fake_kernel import (
    FakeKernel,
    device_found,
    ibeacon_ad,
    packet,
)

HCI0, HCI1 = "b827eb4521b4", "dca632000001"
BEACON = "e78f135624ce"
UUID = bytes(range(16)).hex()


def run_with_kernel(kernel: FakeKernel, body, adapters=()) -> tuple[MgmtBackend, list]:
    got: list[tuple[str, Reading]] = []

    async def main() -> MgmtBackend:
        kernel.attach()
        backend = MgmtBackend(adapters, open_socket=kernel.open_socket, reply_timeout_s=1.0)
        try:
            await backend.start(lambda mac, r: got.append((mac, r)))
            await body(backend, got)
        finally:
            await backend.stop()
            kernel.detach()
        return backend

    return asyncio.run(main()), got


def test_the_monitor_command_bytes() -> None:
    """Add Advertisement Patterns Monitor (0x0052): a count, then per pattern AD type, offset,
    length and a 31-byte value field; the command header carries opcode, index and length."""
    want = bytes([7])
    for value in (b"\x02", b"\x04", b"\x05", b"\x06", b"\x1a", b"\x1e"):
        want += b"\x01\x00\x01" + value + bytes(30)
    want += b"\xff\x00\x04\x4c\x00\x02\x15" + bytes(27)
    assert len(want) == 1 + 7 * 34
    assert mp.command(0x0052, 1, mp.monitor_params()) == b"\x52\x00\x01\x00\xef\x00" + want

    kernel = FakeKernel({0: (HCI0, True), 1: (HCI1, True)})

    async def nothing(backend, got) -> None:
        assert [(a.name, a.mac, a.backend) for a in backend.adapters] == [
            ("hci0", HCI0, "mgmt"),
            ("hci1", HCI1, "mgmt"),
        ]

    run_with_kernel(kernel, nothing)
    ops = [(op, index) for op, index, _ in kernel.commands]
    assert ops == [
        (0x0003, 0xFFFF),
        (0x0004, 0),
        (0x0004, 1),
        (0x0052, 0),
        (0x0052, 1),
        (0x0053, 0),
        (0x0053, 1),
    ]
    assert [p for op, _, p in kernel.commands if op == 0x0052] == [want, want]
    # each monitor is removed again on stop, by its handle
    assert [p for op, _, p in kernel.commands if op == 0x0053] == [b"\x01\x00", b"\x02\x00"]
    assert kernel.monitors == {}


def test_every_report_delivered_with_its_own_rssi_and_ibeacon() -> None:
    kernel = FakeKernel({0: (HCI0, True), 1: (HCI1, True)})
    rssis = [-60, -60, -60, -61, -75, -60]  # repeated values are real repeated receptions

    async def body(backend, got) -> None:
        t_before = time.time_ns()
        for i, rssi in enumerate(rssis):
            kernel.send(device_found(i % 2, BEACON, rssi, ibeacon_ad(1, i)))
        # a classic inquiry result and an unknown controller's report are not advertisements here
        kernel.send(device_found(0, "001122334455", -50, b"", addr_type=0))
        kernel.send(device_found(7, BEACON, -50, ibeacon_ad(1, 99)))
        await wait_for(lambda: len(got) == len(rssis))
        await asyncio.sleep(0.05)
        assert all(t_before <= r.t_ns <= time.time_ns() and r.mono_ns > 0 for _, r in got)

    backend, got = run_with_kernel(kernel, body)
    assert [(mac, r.beacon, r.rssi) for mac, r in got] == [
        ((HCI0, HCI1)[i % 2], BEACON, rssi) for i, rssi in enumerate(rssis)
    ]
    assert [r.ibeacon for _, r in got] == [IBeacon(UUID, 1, i, -59) for i in range(len(rssis))]
    assert backend.reports == len(rssis)


def test_one_advertisement_reported_by_both_events_counts_once() -> None:
    kernel = FakeKernel({0: (HCI0, True)})
    ad = ibeacon_ad(3, 4)

    async def body(backend, got) -> None:
        kernel.send(device_found(0, BEACON, -66, ad))
        kernel.send(device_found(0, BEACON, -66, ad, monitor=1))  # the same report, monitored
        kernel.send(device_found(0, BEACON, -67, ad, monitor=1))  # a different one
        await wait_for(lambda: len(got) == 2)
        await asyncio.sleep(0.05)

    backend, got = run_with_kernel(kernel, body)
    assert [r.rssi for _, r in got] == [-66, -67]
    assert backend.duplicates == 1


def test_malformed_packets_are_skipped_and_counted() -> None:
    kernel = FakeKernel({0: (HCI0, True)})
    good = device_found(0, BEACON, -70, ibeacon_ad(5, 6))
    params = good[6:]
    bad = [
        b"\x12\x00",  # shorter than a header
        packet(0x0012, 0, params)[:-3],  # header says more than follows
        packet(0x0012, 0, params[:5]),  # device found cut inside its fixed part
        packet(0x0012, 0, params[:-1] + b""),  # AD length says one byte more than follows
        packet(0x002F, 0, b"\x01"),  # monitor event without a whole handle
        packet(0x0001, 0, b"\x03"),  # a command result without opcode and status
    ]

    async def body(backend, got) -> None:
        for b in bad:
            kernel.send(b)
        kernel.send(good)
        # an AD structure running past the end: the report is kept, the bad structure dropped
        kernel.send(device_found(0, BEACON, -71, b"\x02\x01\x06\x1a\xff\x4c\x00"))
        await wait_for(lambda: len(got) == 2)

    backend, got = run_with_kernel(kernel, body)
    assert backend.malformed == len(bad)
    assert [(r.rssi, r.ibeacon is not None) for _, r in got] == [(-70, True), (-71, False)]


def test_the_ad_parser() -> None:
    ad = (
        b"\x02\x01\x06"
        + b"\x05\xff\x59\x00\xaa\xbb"  # Nordic's company id, 2 bytes of payload
        + b"\x05\x16\xaa\xfe\x10\x00"  # service data, 16-bit UUID 0xFEAA
        + b"\x00"  # padding ends the data
        + b"\x03\xff\x4c\x00"
    )
    manufacturer, service = mp.parse_ad(ad)
    assert manufacturer == {0x0059: b"\xaa\xbb"}
    assert service == {"0000feaa-0000-1000-8000-00805f9b34fb": b"\x10\x00"}


def test_choosing_adapters_by_name_or_address() -> None:
    kernel = FakeKernel({0: (HCI0, True), 1: (HCI1, False)})

    async def nothing(backend, got) -> None:
        assert [a.name for a in backend.adapters] == ["hci1"]

    run_with_kernel(kernel, nothing, adapters=[HCI1.upper()])
    assert [index for op, index, _ in kernel.commands if op == 0x0052] == [1]

    kernel = FakeKernel({0: (HCI0, True)})
    with pytest.raises(BackendError, match="adapter 'hci3' not found .*hci0 b827eb4521b4"):
        run_with_kernel(kernel, nothing, adapters=["hci3"])


def test_an_untrusted_socket_is_one_line_naming_the_capability() -> None:
    kernel = FakeKernel({0: (HCI0, True)}, monitor_status=0x14)
    with pytest.raises(MgmtUnavailable, match="needs CAP_NET_ADMIN") as err:
        run_with_kernel(kernel, lambda b, g: asyncio.sleep(0))
    assert "\n" not in str(err.value)


def test_an_old_kernel_without_monitors() -> None:
    kernel = FakeKernel({0: (HCI0, True)}, monitor_status=0x01)
    with pytest.raises(MgmtUnavailable, match="Linux 5.10 or later"):
        run_with_kernel(kernel, lambda b, g: asyncio.sleep(0))


def test_no_kernel_bluetooth_here_is_one_line() -> None:
    """This machine has no Bluetooth: opening the real socket says so."""
    message = None
    try:
        open_mgmt_socket().close()
    except MgmtUnavailable as e:
        message = str(e)
    if message is None:  # a machine with Bluetooth and the capability: the socket is real
        pytest.skip("this machine has a usable management socket")
    assert "\n" not in message
    assert "no kernel Bluetooth stack" in message or "CAP_NET_ADMIN" in message


def test_controller_info_layout() -> None:
    info = struct.pack(
        "<6sBHII3s249s11s", bytes.fromhex(HCI0)[::-1], 9, 2, 0, 0x201, b"\0" * 3, b"pi\0x", b""
    )
    parsed = mp.parse_controller_info(info)
    assert (parsed.address, parsed.version, parsed.powered, parsed.name) == (HCI0, 9, True, "pi")
    with pytest.raises(mp.MgmtFormatError):
        mp.parse_controller_info(info[:100])
    with pytest.raises(mp.MgmtFormatError):
        mp.parse_index_list(b"\x02\x00\x00\x00")
