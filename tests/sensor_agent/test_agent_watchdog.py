"""The watchdog's settings, and powering an adapter over D-Bus: BlueZ's 'busy' answers are retried
with backoff, anything else is one clear error (a fake bus stands in for dbus-fast's MessageBus)."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace

import pytest
from dbus_fast import MessageType

from sensor_agent.config import parse_config
from sensor_agent.errors import BackendError, ConfigError
from sensor_agent.scanning.base import Clocks
from sensor_agent.scanning.bleak_backend import POWER_RETRIES, _set_powered


class FakeBus:
    """Answers each call with the next error name from ``errors`` (None = success)."""

    def __init__(self, errors: list[str | None]) -> None:
        self.errors = list(errors)
        self.calls: list[tuple[str, str, list]] = []

    async def call(self, msg):
        self.calls.append((msg.path, msg.member, [msg.body[0], msg.body[1], msg.body[2].value]))
        err = self.errors.pop(0) if self.errors else None
        if err is None:
            return SimpleNamespace(message_type=MessageType.METHOD_RETURN, error_name=None, body=[])
        return SimpleNamespace(message_type=MessageType.ERROR, error_name=err, body=["busy now"])


def run(bus: FakeBus, on: bool) -> list[float]:
    slept: list[float] = []

    async def sleep(s: float) -> None:
        slept.append(s)

    asyncio.run(_set_powered(bus, "/org/bluez/hci3", on, Clocks(sleep=sleep)))
    return slept


def test_in_progress_and_not_ready_are_retried_with_backoff() -> None:
    bus = FakeBus(["org.bluez.Error.InProgress", "org.bluez.Error.NotReady", None])
    assert run(bus, False) == [0.25, 0.5]
    assert bus.calls == [("/org/bluez/hci3", "Set", ["org.bluez.Adapter1", "Powered", False])] * 3


def test_other_errors_fail_at_once_with_one_line() -> None:
    bus = FakeBus(["org.bluez.Error.Failed"])
    with pytest.raises(
        BackendError,
        match=r"cannot power on adapter /org/bluez/hci3: "
        r"org\.bluez\.Error\.Failed busy now",
    ):
        run(bus, True)
    assert len(bus.calls) == 1


def test_retries_are_bounded() -> None:
    bus = FakeBus(["org.bluez.Error.InProgress"] * 50)
    with pytest.raises(BackendError, match="InProgress"):
        run(bus, True)
    assert len(bus.calls) == POWER_RETRIES


def test_watchdog_config_validated() -> None:
    cfg = parse_config({"watchdog": {"silent_s": 20, "power_cycle_after": 3}})
    assert (cfg.watchdog.silent_s, cfg.watchdog.power_cycle_after) == (20.0, 3)
    assert parse_config({}).watchdog.silent_s == 60.0
    for bad, msg in [
        ({"silent_s": 0}, "watchdog.silent_s must be a number > 0, got 0"),
        ({"silent_s": "x"}, "watchdog.silent_s must be a number > 0, got 'x'"),
        ({"power_cycle_after": -1}, "watchdog.power_cycle_after must be an integer >= 0"),
        ({"power_cycle_after": 1.5}, "watchdog.power_cycle_after must be an integer >= 0"),
        ({"restart": 1}, "unknown key 'watchdog.restart'"),
    ]:
        with pytest.raises(ConfigError, match=msg.replace(".", r"\.").replace("(", r"\(")):
            parse_config({"watchdog": bad}, "agent.yaml")
