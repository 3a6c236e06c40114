"""The wire format between sensor agents and the collector: key expressions and payloads.

Standard library only, so both sides (and tools that only inspect traffic) can import it
without pulling in bleak or zenoh. ``docs/protocol.md`` describes the same thing in prose.

A reading batch is binary::

    header   struct "<4sHHI"   magic b"BGTB", schema version, meta length, reading count
    meta     UTF-8 JSON        {"agent", "boot", "sensor", "seq"} (+ optional "sent_ns", "floor")
    readings count x "<qq6sb"  t_ns (Unix ns), mono_ns (agent monotonic ns, 0 = unknown),
                               beacon MAC (6 raw bytes), RSSI (dBm, int8)
    extras   "<I" + JSON       optional: {"<index>": {"ibeacon": {...}, "eddystone": {...}}}

Control and status messages are small JSON objects, also size-checked here.
"""

from __future__ import annotations

import json
import re
import struct
from dataclasses import dataclass, field
from typing import Any, TypeGuard

SCHEMA_VERSION = 1
MAGIC = b"BGTB"
MAX_PAYLOAD_BYTES = 4 * 1024 * 1024
MAX_READINGS = 100_000
MAX_META_BYTES = 4096
MAX_JSON_BYTES = 1024 * 1024

# The batch byte layout (see the module docstring); the collector's fast decoder reads these too.
BATCH_HEAD = struct.Struct("<4sHHI")  # magic, schema version, meta length, reading count
BATCH_READING = struct.Struct("<qq6sb")  # t_ns, mono_ns, beacon MAC, RSSI
BATCH_EXTRAS_LEN = struct.Struct("<I")

_MAC_RE = re.compile(r"^[0-9a-f]{12}$")
# Ids (agent, site, boot): also folder names under a run's rssi/, so never starting with a dot
# (a hidden folder, or '..'). The one rule for the agent, the collector and the deploy tools.
_ID_RE = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}$")
_UUID_RE = re.compile(r"^[0-9a-f]{32}$")

# Plausibility limits: a reading outside them is malformed, not merely unusual.
RSSI_MIN, RSSI_MAX = -127, 20
T_NS_MIN = 946_684_800 * 10**9  # 2000-01-01
T_NS_MAX = 4_102_444_800 * 10**9  # 2100-01-01


class WireError(ValueError):
    """A payload or key that does not follow this protocol."""


class BadMagic(WireError):
    """Not a reading batch at all."""


class UnsupportedVersion(WireError):
    """A batch of a schema version this build does not read."""


class Oversized(WireError):
    """A payload larger than the protocol allows."""


class Truncated(WireError):
    """A payload shorter (or longer) than its own header says."""


class InvalidField(WireError):
    """A field with the wrong type or an impossible value."""


# ---------------------------------------------------------------------------------------------
# MAC addresses and identifiers


def normalize_mac(mac: object) -> str:
    """'AA:BB:CC:DD:EE:FF' / 'aabbccddeeff' / 'aa-bb-…' -> 'aabbccddeeff'."""
    if not isinstance(mac, str):
        raise InvalidField(f"MAC address must be a string, got {type(mac).__name__}")
    flat = mac.replace(":", "").replace("-", "").strip().lower()
    if not _MAC_RE.match(flat):
        raise InvalidField(f"not a MAC address: {mac!r}")
    return flat


def colon_mac(mac: str) -> str:
    """'aabbccddeeff' -> 'AA:BB:CC:DD:EE:FF' (BlueZ spelling)."""
    flat = normalize_mac(mac)
    return ":".join(flat[i : i + 2] for i in range(0, 12, 2)).upper()


def check_id(value: object, what: str = "id") -> str:
    if not isinstance(value, str) or not _ID_RE.match(value):
        raise InvalidField(
            f"{what} must be 1-64 characters of [A-Za-z0-9_.-], not starting with a dot, "
            f"got {value!r:.80}"
        )
    return value


# ---------------------------------------------------------------------------------------------
# Key expressions


def data_key(site: str, agent_id: str, sensor_mac: str) -> str:
    return f"ble/{site}/rssi/{agent_id}/{normalize_mac(sensor_mac)}"


def data_selector(site: str) -> str:
    return f"ble/{site}/rssi/*/*"


def agent_token_key(site: str, agent_id: str) -> str:
    return f"ble/{site}/agents/{agent_id}"


def agent_token_selector(site: str) -> str:
    return f"ble/{site}/agents/*"


def agent_status_key(site: str, agent_id: str) -> str:
    return f"ble/{site}/status/agent/{agent_id}"


