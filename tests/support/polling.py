"""Waiting for a condition with a deadline: the one poll helper of the tests (sync and async).

Deadlines are generous (the test machine is shared); the AssertionError names what was awaited.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any


def wait_for(
    cond: Callable[[], Any],
    timeout: float = 20.0,
    what: str = "condition",
    *,
    step: float = 0.02,
    poll: Callable[[], object] | None = None,
) -> Any:
    """Poll ``cond()`` (after ``poll()``, if given) until it is truthy; returns that value."""
    deadline = time.monotonic() + timeout
    while True:
        if poll is not None:
            poll()
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(step)


async def wait_for_async(
    cond: Callable[[], Any], limit_s: float = 15.0, what: str = "condition", *, step: float = 0.01
) -> Any:
    """``wait_for`` inside an event loop: sleeps with asyncio so the loop keeps running."""
    deadline = time.monotonic() + limit_s
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {limit_s:g} s waiting for {what}")
        await asyncio.sleep(step)
