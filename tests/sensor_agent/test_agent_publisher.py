"""The publisher on real Zenoh sessions over loopback: batching, sequence numbers, acks."""

from __future__ import annotations

import zenoh

from bgt_core import wire
from bgt_core.wire import Reading
from bgt_core.zenoh_config import SessionSpec, build_config
from polling import wait_for
from sensor_agent.publisher import Publisher

SENSOR = "b827eb4521b4"
T = 1_700_000_000 * 10**9


def make_reading(i: int) -> Reading:
    return Reading(T + i * 1000, "e78f135624ce", -60 - i, i + 1)


def test_batches_seqs_and_acks(endpoint: str) -> None:
    router = zenoh.open(build_config(SessionSpec(mode="router", listen=[endpoint])))
    sub = router.declare_subscriber(wire.data_selector("lab"))
    client = zenoh.open(build_config(SessionSpec(mode="client", connect=[endpoint])))
    pub = Publisher(
        client,
        site="lab",
        agent_id="pi-01",
        boot_id="00112233aabbccdd",
        wall_ns=lambda: T + 42,
        max_batch=4,
    )
    try:
        for i in range(3):
            pub.add(SENSOR, make_reading(i))
        assert pub.flush() == 1
        assert pub.flush() == 0  # nothing new: no empty batch
        for i in range(3, 9):  # 6 more with max_batch 4: one sent at once, two wait for flush
            pub.add(SENSOR, make_reading(i))
        assert pub.flush() == 1
        batches: list[wire.Batch] = []

        def drain() -> bool:
            while (s := sub.try_recv()) is not None:
                assert str(s.key_expr) == wire.data_key("lab", "pi-01", SENSOR)
                batches.append(wire.from_wire(s.payload.to_bytes()))
            return len(batches) == 3

        wait_for(drain)
        assert [b.seq for b in batches] == [0, 1, 2]
        assert [len(b.readings) for b in batches] == [3, 4, 2]
        assert [r for b in batches for r in b.readings] == [make_reading(i) for i in range(9)]
        assert {(b.agent_id, b.boot_id, b.sensor, b.sent_ns) for b in batches} == {
            ("pi-01", "00112233aabbccdd", SENSOR, T + 42)
        }
        assert pub.unacked() == {SENSOR: (2, -1)}

        ack = wire.ack_key("lab", "pi-01")
        router.put(ack, wire.to_json({"boot": "ffffffffffffffff", "streams": {SENSOR: 9}}))
        router.put(ack, b"not json")
        router.put(ack, wire.to_json({"boot": "00112233aabbccdd", "streams": {SENSOR: 1}}))
        wait_for(lambda: pub.acked() != {})
        # same sender, delivered in order: the foreign boot's ack came first and was ignored
        assert pub.acked() == {SENSOR: 1}
        assert pub.unacked() == {SENSOR: (2, 1)}
        router.put(ack, wire.to_json({"boot": "00112233aabbccdd", "streams": {SENSOR: 2}}))
        wait_for(lambda: pub.unacked() == {})
        assert pub.readings_sent(SENSOR) == 9
    finally:
        pub.close()
        client.close()
        sub.undeclare()
        router.close()