def agent_status_selector(site: str) -> str:
    return f"ble/{site}/status/agent/*"


def agent_clock_key(site: str, agent_id: str) -> str:
    return f"ble/{site}/clock/agent/{agent_id}"


def ack_key(site: str, agent_id: str) -> str:
    return f"ble/{site}/ack/{agent_id}"


def collector_control_key(site: str, command: str) -> str:
    """Queryables of the collector: start, stop, status, runs."""
    return f"ble/{site}/control/collector/{command}"


def parse_data_key(key: str) -> tuple[str, str, str]:
    """'ble/<site>/rssi/<agent>/<mac>' -> (site, agent, mac); WireError if it is not one."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != "ble" or parts[2] != "rssi":
        raise WireError(f"not a data key: {key!r}")
    return parts[1], check_id(parts[3], "agent id"), normalize_mac(parts[4])


# ---------------------------------------------------------------------------------------------
# Records


def _int_in(d: dict[str, Any], name: str, lo: int, hi: int) -> int:
    v = d.get(name)
    if not _is_int(v) or not lo <= v <= hi:
        raise InvalidField(f"ibeacon {name} must be an integer in [{lo}, {hi}], got {v!r}")
    return v


@dataclass(frozen=True, slots=True)
class IBeacon:
    uuid: str  # 32 lowercase hex digits
    major: int
    minor: int
    tx_power: int  # measured power at 1 m, dBm

    def to_dict(self) -> dict[str, Any]:
        return {
            "uuid": self.uuid,
            "major": self.major,
            "minor": self.minor,
            "tx_power": self.tx_power,
        }

    @staticmethod
    def from_dict(d: Any) -> IBeacon:
        if not isinstance(d, dict):
            raise InvalidField("ibeacon must be an object")
        uuid = d.get("uuid")
        if not isinstance(uuid, str) or not _UUID_RE.match(uuid):
            raise InvalidField(f"ibeacon uuid must be 32 hex digits, got {uuid!r}")
        major, minor = _int_in(d, "major", 0, 65535), _int_in(d, "minor", 0, 65535)
        return IBeacon(uuid, major, minor, _int_in(d, "tx_power", -128, 127))


@dataclass(frozen=True, slots=True)
class Eddystone:
    frame: str  # "uid", "url", "tlm" or "eid"
    namespace: str | None = None  # uid: 20 hex digits
    instance: str | None = None  # uid: 12 hex digits
    url: str | None = None
    tx_power: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            k: v
            for k, v in (
                ("frame", self.frame),
                ("namespace", self.namespace),
                ("instance", self.instance),
                ("url", self.url),
                ("tx_power", self.tx_power),
            )
            if v is not None
        }

    @staticmethod
    def from_dict(d: Any) -> Eddystone:
        if not isinstance(d, dict) or d.get("frame") not in ("uid", "url", "tlm", "eid"):
            raise InvalidField("eddystone must be an object with frame uid|url|tlm|eid")
        for name in ("namespace", "instance", "url"):
            v = d.get(name)
            if v is not None and (not isinstance(v, str) or len(v) > 256):
                raise InvalidField(f"eddystone {name} must be a short string")
        tx = d.get("tx_power")
        if tx is not None and (not _is_int(tx) or not -128 <= tx <= 127):
            raise InvalidField(f"eddystone tx_power must be an int8, got {tx!r}")
        return Eddystone(d["frame"], d.get("namespace"), d.get("instance"), d.get("url"), tx)


@dataclass(frozen=True, slots=True)
class Reading:
    t_ns: int  # capture (reception) time, Unix nanoseconds
    beacon: str  # 12 lowercase hex digits
    rssi: int  # dBm
    mono_ns: int = 0  # agent's monotonic clock at reception, 0 when unknown
    ibeacon: IBeacon | None = None
    eddystone: Eddystone | None = None


@dataclass(frozen=True, slots=True)
class Batch:
    agent_id: str
    boot_id: str  # changes every time the agent process starts
    sensor: str  # adapter MAC, 12 lowercase hex digits
    seq: int  # per (agent, boot, sensor) stream, from 0, +1 per batch
    readings: tuple[Reading, ...] = field(default_factory=tuple)
    sent_ns: int = 0
    # The sender will never (re)send a seq below this one of this stream; -1 = not stated.
    floor: int = -1

    @property
    def stream(self) -> tuple[str, str, str]:
        return (self.agent_id, self.boot_id, self.sensor)


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


# ---------------------------------------------------------------------------------------------
# Batch encoding


def to_wire(batch: Batch) -> bytes:
    meta: dict[str, Any] = {
        "agent": batch.agent_id,
        "boot": batch.boot_id,
        "sensor": batch.sensor,
        "seq": batch.seq,
    }
    if batch.sent_ns:
        meta["sent_ns"] = batch.sent_ns
    if batch.floor >= 0:
        meta["floor"] = batch.floor
    meta_b = json.dumps(meta, separators=(",", ":")).encode()
    if len(meta_b) > MAX_META_BYTES:
        raise Oversized("batch metadata too large")
    n = len(batch.readings)
    if n > MAX_READINGS:
        raise Oversized(f"{n} readings in one batch (max {MAX_READINGS})")
    parts = [BATCH_HEAD.pack(MAGIC, SCHEMA_VERSION, len(meta_b), n), meta_b]
    extras: dict[str, Any] = {}
    pack = BATCH_READING.pack
    for i, r in enumerate(batch.readings):
        parts.append(pack(r.t_ns, r.mono_ns, bytes.fromhex(r.beacon), r.rssi))
        if r.ibeacon is not None or r.eddystone is not None:
            e: dict[str, Any] = {}
            if r.ibeacon is not None:
                e["ibeacon"] = r.ibeacon.to_dict()
            if r.eddystone is not None:
                e["eddystone"] = r.eddystone.to_dict()
            extras[str(i)] = e
    if extras:
        ex_b = json.dumps(extras, separators=(",", ":")).encode()
        parts += [BATCH_EXTRAS_LEN.pack(len(ex_b)), ex_b]
    out = b"".join(parts)
    if len(out) > MAX_PAYLOAD_BYTES:
        raise Oversized(f"batch of {len(out)} bytes (max {MAX_PAYLOAD_BYTES})")
    return out


def check_reading(t_ns: int, rssi: int, mono_ns: int = 0) -> str | None:
    """Why one reading is implausible (timestamp, RSSI, monotonic time), or None if it is fine."""
    if not T_NS_MIN <= t_ns <= T_NS_MAX:
        return f"timestamp {t_ns} ns is not a plausible Unix time"
    if not RSSI_MIN <= rssi <= RSSI_MAX:
        return f"RSSI {rssi} dBm out of range"
    if mono_ns < 0:
        return "negative monotonic time"
    return None


def _batch_head(data: bytes) -> tuple[int, int]:
    """The header's checks; ``(meta_len, n)`` of a header that fits the payload."""
    if len(data) > MAX_PAYLOAD_BYTES:
        raise Oversized(f"payload of {len(data)} bytes (max {MAX_PAYLOAD_BYTES})")
    if len(data) < BATCH_HEAD.size:
        raise Truncated("payload shorter than the batch header")
    magic, version, meta_len, n = BATCH_HEAD.unpack_from(data, 0)
    if magic != MAGIC:
        raise BadMagic("payload is not a reading batch (bad magic)")
    if version != SCHEMA_VERSION:
        raise UnsupportedVersion(f"schema version {version}, this build reads {SCHEMA_VERSION}")
    if meta_len > MAX_META_BYTES:
        raise Oversized("batch metadata too large")
    if n > MAX_READINGS:
        raise Oversized(f"{n} readings in one batch (max {MAX_READINGS})")
    off = BATCH_HEAD.size
    end_readings = off + meta_len + n * BATCH_READING.size
    if len(data) < end_readings:
        raise Truncated("payload shorter than its header says")
    return meta_len, n


