"""The wire format: round trips and every class of rejection, plus the import-weight promise."""

from __future__ import annotations

import json
import struct
import subprocess
import sys

import pytest

from bgt_core import wire

T = 1_581_249_601_408_682_300


def batch(readings=None, **kw) -> wire.Batch:
    args = {
        "agent_id": "pi-01",
        "boot_id": "0123456789abcdef",
        "sensor": "b827eb4521b4",
        "seq": 7,
        "readings": readings
        if readings is not None
        else (wire.Reading(T, "e78f135624ce", -87, 123),),
        "sent_ns": 0,
    }
    args.update(kw)
    return wire.Batch(**args)


def raw(
    meta: dict,
    rows: list[tuple],
    version: int = wire.SCHEMA_VERSION,
    magic: bytes = wire.MAGIC,
    count: int | None = None,
) -> bytes:
    m = json.dumps(meta).encode()
    head = struct.pack("<4sHHI", magic, version, len(m), len(rows) if count is None else count)
    return head + m + b"".join(struct.pack("<qq6sb", *r) for r in rows)


META = {"agent": "pi-01", "boot": "0123456789abcdef", "sensor": "b827eb4521b4", "seq": 0}
ROW = (T, 0, bytes.fromhex("e78f135624ce"), -70)


def test_round_trip_plain_readings() -> None:
    b = batch(
        readings=tuple(wire.Reading(T + i, "e78f135624ce", -30 - i, i) for i in range(50)),
        sent_ns=T + 99,
    )
    assert wire.from_wire(wire.to_wire(b)) == b


def test_round_trip_with_ibeacon_and_eddystone_extras() -> None:
    ib = wire.IBeacon("f7826da64fa24e988024bc5b71e0893e", 1, 65535, -59)
    ed = wire.Eddystone(
        "uid", namespace="edd1ebeac04e5defa017", instance="0123456789ab", tx_power=-20
    )
    url = wire.Eddystone("url", url="https://example.org")
    rs = (
        wire.Reading(T, "e78f135624ce", -60, 0, ibeacon=ib),
        wire.Reading(T + 1, "e78f135624cf", -61),
        wire.Reading(T + 2, "e78f135624d0", -62, 0, ibeacon=ib, eddystone=ed),
        wire.Reading(T + 3, "e78f135624d1", -63, 0, eddystone=url),
    )
    back = wire.from_wire(wire.to_wire(batch(readings=rs)))
    assert back.readings == rs
    assert back.readings[2].ibeacon.uuid == "f7826da64fa24e988024bc5b71e0893e"
    assert back.readings[3].eddystone.url == "https://example.org"


def test_empty_batch_round_trips() -> None:
    assert wire.from_wire(wire.to_wire(batch(readings=()))).readings == ()


def test_accepts_bytearray_and_memoryview() -> None:
    data = wire.to_wire(batch())
    assert wire.from_wire(bytearray(data)) == wire.from_wire(memoryview(data)) == batch()


def test_floor_round_trips_and_is_only_encoded_when_stated() -> None:
    b = batch(seq=12, floor=9)
    data = wire.to_wire(b)
    assert b'"floor":9' in data
    assert wire.from_wire(data) == b
    assert wire.from_wire(data).floor == 9
    # Absent in the payload = -1 (an older agent that states nothing).
    plain = wire.to_wire(batch(floor=-1))
    assert b"floor" not in plain
    assert wire.from_wire(plain).floor == -1
    assert wire.from_wire(raw(META, [ROW])).floor == -1
    assert wire.from_wire(raw({**META, "floor": 0}, [ROW])).floor == 0


@pytest.mark.parametrize("floor", [-2, "3", 1.5, True, None])
def test_bad_floor_rejected(floor) -> None:
    with pytest.raises(wire.InvalidField, match="floor"):
        wire.from_wire(raw({**META, "floor": floor}, [ROW]))


@pytest.mark.parametrize(
    ("payload", "error", "text"),
    [
        (b"XXXX" + raw(META, [ROW])[4:], wire.BadMagic, "bad magic"),
        (raw(META, [ROW], version=2), wire.UnsupportedVersion, "schema version 2"),
        (raw(META, [ROW])[:-3], wire.Truncated, "shorter"),
        (b"BGT", wire.Truncated, "header"),
        (raw(META, [ROW], count=3), wire.Truncated, "shorter"),
        (raw(META, [ROW]) + b"\x01\x02", wire.Truncated, "trailing"),
        (raw(META, [ROW]) + struct.pack("<I", 50) + b"{}", wire.Truncated, "extras length"),
        (raw(META, [ROW], count=wire.MAX_READINGS + 1), wire.Oversized, "readings"),
        (b"\0" * (wire.MAX_PAYLOAD_BYTES + 1), wire.Oversized, "bytes"),
        (raw({**META, "sensor": "b827eb4521"}, [ROW]), wire.InvalidField, "not a MAC"),
        (raw({**META, "sensor": "zz27eb4521b4"}, [ROW]), wire.InvalidField, "not a MAC"),
        (raw({**META, "agent": "pi 01/x"}, [ROW]), wire.InvalidField, "agent id"),
        (raw({**META, "seq": -1}, [ROW]), wire.InvalidField, "seq"),
        (raw({**META, "seq": "1"}, [ROW]), wire.InvalidField, "seq"),
        (raw(META, [(5, 0, ROW[2], -70)]), wire.InvalidField, "plausible Unix time"),
        (
            raw(META, [(wire.T_NS_MAX + 1, 0, ROW[2], -70)]),
            wire.InvalidField,
            "plausible Unix time",
        ),
        (raw(META, [(T, 0, ROW[2], 60)]), wire.InvalidField, "RSSI 60"),
        (raw(META, [(T, 0, ROW[2], -128)]), wire.InvalidField, "RSSI -128"),
        (raw(META, [(T, -5, ROW[2], -70)]), wire.InvalidField, "monotonic"),
        (
            struct.pack("<4sHHI", wire.MAGIC, 1, 5, 0) + b"{bad}",
            wire.InvalidField,
            "not valid UTF-8 JSON",
        ),
        (struct.pack("<4sHHI", wire.MAGIC, 1, 2, 0) + b"[]", wire.InvalidField, "JSON object"),
        (struct.pack("<4sHHI", wire.MAGIC, 1, 2, 0) + b"\xff\xfe", wire.InvalidField, "UTF-8"),
        (raw(META, [ROW]) + struct.pack("<I", 4) + b"nope", wire.InvalidField, "extras"),
    ],
)
def test_rejections_are_typed(payload: bytes, error: type[wire.WireError], text: str) -> None:
    with pytest.raises(error, match=text):
        wire.from_wire(payload)


