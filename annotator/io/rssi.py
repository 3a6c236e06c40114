"""Loading the RSSI side of an experiment: a collector run dir or a folder of ``*.mbd`` files.

A run dir holds ``rssi/<agent>/<sensor>.mbd`` (one file per agent and sensor; older runs
``rssi/<sensor>.mbd``) and ``run.yaml``; a plain folder holds the
``.mbd`` files directly; a single ``.mbd`` file works too. Timestamps stay exact int64 ns.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.errors import ConfigError, NoDataError
from bgt_core.formats._textio import iter_lines
from bgt_core.formats.mbd import MbdError, MbdRow, parse_line
from bgt_core.run_record import RunRecord, RunRecordError

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class RssiTable:
    """Readings sorted by time: t_ns (int64 Unix ns), sensor, beacon (12-hex MACs), rssi (dBm)."""

    t_ns: np.ndarray
    sensor: np.ndarray  # str
    beacon: np.ndarray  # str
    rssi: np.ndarray  # int16
    files: tuple[Path, ...] = ()
    run_info: RunRecord | None = None  # run.yaml of a collector run, if there is one

    def __len__(self) -> int:
        return int(self.t_ns.size)

    def select(self, mask: np.ndarray) -> RssiTable:
        return RssiTable(
            self.t_ns[mask],
            self.sensor[mask],
            self.beacon[mask],
            self.rssi[mask],
            self.files,
            self.run_info,
        )

    def t_seconds(self) -> np.ndarray:
        """Float Unix seconds (about 0.2 us resolution; use t_ns where exactness matters)."""
        return self.t_ns / 1e9


def _is_merged(path: Path) -> bool:
    return path.stem == "all_sensors" or path.stem.endswith("_all_sensors")


def rssi_files(path: str | Path) -> tuple[list[Path], Path | None]:
    """The .mbd files behind ``path`` and the run.yaml (if any); ConfigError if there are none."""
    path = Path(path)
    if path.is_file():
        return [path], None
    if not path.is_dir():
        raise ConfigError(f"rssi: no such file or folder {path}")
    run_yaml = path / "run.yaml"
    folder = path / "rssi" if (path / "rssi").is_dir() else path
    files = sorted(folder.glob("*.mbd"))
    if folder.name == "rssi" and not files:  # a collector run: one folder per agent
        files = sorted(folder.glob("*/*.mbd"))
    per_sensor = [f for f in files if not _is_merged(f)]
    # A merged all_sensors file beside per-sensor files repeats their rows.
    files = per_sensor or files
    if not files:
        raise ConfigError(
            f"rssi: no .mbd files in {folder} (put the sensors' .mbd files or a collector run "
            "there; `annotator track` tracks the videos without readings)"
        )
    return files, run_yaml if run_yaml.is_file() else None


def _file_rows(path: Path) -> list[MbdRow]:
    """Rows of one .mbd file. A last line cut short (no newline: the writer was killed mid-line)
    is skipped with a warning; any other malformed line is an MbdError naming file and line."""
    rows: list[MbdRow] = []
    lines = [line for _, line in iter_lines(path, MbdError)]  # MbdError for bytes not UTF-8
    for lineno, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            rows.append(parse_line(line))
        except ValueError as e:
            if lineno == len(lines) and not line.endswith("\n"):
                log.warning("%s:%d: incomplete last line skipped (%s)", path, lineno, e)
                continue
            raise MbdError(f"{path}:{lineno}: {e}") from None
    return rows


def load_rssi(path: str | Path) -> RssiTable:
    """Every reading under ``path`` (see module doc), sorted by time; MbdError names a bad line."""
    files, run_yaml = rssi_files(path)
    t, sensor, beacon, rssi = [], [], [], []
    for f in files:
        for row in _file_rows(f):
            t.append(row.t_ns)
            sensor.append(row.sensor)
            beacon.append(row.beacon)
            rssi.append(row.rssi)
    if not t:
        raise NoDataError(f"rssi: the .mbd files under {path} hold no readings")
    t_ns = np.asarray(t, dtype=np.int64)
    order = np.argsort(t_ns, kind="stable")
    info = None
    if run_yaml is not None:
        from bgt_core.safe_yaml import YamlError, load_file

        try:
            info = RunRecord.from_dict(
                load_file(run_yaml), str(run_yaml), default_id=run_yaml.parent.name
            )
        except (YamlError, RunRecordError) as e:
            raise ConfigError(f"run info: {e}") from None
    table = RssiTable(
        t_ns[order],
        np.asarray(sensor)[order],
        np.asarray(beacon)[order],
        np.asarray(rssi, dtype=np.int16)[order],
        tuple(files),
        info,
    )
    log.info("rssi: %d readings from %d file(s) under %s", len(table), len(files), path)
    return table


def bundle_beacon(table: RssiTable, beacon: str | None = None) -> str:
    """The bundle's beacon: the one asked for, or the most often heard one."""
    heard = Counter(table.beacon.tolist())
    if beacon is not None:
        if beacon not in heard:
            raise NoDataError(
                f"rssi: beacon {beacon} is never heard (heard: {', '.join(sorted(heard))})"
            )
        return beacon
    (top, n), *rest = heard.most_common()
    if rest:
        log.warning(
            "rssi: %d beacons heard; labelling the most frequent, %s (%d readings)",
            len(heard),
            top,
            n,
        )
    return top


def receiver_readings(table: RssiTable, receiver: str) -> RssiTable:
    """Every reading taken by the sensor ``receiver`` (receiver mode), of any beacon."""
    mine = table.sensor == receiver
    if not mine.any():
        sensors = sorted(set(table.sensor.tolist()))
        shown = ", ".join(sensors[:12]) + (
            f" and {len(sensors) - 12} more" if len(sensors) > 12 else ""
        )
        raise NoDataError(f"rssi: receiver {receiver} took no readings (sensors: {shown})")
    out = table.select(mine)
    log.info(
        "rssi: receiver %s heard %d beacon(s) in %d readings",
        receiver,
        len(set(out.beacon.tolist())),
        len(out),
    )
    return out