def _batch_meta(meta: dict[str, Any]) -> tuple[str, str, str, int, int, int]:
    """The metadata's checks; ``(agent, boot, sensor, seq, sent_ns, floor)``."""
    agent = check_id(meta.get("agent"), "agent id")
    boot = check_id(meta.get("boot"), "boot id")
    sensor = normalize_mac(meta.get("sensor"))
    seq = meta.get("seq")
    if not _is_int(seq) or not 0 <= seq < 2**63:
        raise InvalidField(f"seq must be a non-negative integer, got {seq!r}")
    sent_ns = meta.get("sent_ns", 0)
    if not _is_int(sent_ns) or sent_ns < 0:
        raise InvalidField("sent_ns must be a non-negative integer")
    floor = meta.get("floor", -1)
    if not _is_int(floor) or not -1 <= floor < 2**63:
        raise InvalidField(f"floor must be an integer >= -1, got {floor!r}")
    return agent, boot, sensor, seq, sent_ns, floor


def _batch_extras(rest: bytes) -> dict[str, Any]:
    """The per-reading extras after the readings (``{}`` when there are none)."""
    if not rest:
        return {}
    if len(rest) < BATCH_EXTRAS_LEN.size:
        raise Truncated("trailing bytes after the readings")
    (ex_len,) = BATCH_EXTRAS_LEN.unpack_from(rest, 0)
    if len(rest) != BATCH_EXTRAS_LEN.size + ex_len:
        raise Truncated("extras length does not match the payload")
    return _json_object(rest[BATCH_EXTRAS_LEN.size :], "reading extras")


