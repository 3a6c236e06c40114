"""A phone's (or any scanner app's) own log of what it heard, turned into the run layout.

The log is a CSV file with a header row; three of its columns, named by the user, hold the time of
each reading, the beacon's address and the RSSI. Times are Unix seconds (``1700000000.125``; or
milliseconds with ``time_unit="ms"``) or ISO 8601 with a UTC offset (``2026-11-27T14:03:05.125+01:00``
or ``...Z``); a time without an offset is refused, since the phone's time zone is not known here.
The rows become one ``<sensor>.mbd`` file (the fingerprint format of the dataset), sorted by time,
so that ``rssi:`` in experiment.yaml can name the folder. The phone's clock stays as it is: the
annotator's automatic sync finds each video's start on it.
"""

from __future__ import annotations

import csv
import datetime as dt
import re
from collections.abc import Iterator
from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path

from annotator.errors import AnnotatorError
from bgt_core.formats._textio import iter_lines
from bgt_core.formats.mbd import RSSI_HI, RSSI_LO, T_NS_HI, T_NS_LO, format_row
from bgt_core.wire import WireError, normalize_mac

# What the three mapped columns hold, in the order --columns names them.
FIELDS = ("time", "beacon", "rssi")
TIME_UNITS = {"s": 10**9, "ms": 10**6}
_NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)")
_RSSI = re.compile(r"[+-]?\d{1,4}(\.0*)?")


class LogError(AnnotatorError):
    """A phone log that cannot be imported; the message names the file and the row."""


@dataclass(frozen=True, slots=True)
class LogReading:
    t_ns: int
    beacon: str  # 12 lower-case hex digits
    rssi: int


@dataclass(frozen=True, slots=True)
class ImportedLog:
    path: Path  # the .mbd file written
    readings: int
    beacons: int
    first_ns: int
    last_ns: int


def parse_columns(text: str) -> tuple[str, str, str]:
    """``"t,beacon,rssi"`` -> the header names of the time, beacon and RSSI columns."""
    names = tuple(c.strip() for c in text.split(","))
    if len(names) != 3 or not all(names):
        raise LogError(
            f"--columns {text!r}: expected three header names, TIME,BEACON,RSSI (e.g. t,beacon,rssi)"
        )
    if len(set(names)) != 3:
        raise LogError(f"--columns {text!r}: the three columns must differ")
    return names[0], names[1], names[2]


def parse_time(text: str, time_unit: str = "s") -> int:
    """Unix seconds (or ``time_unit`` "ms") or ISO 8601 with a UTC offset -> Unix ns; ValueError
    says what is wrong."""
    text = text.strip()
    if _NUMBER.fullmatch(text):
        if len(text) > 40:
            raise ValueError(f"time {text[:40]}... is too long")
        t_ns = int(Decimal(text) * TIME_UNITS[time_unit])
    else:
        try:
            when = dt.datetime.fromisoformat(text)
        except ValueError:
            raise ValueError(
                f"time {text[:40]!r} is neither Unix {'milli' if time_unit == 'ms' else ''}"
                "seconds nor ISO 8601 (2026-11-27T14:03:05.125+01:00)"
            ) from None
        if when.tzinfo is None:
            raise ValueError(
                f"time {text[:40]!r} has no UTC offset (add Z or +HH:MM: the phone's time zone "
                "is not known here)"
            )
        # Exact to the microsecond: no float on the way.
        delta = when - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
        t_ns = (delta.days * 86_400 + delta.seconds) * 10**9 + delta.microseconds * 1000
    if not T_NS_LO <= t_ns < T_NS_HI:
        raise ValueError(f"time {text[:40]} is outside 1970..2100")
    return t_ns


def parse_rssi(text: str) -> int:
    text = text.strip()
    if not _RSSI.fullmatch(text):
        raise ValueError(f"RSSI {text[:40]!r} is not a whole number of dBm")
    value = int(Decimal(text))
    if not RSSI_LO <= value <= RSSI_HI:
        raise ValueError(f"RSSI {value} is outside {RSSI_LO}..{RSSI_HI} dBm")
    return value


def _rows(path: Path, delimiter: str) -> Iterator[tuple[int, list[str]]]:
    """(line number, fields) of each CSV record; undecodable or refused files are a LogError."""
    lines = iter_lines(path, LogError, "readings")
    numbered: list[int] = []

    def text() -> Iterator[str]:
        for lineno, line in lines:
            numbered.append(lineno)
            yield line

    reader = csv.reader(text(), delimiter=delimiter, strict=True)
    try:
        for record in reader:
            yield numbered[-1], record
    except csv.Error as e:
        raise LogError(f"{path}:{numbered[-1] if numbered else 1}: not CSV ({e})") from None


def read_log(
    path: str | Path,
    columns: tuple[str, str, str] = ("t", "beacon", "rssi"),
    *,
    time_unit: str = "s",
    delimiter: str = ",",
) -> list[LogReading]:
    """Every reading of the log at ``path``, in file order; LogError names the first bad row."""
    path = Path(path)
    if time_unit not in TIME_UNITS:
        raise LogError(f"time unit {time_unit!r}: expected s or ms")
    rows = _rows(path, delimiter)
    header: list[str] | None = None
    for _, record in rows:
        if record and any(f.strip() for f in record):
            header = [f.strip().lstrip("\ufeff") for f in record]
            break
    if header is None:
        raise LogError(f"{path}: empty; expected a header row naming the columns")
    where = {}
    for field, name in zip(FIELDS, columns, strict=True):
        if name not in header:
            shown = ", ".join(header[:20]) + (" ..." if len(header) > 20 else "")
            raise LogError(
                f"{path}: no column {name!r} for the {field} in the header (columns: {shown}); "
                "name the right ones with --columns TIME,BEACON,RSSI"
            )
        where[field] = header.index(name)
    need = max(where.values()) + 1
    out: list[LogReading] = []
    for lineno, record in rows:
        if not any(f.strip() for f in record):
            continue
        if len(record) < need:
            raise LogError(
                f"{path}:{lineno}: {len(record)} field(s) where the header has {len(header)}"
            )
        try:
            t_ns = parse_time(record[where["time"]], time_unit)
            try:
                beacon = normalize_mac(record[where["beacon"]])
            except WireError:
                raise ValueError(
                    f"beacon {record[where['beacon']].strip()[:40]!r} is not a MAC address"
                ) from None
            rssi = parse_rssi(record[where["rssi"]])
        except (ValueError, InvalidOperation) as e:
            raise LogError(f"{path}:{lineno}: {e}") from None
        out.append(LogReading(t_ns, beacon, rssi))
    if not out:
        raise LogError(f"{path}: a header and no readings")
    return out


def write_log_run(
    readings: list[LogReading], sensor: str, out_dir: str | Path, *, force: bool = False
) -> ImportedLog:
    """``<out_dir>/<sensor>.mbd``: the readings in time order, written whole or not at all. An
    existing file is kept (LogError) unless ``force``."""
    out_dir = Path(out_dir)
    path = out_dir / f"{sensor}.mbd"
    if path.exists() and not force:
        raise LogError(f"{path} exists; pass --force to replace it")
    out_dir.mkdir(parents=True, exist_ok=True)
    ordered = sorted(readings, key=lambda r: r.t_ns)
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("w", encoding="utf-8", newline="\n") as f:
        f.writelines(format_row(r.t_ns, sensor, r.beacon, r.rssi) for r in ordered)
    tmp.replace(path)
    return ImportedLog(
        path,
        len(ordered),
        len({r.beacon for r in ordered}),
        ordered[0].t_ns,
        ordered[-1].t_ns,
    )
