"""`.mbd` rows: ``ts,sensor,beacon,rssi`` (fingerprints, collector output) optionally followed by
``x,y,z,r11..r33`` (annotated tracks). Timestamps are kept as exact integer nanoseconds."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from bgt_core.formats._textio import iter_lines
from bgt_core.wire import WireError, format_ts, normalize_mac, parse_ts


class MbdError(ValueError):
    """A malformed mbd file; the message names the file and line."""


# What a row may hold: an RSSI that fits the int8 of the wire format (plausibility, e.g. the
# +42 dBm of a published file, is for the reader to judge) and a Unix time in 1970..2100.
RSSI_LO, RSSI_HI = -128, 127
T_NS_LO, T_NS_HI = 0, 4_102_444_800 * 10**9


@dataclass(frozen=True, slots=True)
class MbdRow:
    t_ns: int
    sensor: str
    beacon: str
    rssi: int
    rest: tuple[str, ...] = ()  # pose columns of track files, kept as text


_RSSI_TEXT = re.compile(r"[+-]?[0-9]+")


def parse_line(line: str) -> MbdRow:
    parts = line.strip().split(",")
    if len(parts) < 4:
        raise ValueError(f"expected at least 4 comma-separated fields, got {len(parts)}")
    try:
        t_ns, sensor, beacon = parse_ts(parts[0]), normalize_mac(parts[1]), normalize_mac(parts[2])
    except WireError as e:
        raise ValueError(str(e)) from None
    text = parts[3].strip()
    if not _RSSI_TEXT.fullmatch(text):
        raise ValueError(f"RSSI {text[:40]!r} is not an integer")
    if len(text) > 12:
        raise ValueError(f"RSSI {text[:40]}... is outside {RSSI_LO}..{RSSI_HI} dBm")
    row = MbdRow(t_ns, sensor, beacon, int(text), tuple(p.strip() for p in parts[4:]))
    if not T_NS_LO <= row.t_ns < T_NS_HI:
        raise ValueError(f"timestamp {parts[0].strip()[:40]} is outside 1970..2100")
    if not RSSI_LO <= row.rssi <= RSSI_HI:
        raise ValueError(f"RSSI {row.rssi} is outside {RSSI_LO}..{RSSI_HI} dBm")
    return row


def format_row(t_ns: int, sensor: str, beacon: str, rssi: int) -> str:
    """One fingerprint-style line, newline included."""
    return f"{format_ts(t_ns)},{sensor},{beacon},{rssi}\n"


def iter_rows(path: str | Path) -> Iterator[MbdRow]:
    """Rows of one file, in file order; blank lines skipped, anything else malformed is an error."""
    path = Path(path)
    for lineno, line in iter_lines(path, MbdError):
        if not line.strip():
            continue
        try:
            yield parse_line(line)
        except ValueError as e:
            raise MbdError(f"{path}:{lineno}: {e}") from None


def read_rows(paths: Iterable[str | Path]) -> list[MbdRow]:
    rows: list[MbdRow] = []
    for p in paths:
        rows.extend(iter_rows(p))
    return rows


TRACK_COLUMNS = [
    "ts",
    "sensor",
    "beacon",
    "rssi",
    "x",
    "y",
    "z",
    "r11",
    "r12",
    "r13",
    "r21",
    "r22",
    "r23",
    "r31",
    "r32",
    "r33",
]
