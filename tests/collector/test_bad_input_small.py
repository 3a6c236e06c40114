"""Bad input, round three, the small ones (issue 35): numbers that must be finite, run names
that must be printable and short, one rule for ids, text shown as text."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from bgt_core.display import shown
from bgt_core.wire import InvalidField, check_id
from collector.cli import app
from sensor_agent.config import parse_config
from sensor_agent.errors import ConfigError as AgentConfigError


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--max-offset-ms", "nan"], "--max-offset-ms must be a finite number"),
        (["--max-offset-ms", "inf"], "--max-offset-ms must be a finite number"),
        (["--max-offset-ms", "-1"], "--max-offset-ms must be a finite number"),
        (["--name", "x" * 100_000], "--name: start: name must be at most 200 printable"),
        (["--name", "walk\x1b[2J"], "--name: start: name must be at most 200 printable"),
    ],
)
def test_start_refuses_before_asking_the_collector(args: list[str], message: str) -> None:
    """Refused with one line before any connection (the endpoint here has no collector)."""
    res = CliRunner().invoke(app, ["start", *args, "--connect", "tcp/127.0.0.1:9"])
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    assert message in lines[0]
    assert "\x1b[2J" not in res.output


def test_ids_follow_one_rule_in_the_agent_and_the_collector() -> None:
    for good in ("pi-1", "a.b", "_x", "A" * 64):
        assert check_id(good) == good
    for bad in (".hidden", "..", "", "a/b", "A" * 65, "é"):
        with pytest.raises(InvalidField, match="not starting with a dot"):
            check_id(bad, "agent id")
    with pytest.raises(AgentConfigError, match="agent_id must be"):
        parse_config({"agent_id": ".pi"})


def test_shown_escapes_and_cuts() -> None:
    assert shown("hall walk") == "hall walk"
    assert shown("a\x1b[31mred\n") == "a\\x1b[31mred\\n"
    assert shown("x" * 100, 10) == "x" * 9 + "…"
    assert shown("x" * 100, None) == "x" * 100


def test_a_long_timestamp_is_named_as_the_timestamp() -> None:
    from bgt_core.formats.mbd import parse_line

    with pytest.raises(ValueError, match=r"timestamp 1{40}... is outside 1970..2100") as err:
        parse_line("1" * 5000 + ",aabbccddeeff,112233445566,-60")
    assert len(str(err.value)) < 120
    with pytest.raises(ValueError, match="RSSI '--60' is not an integer"):
        parse_line("1700000000.5,aabbccddeeff,112233445566,--60")
    assert parse_line("1700000000.5,aabbccddeeff,112233445566,-60").rssi == -60


def test_a_replay_file_that_is_not_text_is_one_line(tmp_path) -> None:  # noqa: ANN001
    from sensor_agent.errors import BackendError
    from sensor_agent.scanning.replay import ReplayBackend

    good = "1700000000.5,aabbccddeeff,112233445566,-60\n"
    path = tmp_path / "rec.mbd"
    path.write_bytes(good.encode() * 3 + b"1700000001.5,aabbccddeeff,11223344\xff566,-60\n")
    backend = ReplayBackend([path])
    with pytest.raises(BackendError, match=r"rec.mbd:4: not UTF-8 text"):
        backend.check()


def test_a_start_that_timed_out_leaves_nothing_started(tmp_path, endpoint) -> None:  # noqa: ANN001
    """Issue 35: the start an operator saw fail (its writer was busy past the timeout) used to
    start a run anyway once the writer got to it."""
    import time

    from bgt_core.control_messages import StartRequest
    from collector.config import CollectorConfig
    from collector.errors import CollectorError
    from collector.service import Collector

    c = Collector(CollectorConfig(data_dir=tmp_path / "data", listen=(endpoint,))).open()
    try:
        c.writer.post(lambda: time.sleep(1.5))  # the writer thread busy for 1.5 s
        with pytest.raises(CollectorError, match="nothing was started"):
            c.control.start_run(StartRequest("late"), timeout=0.5)
        time.sleep(2.0)  # the writer has run the queued start by now: it must have refused
        assert c.status()["run"] is None
        assert not list((tmp_path / "data").glob("*-late"))
        assert c.start_run("on-time")["run_id"].endswith("-on-time")  # and the next start works
        c.stop_run()
    finally:
        c.close()
