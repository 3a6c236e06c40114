"""`annotator import-log` (issue 36): a phone's scan log in CSV becomes the receiver's .mbd file,
times exact (Unix seconds or milliseconds, ISO 8601 with an offset), rows in time order; a bad row
is one line naming the file and the row, and nothing is written."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from annotator.cli import app
from annotator.io.phone_log import LogError, parse_time, read_log, write_log_run
from annotator.io.rssi import load_rssi
from bgt_core.formats.mbd import iter_rows

T = 1_700_000_000


@pytest.mark.parametrize(
    ("text", "unit", "t_ns"),
    [
        ("1700000000.125", "s", T * 10**9 + 125_000_000),
        ("1700000000.000000001", "s", T * 10**9 + 1),
        ("1700000000125", "ms", T * 10**9 + 125_000_000),
        ("2023-11-14T22:13:20.125Z", "s", T * 10**9 + 125_000_000),
        ("2023-11-14T23:13:20.125+01:00", "s", T * 10**9 + 125_000_000),
        ("2023-11-14T17:13:20.000250-05:00", "s", T * 10**9 + 250_000),
    ],
)
def test_times_are_exact(text: str, unit: str, t_ns: int) -> None:
    assert parse_time(text, unit) == t_ns


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("2023-11-14T22:13:20", "no UTC offset"),
        ("yesterday", "neither Unix seconds nor ISO 8601"),
        ("99999999999", "outside 1970..2100"),
        ("-5", "outside 1970..2100"),
        ("1" * 60, "too long"),
    ],
)
def test_bad_times_say_why(text: str, says: str) -> None:
    with pytest.raises(ValueError, match=says):
        parse_time(text)


def write_csv(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


GOOD = [
    "when,name,address,rssi",
    "2023-11-14T22:13:21.500Z,tag,AA:BB:CC:DD:EE:01,-70",
    '1700000001.25,"a, quoted name",aa-bb-cc-dd-ee-02,-61.0',
    "",
    "1700000000.75,tag,aabbccddee01,-80",
]


def test_log_rows_become_the_receivers_file_in_time_order(tmp_path: Path) -> None:
    log = write_csv(tmp_path / "scan.csv", GOOD)
    readings = read_log(log, ("when", "address", "rssi"))
    assert [(r.t_ns, r.beacon, r.rssi) for r in readings] == [
        (T * 10**9 + 1_500_000_000, "aabbccddee01", -70),
        (T * 10**9 + 1_250_000_000, "aabbccddee02", -61),
        (T * 10**9 + 750_000_000, "aabbccddee01", -80),
    ]
    done = write_log_run(readings, "020000000001", tmp_path / "rssi")
    assert (done.readings, done.beacons) == (3, 2)
    rows = list(iter_rows(done.path))
    assert [r.t_ns for r in rows] == sorted(r.t_ns for r in rows)
    assert {r.sensor for r in rows} == {"020000000001"}
    # the folder is what experiment.yaml's rssi: names
    table = load_rssi(tmp_path / "rssi")
    assert len(table) == 3
    assert set(table.sensor) == {"020000000001"}
    # an existing file is kept unless --force
    with pytest.raises(LogError, match="exists; pass --force"):
        write_log_run(readings[:1], "020000000001", tmp_path / "rssi")
    assert len(list(iter_rows(done.path))) == 3


@pytest.mark.parametrize(
    ("lines", "columns", "says"),
    [
        (GOOD[:1] + ["not-a-time,tag,aabbccddee01,-70"], None, "scan.csv:2: time 'not-a-time'"),
        (GOOD[:2] + ["1700000001,tag,zz:bb,-70"], None, "scan.csv:3: beacon 'zz:bb' is not a MAC"),
        (GOOD[:2] + ["1700000001,tag,aabbccddee01,strong"], None, "scan.csv:3: RSSI 'strong'"),
        (GOOD[:2] + ["1700000001,tag,aabbccddee01,-300"], None, "scan.csv:3: RSSI -300 is outside"),
        (GOOD[:2] + ["1700000001,tag"], None, "scan.csv:3: 2 field\\(s\\) where the header has 4"),
        (GOOD, ("when", "mac", "rssi"), "no column 'mac' for the beacon .*columns: when, name"),
        ([""], None, "empty; expected a header row"),
        (GOOD[:1], None, "a header and no readings"),
        (GOOD[:1] + ['1700000001,"unclosed,aabbccddee01,-70'], None, "not CSV"),
    ],
)
def test_a_bad_row_is_one_line_naming_it(
    tmp_path: Path, lines: list[str], columns: tuple[str, str, str] | None, says: str
) -> None:
    log = write_csv(tmp_path / "scan.csv", lines)
    with pytest.raises(LogError, match=says):
        read_log(log, columns or ("when", "address", "rssi"))


def test_the_command(tmp_path: Path) -> None:
    log = write_csv(tmp_path / "scan.csv", GOOD)
    out = tmp_path / "rssi"
    cli = CliRunner()
    args = ["import-log", str(log), "--columns", "when,address,rssi", "--out", str(out)]
    res = cli.invoke(app, [*args, "--sensor", "02:00:00:00:00:01"])
    assert res.exit_code == 0, res.output
    assert "3 readings of 2 beacons" in res.output
    assert (out / "020000000001.mbd").is_file()
    # one line, nothing written, for each kind of mistake
    for extra, says in (
        (["--sensor", "my-phone"], "--sensor 'my-phone' is not a MAC address"),
        (["--sensor", "020000000002", "--format", "json"], "csv is the one format"),
        (["--sensor", "020000000002", "--time-unit", "h"], "time unit 'h'"),
        (["--sensor", "020000000002", "--columns", "a,b"], "expected three header names"),
    ):
        res = cli.invoke(app, [*args, *extra])
        assert res.exit_code != 0
        assert says in res.output, res.output
        assert len(res.output.strip().splitlines()) == 1, res.output
    assert sorted(p.name for p in out.iterdir()) == ["020000000001.mbd"]
