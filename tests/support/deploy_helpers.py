"""Helpers for the deployment tests: constants, free loopback ports, and polling with a deadline."""

from __future__ import annotations

from collections.abc import Callable

from loopback import free_port  # noqa: F401 - the deploy tests import it from here
from polling import wait_for

AGENTS = ("a1", "a2")
ADMINS = ("collector", "operator")


def wait_until(pred: Callable[[], bool], timeout: float = 10.0, step: float = 0.02) -> bool:
    """Poll ``pred`` until it is true or ``timeout`` seconds pass (generous: the CI box is shared)."""
    try:
        wait_for(pred, timeout, step=step)
    except AssertionError:
        return False
    return True
