"""Helpers for the agent tests that run a real agent process against a bare Zenoh session."""

from __future__ import annotations

import os
import sys

import zenoh

from ble_groundtruth import wire
from ble_groundtruth.zenoh_config import SessionSpec, build_config

AGENT = [sys.executable, "-c", "from sensor_agent.cli import main; main()"]


def agent_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("DBUS_SYSTEM_BUS_ADDRESS", None)
    return env


class FakeCollector:
    """Receives batches and acknowledges them per the contract (highest contiguous seq)."""

    def __init__(self, endpoint: str, site: str, ack: bool = True) -> None:
        self.site = site
        self.ack = ack
        self.session = zenoh.open(build_config(SessionSpec(mode="router", listen=[endpoint])))
        self.sub = self.session.declare_subscriber(wire.data_selector(site))
        self.batches: list[wire.Batch] = []
        self._seen: dict[tuple[str, str, str], set[int]] = {}

    def _contiguous(self, seqs: set[int]) -> int:
        n = -1
        while n + 1 in seqs:
            n += 1
        return n

    def poll(self) -> None:
        while (sample := self.sub.try_recv()) is not None:
            b = wire.from_wire(sample.payload.to_bytes())
            self.batches.append(b)
            self._seen.setdefault(b.stream, set()).add(b.seq)
            if self.ack:
                streams = {s: self._contiguous(q) for (a, boot, s), q in self._seen.items()
                           if a == b.agent_id and boot == b.boot_id}
                self.session.put(wire.ack_key(self.site, b.agent_id),
                                 wire.to_json({"boot": b.boot_id, "streams": streams}))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()
