"""`annotator import-log`: a phone's scan log (CSV) -> the .mbd readings `annotator run` reads."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError

HELP = (
    "Turn a scan app's log into readings `annotator run` can label: OUT/<SENSOR>.mbd, one row "
    "per reading, in time order.\n\n"
    "FILE is a CSV with a header row. --columns names the header's columns that hold the time, "
    "the beacon's address and the RSSI (other columns are ignored). A time is Unix seconds "
    "(--time-unit ms for milliseconds) or ISO 8601 with a UTC offset "
    "(2026-11-27T14:03:05.125+01:00 or ...Z). --sensor is the id the receiver gets in the "
    "dataset (a 12-hex MAC: the phone's Bluetooth address, or any fixed made-up one).\n\n"
    "The phone's clock is kept: point experiment.yaml's rssi: at OUT, set receiver: to SENSOR "
    "and sync.mode: auto, and the hands-cover event maps each video onto the phone's clock.\n\n"
    "Example:\n\n"
    "  annotator import-log scan.csv --columns timestamp,mac,rssi --sensor 02:00:00:00:00:01 "
    "--out walk1/rssi\n"
)


def import_log(
    source: Annotated[
        Path, typer.Argument(metavar="FILE", help="The app's CSV log.", show_default=False)
    ],
    sensor: Annotated[
        str,
        typer.Option(help="The receiver's id in the dataset, a MAC address.", show_default=False),
    ],
    out: Annotated[
        Path,
        typer.Option("--out", "-o", help="Folder for SENSOR.mbd (created).", show_default=False),
    ],
    columns: Annotated[
        str, typer.Option(help="Header names of the TIME,BEACON,RSSI columns.")
    ] = "t,beacon,rssi",
    log_format: Annotated[
        str, typer.Option("--format", help="Format of FILE; csv is the one known.")
    ] = "csv",
    time_unit: Annotated[
        str, typer.Option(help="Unit of numeric times: s (Unix seconds) or ms.")
    ] = "s",
    delimiter: Annotated[
        str, typer.Option(help="Field separator of the CSV (one character; 'tab' for a tab).")
    ] = ",",
    force: Annotated[bool, typer.Option(help="Replace OUT/SENSOR.mbd if it exists.")] = False,
) -> None:
    with one_line_errors():
        from annotator.io.phone_log import parse_columns, read_log, write_log_run
        from bgt_core.wire import normalize_mac

        if log_format != "csv":
            raise ConfigError(f"--format {log_format!r}: csv is the one format known")
        delimiter = "\t" if delimiter == "tab" else delimiter
        if len(delimiter) != 1:
            raise ConfigError(f"--delimiter {delimiter!r}: one character, or 'tab'")
        try:
            mac = normalize_mac(sensor)
        except ValueError:
            raise ConfigError(
                f"--sensor {sensor!r} is not a MAC address (use the phone's Bluetooth address "
                "or any fixed 12-hex id)"
            ) from None
        readings = read_log(
            source, parse_columns(columns), time_unit=time_unit, delimiter=delimiter
        )
        done = write_log_run(readings, mac, out, force=force)

        def utc(t_ns: int) -> str:
            return dt.datetime.fromtimestamp(t_ns / 1e9, dt.UTC).isoformat(timespec="milliseconds")

        span = (done.last_ns - done.first_ns) / 1e9
        console.print(
            f"wrote {done.path}: {done.readings} readings of {done.beacons} beacons, "
            f"{utc(done.first_ns)} to {utc(done.last_ns)} UTC on the phone's clock ({span:.1f} s)",
            highlight=False,
            soft_wrap=True,
            markup=False,
        )


def register(app: typer.Typer) -> None:
    app.command("import-log", help=HELP)(import_log)