def test_bad_extras_content_rejected() -> None:
    ex = json.dumps(
        {"0": {"ibeacon": {"uuid": "short", "major": 1, "minor": 1, "tx_power": -59}}}
    ).encode()
    with pytest.raises(wire.InvalidField, match="uuid"):
        wire.from_wire(raw(META, [ROW]) + struct.pack("<I", len(ex)) + ex)
    ex = json.dumps({"0": {"eddystone": {"frame": "nope"}}}).encode()
    with pytest.raises(wire.InvalidField, match="eddystone"):
        wire.from_wire(raw(META, [ROW]) + struct.pack("<I", len(ex)) + ex)


def test_every_rejection_is_a_value_error() -> None:
    # Callers that only know ValueError still catch protocol errors.
    for cls in (
        wire.BadMagic,
        wire.UnsupportedVersion,
        wire.Oversized,
        wire.Truncated,
        wire.InvalidField,
    ):
        assert issubclass(cls, wire.WireError)
        assert issubclass(cls, ValueError)


def test_encoder_refuses_too_many_readings() -> None:
    rs = (wire.Reading(T, "e78f135624ce", -60),) * (wire.MAX_READINGS + 1)
    with pytest.raises(wire.Oversized):
        wire.to_wire(batch(readings=rs))


def test_keys_and_key_parsing() -> None:
    assert (
        wire.data_key("default", "pi-01", "B8:27:EB:45:21:B4")
        == "ble/default/rssi/pi-01/b827eb4521b4"
    )
    assert wire.parse_data_key("ble/default/rssi/pi-01/b827eb4521b4") == (
        "default",
        "pi-01",
        "b827eb4521b4",
    )
    assert wire.ack_key("s", "a") == "ble/s/ack/a"
    assert wire.collector_control_key("s", "stop") == "ble/s/control/collector/stop"
    assert wire.agent_status_key("s", "a") == "ble/s/status/agent/a"
    assert wire.agent_token_key("s", "a") == "ble/s/agents/a"
    for bad in (
        "ble/default/rssi/pi-01",
        "ble/default/ack/pi-01/b827eb4521b4",
        "ble/default/rssi/pi 01/b827eb4521b4",
        "ble/default/rssi/pi-01/nothex",
    ):
        with pytest.raises(wire.WireError):
            wire.parse_data_key(bad)


def test_mac_helpers() -> None:
    assert wire.normalize_mac("AA-BB-CC-DD-EE-FF") == "aabbccddeeff"
    assert wire.colon_mac("aabbccddeeff") == "AA:BB:CC:DD:EE:FF"
    with pytest.raises(wire.InvalidField):
        wire.normalize_mac(12)


def test_json_helpers() -> None:
    msg = {"boot": "0123456789abcdef", "streams": {"b827eb4521b4": 41}}
    assert wire.from_json(wire.to_json(msg)) == msg
    assert wire.from_json('{"a": 1}') == {"a": 1}
    with pytest.raises(wire.InvalidField, match="ack"):
        wire.from_json(b"{not json", "ack")
    with pytest.raises(wire.InvalidField, match="object"):
        wire.from_json(b"[1, 2]")
    with pytest.raises(wire.Oversized):
        wire.from_json(b" " * (wire.MAX_JSON_BYTES + 1))
    with pytest.raises(wire.Oversized):
        wire.to_json({"x": "y" * wire.MAX_JSON_BYTES})


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("1581249601.4086823", 1_581_249_601_408_682_300),
        ("1581249601", 1_581_249_601_000_000_000),
        ("1581249601.123456789", 1_581_249_601_123_456_789),
        ("0.000000001", 1),
    ],
)
def test_timestamps_are_exact(text: str, ns: int) -> None:
    assert wire.parse_ts(text) == ns
    assert wire.parse_ts(wire.format_ts(ns)) == ns
    assert wire.format_ts(1_581_249_601_000_000_005) == "1581249601.000000005"


def test_bad_timestamp_text() -> None:
    with pytest.raises(wire.InvalidField):
        wire.parse_ts("12a.5")


def test_import_is_stdlib_only() -> None:
    code = (
        "import sys, bgt_core.wire; "
        "bad = [m for m in ('bleak', 'zenoh', 'yaml', 'numpy') if m in sys.modules]; "
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
