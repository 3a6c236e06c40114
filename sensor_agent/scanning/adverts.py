"""Pure parsing of advertisement payloads: iBeacon (Apple manufacturer data) and Eddystone
(service data 0xFEAA: UID, URL, TLM, EID). Bytes in, records (or None) out; no I/O."""

from __future__ import annotations

from collections.abc import Mapping

from bgt_core.wire import Eddystone, IBeacon

APPLE_COMPANY_ID = 0x004C
IBEACON_PREFIX = b"\x02\x15"  # type 0x02, length 0x15 (21 bytes follow)
EDDYSTONE_UUID128 = "0000feaa-0000-1000-8000-00805f9b34fb"

_URL_SCHEMES = ("http://www.", "https://www.", "http://", "https://")
_URL_CODES = (
    ".com/",
    ".org/",
    ".edu/",
    ".net/",
    ".info/",
    ".biz/",
    ".gov/",
    ".com",
    ".org",
    ".edu",
    ".net",
    ".info",
    ".biz",
    ".gov",
)


def _int8(b: int) -> int:
    return b - 256 if b > 127 else b


def parse_ibeacon(manufacturer_data: Mapping[int, bytes]) -> IBeacon | None:
    """The iBeacon in a ``{company_id: payload}`` map (company id already stripped), if any."""
    data = manufacturer_data.get(APPLE_COMPANY_ID)
    if data is None or len(data) < 23 or not bytes(data).startswith(IBEACON_PREFIX):
        return None
    data = bytes(data)
    return IBeacon(
        uuid=data[2:18].hex(),
        major=int.from_bytes(data[18:20], "big"),
        minor=int.from_bytes(data[20:22], "big"),
        tx_power=_int8(data[22]),
    )


def parse_eddystone_frame(data: bytes) -> Eddystone | None:
    """One Eddystone frame (the service data of UUID 0xFEAA); None if malformed or unknown."""
    data = bytes(data)
    if not data:
        return None
    kind = data[0]
    if kind == 0x00:  # UID: tx power, 10-byte namespace, 6-byte instance (+2 reserved)
        if len(data) < 18:
            return None
        return Eddystone(
            "uid", namespace=data[2:12].hex(), instance=data[12:18].hex(), tx_power=_int8(data[1])
        )
    if kind == 0x10:  # URL: tx power, scheme prefix, compressed URL
        if len(data) < 3 or data[2] >= len(_URL_SCHEMES):
            return None
        parts = [_URL_SCHEMES[data[2]]]
        for b in data[3:]:
            if b < len(_URL_CODES):
                parts.append(_URL_CODES[b])
            elif 0x21 <= b <= 0x7E:
                parts.append(chr(b))
            else:  # reserved codes: the frame is not a valid URL
                return None
        return Eddystone("url", url="".join(parts), tx_power=_int8(data[1]))
    if kind == 0x20:  # TLM: telemetry (battery, temperature, counters); only its presence is kept
        return Eddystone("tlm") if len(data) >= 14 else None
    if kind == 0x30:  # EID: tx power, 8-byte ephemeral id
        if len(data) < 10:
            return None
        return Eddystone("eid", instance=data[2:10].hex(), tx_power=_int8(data[1]))
    return None


def parse_eddystone(service_data: Mapping[str, bytes]) -> Eddystone | None:
    """The Eddystone frame in a ``{service_uuid: payload}`` map (16- or 128-bit UUID keys)."""
    for key, payload in service_data.items():
        k = str(key).lower()
        if k in (EDDYSTONE_UUID128, "feaa", "0000feaa"):
            return parse_eddystone_frame(payload)
    return None