def _reading_extras(i: int, e: object) -> tuple[IBeacon | None, Eddystone | None]:
    """Reading ``i``'s iBeacon and Eddystone frames from its extras object (``None`` if none)."""
    ib = ed = None
    if e is not None:
        if not isinstance(e, dict):
            raise InvalidField(f"reading {i}: extras must be an object")
        if "ibeacon" in e:
            ib = IBeacon.from_dict(e["ibeacon"])
        if "eddystone" in e:
            ed = Eddystone.from_dict(e["eddystone"])
    return ib, ed


def from_wire(
    data: bytes | bytearray | memoryview, *, skipped: list[tuple[int, str]] | None = None
) -> Batch:
    """Decode and validate one batch; raises a WireError subclass for anything malformed.

    With ``skipped`` (a list), an implausible reading does not fail the batch: it is left out
    and ``(index, reason)`` appended, so one absurd value cannot cost the other readings."""
    data = bytes(data)
    meta_len, n = _batch_head(data)
    off = BATCH_HEAD.size
    end_readings = off + meta_len + n * BATCH_READING.size
    meta = _json_object(data[off : off + meta_len], "batch metadata")
    agent, boot, sensor, seq, sent_ns, floor = _batch_meta(meta)
    extras = _batch_extras(data[end_readings:])

    readings = []
    off += meta_len
    for i, (t_ns, mono_ns, mac, rssi) in enumerate(
        BATCH_READING.iter_unpack(data[off:end_readings])
    ):
        why = check_reading(t_ns, rssi, mono_ns)
        if why is not None:
            if skipped is None:
                raise InvalidField(f"reading {i}: {why}")
            skipped.append((i, why))
            continue
        ib, ed = _reading_extras(i, extras.get(str(i)) if extras else None)
        readings.append(Reading(t_ns, mac.hex(), rssi, mono_ns, ib, ed))
    return Batch(agent, boot, sensor, seq, tuple(readings), sent_ns, floor)


# ---------------------------------------------------------------------------------------------
# Small JSON messages (control, status, acknowledgements)


def to_json(obj: Any) -> bytes:
    out = json.dumps(obj, separators=(",", ":"), sort_keys=True).encode()
    if len(out) > MAX_JSON_BYTES:
        raise Oversized(f"message of {len(out)} bytes (max {MAX_JSON_BYTES})")
    return out


def from_json(data: bytes | bytearray | memoryview | str, what: str = "message") -> dict[str, Any]:
    raw = data.encode() if isinstance(data, str) else bytes(data)
    if len(raw) > MAX_JSON_BYTES:
        raise Oversized(f"{what} of {len(raw)} bytes (max {MAX_JSON_BYTES})")
    return _json_object(raw, what)


def _json_object(raw: bytes, what: str) -> dict[str, Any]:
    try:
        obj = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise InvalidField(f"{what} is not valid UTF-8 JSON: {e}") from None
    if not isinstance(obj, dict):
        raise InvalidField(f"{what} must be a JSON object")
    return obj


def format_ts(t_ns: int) -> str:
    """Unix ns -> 'seconds.fraction' with 9 decimals, exact (no float rounding)."""
    s, ns = divmod(t_ns, 10**9)
    return f"{s}.{ns:09d}"


def parse_ts(text: str) -> int:
    """'1581249601.4086823' -> Unix ns, exact for up to 9 decimals (no float rounding)."""
    text = text.strip()
    neg = text.startswith("-")
    whole, _, frac = text.lstrip("+-").partition(".")
    # isdecimal, not isdigit: int() refuses superscripts.
    if not whole.isdecimal() or (frac and not frac.isdecimal()):
        raise InvalidField(f"not a timestamp: {text[:40]!r}{'...' if len(text) > 40 else ''}")
    if len(whole) > 20:  # far past 2100 (and int() of thousands of digits is refused)
        raise InvalidField(
            f"timestamp {text[:40]}{'...' if len(text) > 40 else ''} is outside 1970..2100"
        )
    ns = int(whole) * 10**9 + int((frac + "000000000")[:9] or 0)
    return -ns if neg else ns
