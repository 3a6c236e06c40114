"""Helpers for the agent tests that run a real agent process against a bare Zenoh session."""

from __future__ import annotations

import os
import sys

import zenoh

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, build_config

AGENT = [sys.executable, "-c", "from sensor_agent.cli import main; main()"]


def agent_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("DBUS_SYSTEM_BUS_ADDRESS", None)
    return env


class FakeCollector:
    """Receives batches and acknowledges them per the contract: per (agent, boot) stream the
    highest seq with every earlier one received, skipping over seqs below the batch's floor;
    one ack message per boot of the agent."""

    def __init__(self, endpoint: str, site: str, ack: bool = True) -> None:
        self.site = site
        self.ack = ack
        self.session = zenoh.open(build_config(SessionSpec(mode="router", listen=[endpoint])))
        self.sub = self.session.declare_subscriber(wire.data_selector(site))
        self.batches: list[wire.Batch] = []
        self.payloads: list[bytes] = []
        self._seen: dict[tuple[str, str, str], set[int]] = {}
        self._mark: dict[tuple[str, str, str], int] = {}

    def watermark(self, stream: tuple[str, str, str]) -> int:
        n = self._mark.get(stream, -1)
        seen = self._seen.get(stream, set())
        while n + 1 in seen:
            n += 1
        self._mark[stream] = n
        return n

    def poll(self) -> None:
        while (sample := self.sub.try_recv()) is not None:
            data = sample.payload.to_bytes()
            b = wire.from_wire(data)
            self.batches.append(b)
            self.payloads.append(data)
            self._seen.setdefault(b.stream, set()).add(b.seq)
            if b.floor > 0:
                self._mark[b.stream] = max(self._mark.get(b.stream, -1), b.floor - 1)
            if self.ack:
                streams = {
                    s: self.watermark((a, boot, s))
                    for (a, boot, s) in list(self._seen)
                    if a == b.agent_id and boot == b.boot_id
                }
                self.session.put(
                    wire.ack_key(self.site, b.agent_id),
                    wire.to_json({"boot": b.boot_id, "streams": streams}),
                )

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()
