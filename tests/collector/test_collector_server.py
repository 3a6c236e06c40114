"""The collector in-process against real Zenoh sessions on loopback (a small publisher stands in
for an agent): runs, acks, rejects, dedupe, status, and the control queryables."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import yaml

from bgt_core import wire
from collector.client import CollectorClient
from collector.config import CollectorConfig
from collector.errors import CollectorError, CommandFailed, Unreachable
from collector.service import Collector
from collector_helpers import FakeAgent, expected_lines, make_batch, wait_for

A, B = "b827eb4521b4", "000000000101"


@pytest.fixture
def collector(tmp_path, endpoint):
    c = Collector(
        CollectorConfig(data_dir=tmp_path / "data", listen=(endpoint,), fsync_interval_s=0.1),
        drain_timeout_s=2.0,
    ).open()
    yield c
    c.close()


@pytest.fixture
def agent(endpoint, collector):
    a = FakeAgent(endpoint)
    yield a
    a.close()


@pytest.fixture
def client(endpoint, collector):
    with CollectorClient(endpoint) as c:
        yield c


def lines(run_dir, sensor) -> list[str]:
    return (Path(run_dir) / "rssi" / "pi-01" / f"{sensor}.mbd").read_text().splitlines()


def run_yaml(run_dir) -> dict:
    return yaml.safe_load((Path(run_dir) / "run.yaml").read_text())


def test_run_holds_exactly_the_published_rows(agent, client) -> None:
    started = client.start("walk 1")
    assert started["run_id"].endswith("-walk-1")
    batches = {
        A: [make_batch(i, sensor=A) for i in range(20)],
        B: [make_batch(i, sensor=B, first=1000 + 7 * i, n=7) for i in range(15)],
    }
    for i in range(20):
        for s in (A, B):
            if i < len(batches[s]):
                agent.put(batches[s][i])
    wait_for(lambda: agent.acked(A) == 19 and agent.acked(B) == 14, what="acks for both sensors")
    stopped = client.stop()
    assert stopped["run_dir"] == started["run_dir"]
    assert stopped["readings"] == 20 * 5 + 15 * 7
    for s in (A, B):
        assert lines(stopped["run_dir"], s) == expected_lines(batches[s])
    doc = run_yaml(stopped["run_dir"])
    assert doc["name"] == "walk 1"
    assert doc["stop"] is not None
    assert doc["readings"] == 205
    sensors = doc["agents"]["pi-01"]["sensors"]
    assert sensors[A]["readings"] == 100
    assert sensors[B]["readings"] == 105
    assert sensors[A]["gaps"] == 0
    assert doc["missing_batches"] == 0
    assert [r["run_id"] for r in client.runs()] == [started["run_id"]]


def _raw(sensor: str, rssis: list[int], seq: int = 99) -> bytes:
    meta = (
        f'{{"agent":"pi-01","boot":"0123456789abcdef","sensor":"{sensor}","seq":{seq}}}'
    ).encode()
    return (
        wire.BATCH_HEAD.pack(wire.MAGIC, 1, len(meta), len(rssis))
        + meta
        + b"".join(
            wire.BATCH_READING.pack(1_700_000_000 * 10**9 + i, 0, bytes(6), r)
            for i, r in enumerate(rssis)
        )
    )


def test_malformed_payloads_are_counted_never_written(agent, client, collector) -> None:
    client.start("bad")
    good = [make_batch(i, sensor=A) for i in range(3)]
    agent.put(good[0])
    agent.put_raw(A, b"short")  # truncated
    agent.put_raw(A, b"XXXX" + wire.to_wire(good[1])[4:])  # bad magic
    agent.put_raw(A, wire.to_wire(good[1])[:-5])  # truncated
    agent.put_raw(B, wire.to_wire(good[1]))  # sensor A's batch on B's key
    agent.put_raw(A, wire.to_wire(good[1]), agent="pi-02")  # another agent's key
    agent.put(good[1])
    agent.put(good[2])
    agent.put_raw(A, _raw(A, [-70, 42, -71, 99], seq=3))  # two impossible RSSIs of four
    wait_for(lambda: agent.acked(A) == 3, what="ack of the valid stream, bad readings and all")
    st = client.status()
    assert st["rejected_payloads"] == {
        "truncated": 2,
        "bad_magic": 1,
        "key_mismatch": 2,
        "bad_reading": 2,
    }
    stopped = client.stop()
    t0 = 1_700_000_000 * 10**9
    assert lines(stopped["run_dir"], A) == expected_lines(good) + [
        f"{wire.format_ts(t0)},{A},000000000000,-70",
        f"{wire.format_ts(t0 + 2)},{A},000000000000,-71",
    ]
    rssi = collector.cfg.data_dir / stopped["run_id"] / "rssi"
    assert sorted(str(p.relative_to(rssi)) for p in rssi.rglob("*.mbd")) == [f"pi-01/{A}.mbd"]
    doc = run_yaml(stopped["run_dir"])
    assert doc["rejected_payloads"]["key_mismatch"] == 2


def test_duplicates_dropped_and_gaps_filled(agent, client) -> None:
    client.start(None)
    b = [make_batch(i, sensor=A) for i in range(3)]
    for i in (0, 2, 1, 1, 0, 2):
        agent.put(b[i])
    wait_for(lambda: agent.acked(A) == 2, what="ack after the gap is filled")
    assert client.status()["duplicates_dropped"] == 3
    stopped = client.stop()
    # Rows are written in arrival order; each batch exactly once.
    assert lines(stopped["run_dir"], A) == expected_lines([b[0], b[2], b[1]])
    doc = run_yaml(stopped["run_dir"])
    assert doc["agents"]["pi-01"]["sensors"][A]["gaps"] == 1
    assert doc["missing_batches"] == 0
    assert doc["duplicates_dropped"] == 3


def test_gap_never_filled_is_reported_and_not_acked(agent, client) -> None:
    client.start("gap")
    agent.put(make_batch(0, sensor=A))
    agent.put(make_batch(2, sensor=A))
    wait_for(lambda: agent.acked(A) == 0, what="ack of seq 0")
    stopped = client.stop()  # waits for the gap up to drain_timeout_s, then gives up
    assert stopped["missing_batches"] == 1
    assert agent.acked(A) == 0
    assert len(lines(stopped["run_dir"], A)) == 10


def test_readings_without_a_run_are_acked_not_written(agent, client, collector) -> None:
    for i in range(4):
        agent.put(make_batch(i, sensor=A))
    wait_for(lambda: agent.acked(A) == 3, what="acks without a run")
    st = client.status()
    assert st["run"] is None
    assert st["discarded_no_run"] == 20
    sensor = st["agents"]["pi-01"]["sensors"][A]
    assert sensor["readings"] == 20
    assert sensor["last_rssi"] == make_batch(3, sensor=A).readings[-1].rssi
    assert sensor["rate_hz"] > 0
    assert sensor["last_seen_age_s"] >= 0
    run = client.start("after")
    agent.put(make_batch(4, sensor=A))
    wait_for(lambda: agent.acked(A) == 4, what="ack in the run")
    client.stop()
    assert lines(run["run_dir"], A) == expected_lines([make_batch(4, sensor=A)])


def test_acks_follow_the_agents_current_boot(agent, client) -> None:
    agent.put(make_batch(0, sensor=A, boot="aaaaaaaaaaaaaaaa"))
    agent.put(make_batch(0, sensor=A))  # FakeAgent's own boot id, seen last
    wait_for(lambda: agent.acked(A) == 0, what="ack")
    assert all(m["boot"] == agent.boot for m in agent.ack_msgs[-1:])


def test_control_errors(client) -> None:
    with pytest.raises(CommandFailed, match="stop: no run is active"):
        client.stop()
    run = client.start("one")
    with pytest.raises(CommandFailed, match=f"start: run {run['run_id']} is already active"):
        client.start("two")
    with pytest.raises(CommandFailed, match="start: name must be a string"):
        client.call("start", {"name": 5})
    client.stop()


def test_liveliness_shows_agents_alive_then_gone(agent, client) -> None:
    agent.declare_token()
    wait_for(lambda: client.status()["agents"].get("pi-01", {}).get("alive"), what="agent alive")
    agent.token.undeclare()
    agent.token = None
    wait_for(lambda: client.status()["agents"]["pi-01"]["alive"] is False, what="agent gone")


def test_agent_status_goes_into_run_yaml(agent, client) -> None:
    status = {
        "agent_id": "pi-01",
        "boot_id": agent.boot,
        "version": "9.9",
        "backend": "replay",
        "hostname": "pi-kitchen",
        "started_ns": 1,
        "now_ns": 2,
        "adapters": [
            {
                "name": "hci0",
                "mac": "B8:27:EB:45:21:B4",
                "backend": "replay",
                "mode": "passive",
                "adverts_per_s": 1.0,
                "last_advert_age_s": 0.1,
                "restarts": 0,
                "readings_total": 5,
            }
        ],
    }
    key = wire.agent_status_key("default", "pi-01")
    q = agent.session.declare_queryable(key, lambda query: query.reply(key, wire.to_json(status)))
    try:
        agent.declare_token()
        run = client.start("meta")
        agent.put(make_batch(0, sensor=A))
        wait_for(lambda: agent.acked(A) == 0, what="ack")
        # the status reply carries what the agent said of itself (the operator console shows it)
        live = wait_for(
            lambda: (a := client.status()["agents"].get("pi-01")) and a.get("version") and a,
            what="the agent's version in the status",
        )
        client.stop()
    finally:
        q.undeclare()
    assert (live["version"], live["backend"], live["hostname"]) == ("9.9", "replay", "pi-kitchen")
    assert live["adapters"] == ["hci0 B8:27:EB:45:21:B4 passive"]
    doc = run_yaml(run["run_dir"])
    a = doc["agents"]["pi-01"]
    assert (a["hostname"], a["version"], a["backend"], a["boot_ids"]) == (
        "pi-kitchen",
        "9.9",
        "replay",
        [agent.boot],
    )
    # readings per beacon over the run, and their rate (the run lasted well under a minute)
    beacons = a["sensors"][A].pop("beacons")
    assert list(beacons) == ["e78f135624ce"]
    assert beacons["e78f135624ce"]["readings"] == 5
    assert 5 / 60 < beacons["e78f135624ce"]["rate_hz"] < 5 / 0.01
    assert a["sensors"][A] == {
        "adapter": "hci0",
        "mac": A,
        "backend": "replay",
        "mode": "passive",
        "file": f"rssi/pi-01/{A}.mbd",
        "readings": 5,
        "batches": 1,
        "gaps": 0,
        "missing_batches": 0,
        "lost_batches": 0,
    }


def test_close_finalises_the_active_run(tmp_path, endpoint) -> None:
    c = Collector(
        CollectorConfig(data_dir=tmp_path, listen=(endpoint,), fsync_interval_s=0.1)
    ).open()
    a = FakeAgent(endpoint)
    try:
        run = c.start_run("shutdown")
        a.put(make_batch(0, sensor=A))
        wait_for(lambda: a.acked(A) == 0, what="ack")
    finally:
        a.close()
        c.close()
    doc = yaml.safe_load((tmp_path / run["run_id"] / "run.yaml").read_text())
    assert doc["stopped_by"] == "shutdown"
    assert doc["stop"] is not None
    assert doc["readings"] == 5
    assert lines(run["run_dir"], A) == expected_lines([make_batch(0, sensor=A)])


def test_concurrent_status_while_ingesting(agent, client) -> None:
    client.start("busy")
    stop = threading.Event()

    def pump() -> None:
        i = 0
        while not stop.is_set() and i < 400:
            agent.put(make_batch(i, sensor=A, n=50))
            i += 1

    t = threading.Thread(target=pump)
    t.start()
    for _ in range(5):
        assert client.status()["run"]["run_id"]
    t.join()
    wait_for(lambda: agent.acked(A) == 399, what="all acks")
    stopped = client.stop()
    assert stopped["readings"] == 400 * 50


def test_unreachable_collector_is_one_line(endpoint) -> None:
    with pytest.raises(Unreachable) as e, CollectorClient(endpoint, connect_timeout_s=0.5) as c:
        c.status()
    assert str(e.value) == f"no collector answered at {endpoint} (is `collector serve` running?)"


def test_acl_file_is_applied_or_rejected_in_one_line(tmp_path, endpoint) -> None:
    acl = tmp_path / "acl.json5"
    acl.write_text('{enabled: "maybe"}')
    cfg = CollectorConfig(data_dir=tmp_path, listen=(endpoint,), acl=acl)
    with pytest.raises(
        CollectorError,
        match=r"acl\.json5: not a valid zenoh access_control section: .*expected a boolean",
    ) as e:
        Collector(cfg).open()
    assert "\n" not in str(e.value)
    assert ".rs:" not in str(e.value)
    acl.write_text("{enabled: false}")
    Collector(cfg).open().close()
