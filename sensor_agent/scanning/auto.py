"""``backend: auto``: the kernel's management socket when it can be used, else BlueZ over D-Bus.

The management backend sees every advertisement; bleak sees what BlueZ passes on. When the
management socket cannot be opened (no CAP_NET_ADMIN/CAP_NET_RAW, no kernel Bluetooth stack, a
kernel without advertisement monitors) the reason is logged in one line and bleak takes over.
``backend: mgmt`` demands the socket and fails with that line instead.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from sensor_agent.scanning.base import AdapterInfo, AdvertSink, ScannerBackend
from sensor_agent.scanning.mgmt_backend import MgmtUnavailable

log = logging.getLogger(__name__)


class AutoBackend(ScannerBackend):
    name = "auto"

    def __init__(
        self,
        mgmt: Callable[[], ScannerBackend],
        fallback: Callable[[], ScannerBackend],
    ) -> None:
        self._make_mgmt = mgmt
        self._make_fallback = fallback
        self.active: ScannerBackend | None = None
        self.fallback_reason: str | None = None

    @property
    def adapters(self) -> tuple[AdapterInfo, ...]:
        return self.active.adapters if self.active is not None else ()

    async def start(self, sink: AdvertSink) -> None:
        backend = self._make_mgmt()
        try:
            await backend.start(sink)
        except MgmtUnavailable as e:
            self.fallback_reason = str(e)
            log.warning(
                "management socket unavailable: %s; scanning through BlueZ over D-Bus instead "
                "(fewer reports on many controllers; see `sensor-agent doctor`)",
                e,
            )
            backend = self._make_fallback()
            await backend.start(sink)
        self.active = backend

    async def stop(self) -> None:
        if self.active is not None:
            await self.active.stop()

    def restarts(self, adapter_mac: str) -> int:
        return self.active.restarts(adapter_mac) if self.active is not None else 0

    def power_cycles(self, adapter_mac: str) -> int:
        return self.active.power_cycles(adapter_mac) if self.active is not None else 0
