"""Tells systemd how a service is doing (sd_notify protocol), with the standard library only.

``Type=notify`` units wait for READY=1; ``WatchdogSec=`` expects WATCHDOG=1 at least that often.
Without ``$NOTIFY_SOCKET`` (not started by systemd, or in tests) every call is a cheap no-op.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class Notifier:
    """One datagram socket to systemd's notification socket, opened lazily.

    Failures are logged and swallowed: losing contact with systemd must never stop a capture
    (systemd itself will act through the watchdog if the service really is stuck).
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._address = self._parse(env.get("NOTIFY_SOCKET", ""))
        self._watchdog_usec = self._int(env.get("WATCHDOG_USEC"))
        # WATCHDOG_PID, when set, names the one process the watchdog expects to hear from.
        wpid = self._int(env.get("WATCHDOG_PID"))
        if wpid is not None and wpid != os.getpid():
            self._watchdog_usec = None
        self._sock: socket.socket | None = None

    @staticmethod
    def _parse(raw: str) -> str | bytes | None:
        if not raw:
            return None
        if raw.startswith("@"):  # abstract namespace socket
            return b"\0" + raw[1:].encode()
        if raw.startswith("/"):
            return raw
        log.warning("ignoring NOTIFY_SOCKET=%r: only AF_UNIX sockets are supported", raw)
        return None

    @staticmethod
    def _int(raw: str | None) -> int | None:
        try:
            return int(raw) if raw else None
        except ValueError:
            return None

    @property
    def enabled(self) -> bool:
        return self._address is not None

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to call :meth:`watchdog`: half of ``WatchdogSec=``, or None if not enabled."""
        if self._watchdog_usec is None or self._watchdog_usec <= 0:
            return None
        return self._watchdog_usec / 2e6

    def notify(self, *fields: str) -> bool:
        """Send ``KEY=value`` lines in one datagram; True if it was sent."""
        if self._address is None:
            return False
        msg = "\n".join(fields).encode()
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(msg, self._address)
        except OSError as e:
            log.warning("sd_notify %s failed: %s", fields[0] if fields else "", e)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1", *([f"STATUS={_one_line(status)}"] if status else []))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={_one_line(status)}"] if status else []))

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={_one_line(text)}")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def _one_line(text: str) -> str:
    # A newline would start a new KEY=value field in the datagram.
    return " ".join(text.split())
