"""Builders and a small real-Zenoh publisher for the collector tests (stand-in for an agent)."""

from __future__ import annotations

import json
import threading
import time

import zenoh

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, TlsFiles, build_config
from polling import wait_for  # noqa: F401 - the collector tests import it from here

T0 = 1_700_000_000_123_456_789


def make_reading(i: int = 0, **kw) -> wire.Reading:
    args = {
        "t_ns": T0 + i * 1_000_003,
        "beacon": "e78f135624ce",
        "rssi": -40 - i % 60,
        "mono_ns": 0,
    }
    args.update(kw)
    return wire.Reading(**args)


def make_batch(
    seq: int,
    n: int = 5,
    *,
    agent: str = "pi-01",
    boot: str = "0123456789abcdef",
    sensor: str = "b827eb4521b4",
    first: int | None = None,
) -> wire.Batch:
    first = seq * n if first is None else first
    return wire.Batch(agent, boot, sensor, seq, tuple(make_reading(first + j) for j in range(n)))


def with_floor(batch: wire.Batch, floor: int) -> wire.Batch:
    return wire.Batch(
        batch.agent_id, batch.boot_id, batch.sensor, batch.seq, batch.readings, batch.sent_ns, floor
    )


def expected_lines(batches: list[wire.Batch]) -> list[str]:
    return [
        f"{wire.format_ts(r.t_ns)},{b.sensor},{r.beacon},{r.rssi}"
        for b in batches
        for r in b.readings
    ]


def run_yaml_doc(run_dir) -> dict:
    from pathlib import Path

    import yaml

    return yaml.safe_load((Path(run_dir) / "run.yaml").read_text(encoding="utf-8"))


class FakeAgent:
    """Publishes batches on the data keys and records the acks it is sent, like a real agent."""

    def __init__(
        self,
        endpoint: str,
        agent: str = "pi-01",
        site: str = "default",
        boot: str = "0123456789abcdef",
        tls: TlsFiles | None = None,
    ) -> None:
        self.agent, self.site, self.boot = agent, site, boot
        self.session = zenoh.open(
            build_config(SessionSpec(mode="client", connect=[endpoint], tls=tls))
        )
        self.acks: dict[str, int] = {}
        self.boot_acks: dict[str, dict[str, int]] = {}  # every boot's acks (contract 2)
        self.ack_msgs: list[dict] = []
        self.refusals: dict[str, dict] = {}  # sensor -> the latest negative acknowledgement
        self._lock = threading.Lock()
        self._ack_sub = self.session.declare_subscriber(wire.ack_key(site, agent), self._on_ack)
        self.token = None

    def _on_ack(self, sample: zenoh.Sample) -> None:
        msg = json.loads(sample.payload.to_bytes())
        with self._lock:
            self.ack_msgs.append(msg)
            self.boot_acks.setdefault(msg["boot"], {}).update(msg["streams"])
            if msg["boot"] == self.boot:
                self.acks.update(msg["streams"])
                self.refusals.update(msg.get("refused", {}))

    def refused(self) -> dict[str, dict]:
        with self._lock:
            return dict(self.refusals)

    def acked(self, sensor: str) -> int:
        with self._lock:
            return self.acks.get(sensor, -1)

    def acked_boot(self, boot: str, sensor: str) -> int:
        with self._lock:
            return self.boot_acks.get(boot, {}).get(sensor, -1)

    def serve_clock(self, offset_ns: int = 0, chrony: dict | None = None) -> None:
        """Answer the collector's clock exchange like an agent whose clock is `offset_ns` ahead."""
        key = wire.agent_clock_key(self.site, self.agent)

        def on_query(q: zenoh.Query) -> None:
            t2 = time.time_ns() + offset_ns
            t1 = json.loads(q.payload.to_bytes())["t1"]
            reply = {"t1": t1, "t2": t2, "t3": time.time_ns() + offset_ns, "chrony": chrony}
            q.reply(key, wire.to_json(reply))

        self._clock_q = self.session.declare_queryable(key, on_query)

    def declare_token(self) -> None:
        self.token = self.session.liveliness().declare_token(
            wire.agent_token_key(self.site, self.agent)
        )

    def put(self, batch: wire.Batch) -> None:
        self.session.put(
            wire.data_key(self.site, batch.agent_id, batch.sensor), wire.to_wire(batch)
        )

    def put_raw(self, sensor: str, payload: bytes, agent: str | None = None) -> None:
        self.session.put(wire.data_key(self.site, agent or self.agent, sensor), payload)

    def close(self) -> None:
        if self.token is not None:
            self.token.undeclare()
        self._ack_sub.undeclare()
        if getattr(self, "_clock_q", None) is not None:
            self._clock_q.undeclare()
        self.session.close()


def resend_until_acked(ag: FakeAgent, batches: list[wire.Batch], timeout: float = 30.0) -> None:
    """What an agent's spool does: re-send every unacknowledged batch now and then until all
    are acknowledged (its session reconnects to a restarted router on its own, after a while)."""
    sensor, last = batches[0].sensor, batches[-1].seq
    end = time.monotonic() + timeout
    while ag.acked(sensor) < last:
        assert time.monotonic() < end, f"acks stuck at {ag.acked(sensor)} of {last}"
        acked = ag.acked(sensor)
        for b in batches:
            if b.seq > acked:
                ag.put(b)
        try:
            wait_for(lambda: ag.acked(sensor) == last, timeout=1.0)
        except AssertionError:
            pass
