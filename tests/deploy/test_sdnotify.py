"""sd_notify against a real AF_UNIX datagram socket standing in for systemd's."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from bgt_core.sdnotify import Notifier


@pytest.fixture
def systemd_socket(tmp_path: Path):
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(5)
    yield path, sock
    sock.close()


def test_messages_arrive_as_systemd_expects(systemd_socket) -> None:
    path, sock = systemd_socket
    n = Notifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "20000000"})
    assert n.enabled
    assert n.watchdog_interval_s == pytest.approx(10.0)
    assert n.ready("listening on\ntls/0.0.0.0:7447")
    assert n.watchdog()
    assert n.status("3 agents")
    assert n.stopping("draining")
    got = [sock.recv(4096).decode() for _ in range(4)]
    assert got == [
        "READY=1\nSTATUS=listening on tls/0.0.0.0:7447",
        "WATCHDOG=1",
        "STATUS=3 agents",
        "STOPPING=1\nSTATUS=draining",
    ]
    n.close()


def test_abstract_socket_address() -> None:
    name = f"ble-groundtruth-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(5)
    try:
        n = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert sock.recv(64) == b"READY=1"
        n.close()
    finally:
        sock.close()


def test_without_notify_socket_everything_is_a_no_op() -> None:
    n = Notifier({})
    assert not n.enabled
    assert n.watchdog_interval_s is None
    assert not n.ready()
    assert not n.watchdog()
    assert not n.stopping()


def test_watchdog_meant_for_another_process_is_ignored(systemd_socket) -> None:
    path, _ = systemd_socket
    n = Notifier(
        {
            "NOTIFY_SOCKET": str(path),
            "WATCHDOG_USEC": "1000000",
            "WATCHDOG_PID": str(os.getpid() + 1),
        }
    )
    assert n.watchdog_interval_s is None
    n = Notifier(
        {"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(os.getpid())}
    )
    assert n.watchdog_interval_s == pytest.approx(0.5)


def test_vanished_socket_is_logged_not_raised(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert n.ready() is False
    assert "sd_notify READY=1 failed" in caplog.text
    n.close()
