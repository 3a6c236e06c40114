"""Helpers for the deployment tests: constants, free loopback ports, and polling with a deadline."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

AGENTS = ("a1", "a2")
ADMINS = ("collector", "operator")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(pred: Callable[[], bool], timeout: float = 10.0, step: float = 0.02) -> bool:
    """Poll ``pred`` until it is true or ``timeout`` seconds pass (generous: the CI box is shared)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()
