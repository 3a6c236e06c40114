"""iBeacon and Eddystone parsing on raw advertisement bytes."""

from __future__ import annotations

import pytest

from bgt_core.wire import Eddystone, IBeacon
from sensor_agent.scanning.adverts import (
    APPLE_COMPANY_ID,
    EDDYSTONE_UUID128,
    parse_eddystone,
    parse_eddystone_frame,
    parse_ibeacon,
)

UUID = bytes.fromhex("e2c56db5dffb48d2b060d0f5a71096e0")


def ibeacon_payload(major: int = 1, minor: int = 2, tx: int = -59) -> bytes:
    return (
        b"\x02\x15"
        + UUID
        + major.to_bytes(2, "big")
        + minor.to_bytes(2, "big")
        + bytes([tx & 0xFF])
    )


def test_ibeacon_fields() -> None:
    ib = parse_ibeacon({APPLE_COMPANY_ID: ibeacon_payload(0x1234, 0xFFFE, -59)})
    assert ib == IBeacon("e2c56db5dffb48d2b060d0f5a71096e0", 0x1234, 0xFFFE, -59)


def test_ibeacon_positive_tx_power() -> None:
    assert parse_ibeacon({APPLE_COMPANY_ID: ibeacon_payload(tx=4)}).tx_power == 4


@pytest.mark.parametrize(
    "data",
    [
        {0x0059: ibeacon_payload()},  # not Apple
        {APPLE_COMPANY_ID: b"\x10\x05" + ibeacon_payload()[2:]},  # Apple, but not type 0x02 0x15
        {APPLE_COMPANY_ID: ibeacon_payload()[:22]},  # truncated
        {},
    ],
)
def test_not_an_ibeacon(data: dict[int, bytes]) -> None:
    assert parse_ibeacon(data) is None


def test_eddystone_uid() -> None:
    frame = b"\x00" + bytes([0xEE]) + bytes(range(10)) + bytes.fromhex("aabbccddeeff") + b"\x00\x00"
    assert parse_eddystone({EDDYSTONE_UUID128: frame}) == Eddystone(
        "uid", namespace="00010203040506070809", instance="aabbccddeeff", tx_power=-18
    )


def test_eddystone_url_expansion() -> None:
    frame = b"\x10\xf4\x03" + b"example" + b"\x07" + b"/x"
    assert parse_eddystone_frame(frame) == Eddystone(
        "url", url="https://example.com/x", tx_power=-12
    )
    assert parse_eddystone_frame(b"\x10\x00\x00goo.gl\x00") == Eddystone(
        "url", url="http://www.goo.gl.com/", tx_power=0
    )


def test_eddystone_tlm_and_eid() -> None:
    tlm = b"\x20\x00" + (3000).to_bytes(2, "big") + b"\x18\x00" + bytes(8)
    assert parse_eddystone({"FEAA": tlm}) == Eddystone("tlm")
    eid = b"\x30\xf0" + bytes.fromhex("0102030405060708")
    assert parse_eddystone_frame(eid) == Eddystone("eid", instance="0102030405060708", tx_power=-16)


@pytest.mark.parametrize(
    "frame",
    [
        b"",
        b"\x00\x00" + bytes(5),
        b"\x10\x00\x09x",
        b"\x10\x00\x00\x80",
        b"\x20\x00",
        b"\x40" + bytes(20),
    ],
)
def test_malformed_eddystone(frame: bytes) -> None:
    assert parse_eddystone_frame(frame) is None


def test_other_service_data_is_ignored() -> None:
    assert parse_eddystone({"0000180f-0000-1000-8000-00805f9b34fb": b"\x00" * 18}) is None
