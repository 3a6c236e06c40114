"""Issue 11: one authenticated agent that misbehaves (floods MACs, absurd seqs, oversized
messages) must not hurt the others. Bounded collector resources, on loopback Zenoh."""

from __future__ import annotations

import json
import resource
import signal
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
import zenoh
from collector_helpers import FakeAgent, expected_lines, make_batch, run_yaml_doc, wait_for

from ble_groundtruth import wire
from collector.client import CollectorClient
from collector.config import CollectorConfig, Limits
from collector.errors import CollectorError
from collector.inbox import ByteQueue
from collector.ingest import StreamTracker
from collector.service import Collector
from collector.store import RunWriter

A, B = "b827eb4521b4", "000000000101"


def with_floor(batch: wire.Batch, floor: int) -> wire.Batch:
    return wire.Batch(batch.agent_id, batch.boot_id, batch.sensor, batch.seq, batch.readings,
                      batch.sent_ns, floor)


def flood_macs(n: int) -> list[str]:
    return [f"ff{i:010x}" for i in range(n)]


# -- pure parts ---------------------------------------------------------------------------------


def test_byte_queue_bounds_bytes_not_items() -> None:
    q = ByteQueue(100)
    assert q.put("a", 60, timeout=0)
    assert not q.put("b", 60, timeout=0.05)  # 120 > 100: no room
    assert q.put("c", 40, timeout=0)
    assert (q.qsize(), q.bytes) == (2, 100)
    assert q.get(timeout=0) == "a"
    assert q.get(timeout=0) == "c"
    assert q.get(timeout=0) is None
    assert q.bytes == 0
    assert q.put("huge", 10_000, timeout=0)  # alone, even an item over the bound passes


def test_run_writer_keeps_at_most_open_files_descriptors(tmp_path) -> None:
    w = RunWriter(tmp_path, "r", "r", 1_795_318_500 * 10**9, {}, open_files=3)
    batches = {}
    for round_ in range(3):
        for i in range(10):
            mac = f"aa{i:010x}"
            b = make_batch(round_, n=2, sensor=mac)
            batches.setdefault(mac, []).append(b)
            w.append("pi-01", mac, "\n".join(expected_lines([b])) + "\n", 2)
            w.flush()
            assert w.open_count <= 3
    w.fsync()
    assert w.open_count <= 3
    w.close()
    for mac, bs in batches.items():
        assert (w.dir / "rssi" / "pi-01" / f"{mac}.mbd").read_text().splitlines() == expected_lines(bs)


def test_tracker_gives_up_a_gap_only_past_max_ahead() -> None:
    t = StreamTracker(max_ahead=4)
    s = ("pi-01", "0123456789abcdef", A)
    assert t.accept(s, 0, floor=0)
    for seq in range(2, 6):  # seq 1 missing, four waiting above it: still within the bound
        assert t.accept(s, seq, floor=0)
    assert (t.streams[s].done_upto, t.missing(s)) == (0, 1)
    assert t.accept(s, 6, floor=0)  # the fifth: seq 1 is given up and counted lost
    st = t.streams[s]
    assert (st.done_upto, st.ahead, st.lost, t.given_up) == (6, set(), 1, 1)


def test_tracker_keeps_a_bounded_number_of_boots_per_stream() -> None:
    t = StreamTracker(max_boots=3)
    for i in range(10):
        boot = f"{i:016x}"
        assert t.accept(("pi-01", boot, A), 0, floor=0)
        assert t.accept(("pi-01", boot, A), 2, floor=0)  # a gap: seq 1 missing
        t.mark_durable()
    assert len(t.streams) == 3
    totals = t.stream_totals()[("pi-01", A)]
    assert totals.gaps == 10
    assert (totals.missing, totals.lost) == (3, 7)  # retired boots' missing seqs count as lost
    assert totals.boots == [f"{i:016x}" for i in (7, 8, 9)]


def test_limits_in_the_config_file(tmp_path) -> None:
    from collector.config import load_config
    from collector.errors import ConfigError

    f = tmp_path / "c.yaml"
    f.write_text("limits: {streams_per_agent: 8, queue_mb: 16}\n")
    assert load_config(f).limits == Limits(streams_per_agent=8, queue_mb=16.0)
    f.write_text("limits: {open_files: 0}\n")
    with pytest.raises(ConfigError, match=r"limits\.open_files must be an integer in \[1, 65536\], got 0"):
        load_config(f)
    f.write_text("limits: {fds: 3}\n")
    with pytest.raises(ConfigError, match=r"unknown key limits\.fds"):
        load_config(f)


# -- in-process collector, loopback Zenoh ------------------------------------------------------


@pytest.fixture
def collector(tmp_path, endpoint):
    c = Collector(CollectorConfig(data_dir=tmp_path / "data", listen=(endpoint,), fsync_interval_s=0.1,
                                  limits=Limits(streams_per_agent=4, streams_total=5)),
                  drain_timeout_s=2.0).open()
    yield c
    c.close()


def test_absurd_seq_is_refused_and_never_reaches_run_yaml(collector, endpoint) -> None:
    a = FakeAgent(endpoint)
    try:
        run = collector.start_run("seq")
        a.put(with_floor(make_batch(0, sensor=A), 0))
        bad = wire.Batch("pi-01", a.boot, A, 2**63 - 1, make_batch(1, sensor=A).readings, floor=2**63 - 1)
        a.put(bad)
        a.put(with_floor(make_batch(1, sensor=A), 0))
        wait_for(lambda: a.acked(A) == 1, what="acks of the honest seqs")
        wait_for(lambda: collector.status()["rejected_payloads"].get("seq_out_of_range") == 1,
                 what="the absurd seq counted")
        collector.stop_run()
    finally:
        a.close()
    doc = run_yaml_doc(run["run_dir"])
    assert doc["lost_batches"] == 0
    assert doc["missing_batches"] == 0
    assert doc["agents"]["pi-01"]["sensors"][A]["readings"] == 10


def test_streams_over_the_caps_are_refused_counted_and_reported(collector, endpoint) -> None:
    flooder = FakeAgent(endpoint, agent="pi-bad")
    honest = FakeAgent(endpoint, agent="pi-01")
    try:
        run = collector.start_run("caps")
        honest.put(with_floor(make_batch(0, agent="pi-01", sensor=A), 0))
        wait_for(lambda: honest.acked(A) == 0, what="honest ack")
        for mac in flood_macs(10):
            flooder.put(with_floor(make_batch(0, agent="pi-bad", sensor=mac), 0))
        wait_for(lambda: collector.status()["refused_streams"]["batches"] == 6, what="6 refused")
        honest.put(with_floor(make_batch(1, agent="pi-01", sensor=A), 0))
        honest.put(with_floor(make_batch(0, agent="pi-01", sensor=B), 0))  # total cap (5) reached
        wait_for(lambda: honest.acked(A) == 1, what="honest ack after the flood")
        wait_for(lambda: collector.status()["refused_streams"]["batches"] == 7, what="7 refused")
        st = collector.status()
        stopped = collector.stop_run()
    finally:
        flooder.close()
        honest.close()
    assert st["refused_streams"] == {"batches": 7, "streams": 7, "by_agent": {"pi-bad": 6, "pi-01": 1}}
    assert st["streams"]["admitted"] == 5
    doc = run_yaml_doc(stopped["run_dir"])
    assert doc["refused_streams"]["batches"] == 7
    assert len(doc["agents"]["pi-bad"]["sensors"]) == 4  # streams_per_agent
    rssi = Path(run["run_dir"]) / "rssi"
    assert len(list((rssi / "pi-bad").glob("*.mbd"))) == 4
    assert (rssi / "pi-01" / f"{A}.mbd").read_text().splitlines() == expected_lines(
        [make_batch(0, agent="pi-01", sensor=A), make_batch(1, agent="pi-01", sensor=A)])


def test_oversized_message_is_refused_before_it_reaches_the_collector(collector, endpoint) -> None:
    a = FakeAgent(endpoint)
    try:
        a.put(with_floor(make_batch(0, sensor=A), 0))
        wait_for(lambda: a.acked(A) == 0, what="first ack")
        a.put_raw(A, b"\0" * (8 * 1024 * 1024))  # twice the protocol's limit
        # The session drops the message (Zenoh's max_message_size); honest data goes on.
        a2 = FakeAgent(endpoint, agent="pi-02")
        try:
            a2.put(with_floor(make_batch(0, agent="pi-02", sensor=B), 0))
            wait_for(lambda: a2.acked(B) == 0, what="ack of another agent after the big message")
        finally:
            a2.close()
        st = collector.status()
        assert "oversized" not in st["rejected_payloads"]  # never reassembled, never decoded
    finally:
        a.close()


# -- a separate `collector serve` process under a low descriptor limit ------------------------------


def _reachable(endpoint: str) -> bool:
    try:
        with CollectorClient(endpoint, connect_timeout_s=0.5) as c:
            c.status()
    except CollectorError:
        return False
    return True


def _low_nofile() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))


@pytest.mark.slow
def test_1100_macs_under_a_low_descriptor_limit_honest_agents_complete_and_stop_works(
        tmp_path, endpoint) -> None:
    cfg = tmp_path / "collector.yaml"
    # Room for 1,000 streams of one agent while only 128 files may be open (half of 256).
    cfg.write_text(f"data_dir: data\nlisten: [{endpoint}]\nfsync_interval_s: 0.2\n"
                   "limits: {streams_per_agent: 1000, streams_total: 1100}\n")
    proc = subprocess.Popen([sys.executable, "-m", "collector.cli", "serve", "--config", str(cfg)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_low_nofile)
    agents: list[FakeAgent] = []
    try:
        wait_for(lambda: proc.poll() is not None or _reachable(endpoint), 30, "collector serve")
        assert proc.poll() is None, proc.stderr.read()
        h1, h2, bad = (FakeAgent(endpoint, agent=n) for n in ("pi-01", "pi-02", "pi-bad"))
        agents += [h1, h2, bad]
        with CollectorClient(endpoint) as c:
            c.start("nofile")
            honest = {h: [with_floor(make_batch(i, agent=h.agent, sensor=A), 0) for i in range(30)]
                      for h in (h1, h2)}
            for i in range(10):
                for h in (h1, h2):
                    h.put(honest[h][i])
            for mac in flood_macs(1100):
                bad.put(with_floor(make_batch(0, agent="pi-bad", sensor=mac, n=2), 0))
            for i in range(10, 30):
                for h in (h1, h2):
                    h.put(honest[h][i])
            wait_for(lambda: h1.acked(A) == 29 and h2.acked(A) == 29, 60, "honest acks after the flood")
            wait_for(lambda: bad.acked("ff00000003e7") == 0, 60, "the flood's admitted streams acked")
            status = c.status()
            reply = json.dumps({"ok": True, **status}).encode()
            stopped = c.stop()
    finally:
        for a in agents:
            a.close()
        proc.send_signal(signal.SIGINT)
        try:
            _out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 0, err
    assert len(reply) < 256 * 1024  # summarised, far below Zenoh's and our 1 MiB JSON limit
    assert status["streams"]["shown"] <= 200
    assert status["refused_streams"]["batches"] == 100
    assert status["streams"]["open_files"] <= 128
    run_dir = Path(stopped["run_dir"])
    for h in (h1, h2):
        got = (run_dir / "rssi" / h.agent / f"{A}.mbd").read_text().splitlines()
        assert got == expected_lines(honest[h])  # 0 lost, 0 duplicated, in order
    assert len(list((run_dir / "rssi" / "pi-bad").glob("*.mbd"))) == 1000
    doc = run_yaml_doc(run_dir)
    assert doc["refused_streams"]["batches"] == 100
    assert doc["readings"] == 2 * 30 * 5 + 1000 * 2
    assert "Traceback" not in err


def test_a_zenoh_session_refuses_messages_over_the_limit() -> None:
    from ble_groundtruth.zenoh_config import MAX_MESSAGE_BYTES, SessionSpec, build_config

    conf = build_config(SessionSpec(mode="client"))
    assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == MAX_MESSAGE_BYTES
    assert MAX_MESSAGE_BYTES == wire.MAX_PAYLOAD_BYTES + 64 * 1024
    assert isinstance(conf, zenoh.Config)


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


@pytest.mark.slow
def test_max_size_flood_keeps_collector_memory_bounded_and_honest_data_complete(tmp_path, endpoint) -> None:
    """Maximum-size batches (100,000 readings) as fast as the collector takes them: its RSS
    stays under the documented 512 MiB and an honest agent's stream arrives complete.
    (bench/collector_floods.py runs the 20 s version and prints the figures.)"""
    import threading
    import time

    cfg = tmp_path / "collector.yaml"
    cfg.write_text(f"data_dir: data\nlisten: [{endpoint}]\nfsync_interval_s: 0.5\n")
    proc = subprocess.Popen([sys.executable, "-m", "collector.cli", "serve", "--config", str(cfg)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    peak = [0]
    done = threading.Event()

    def sample() -> None:
        while not done.wait(0.05):
            try:
                peak[0] = max(peak[0], _rss_kb(proc.pid))
            except OSError:
                return

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    honest = bad = None
    try:
        wait_for(lambda: proc.poll() is not None or _reachable(endpoint), 30, "collector serve")
        assert proc.poll() is None, proc.stderr.read()
        honest, bad = FakeAgent(endpoint, agent="pi-01"), FakeAgent(endpoint, agent="pi-bad")
        with CollectorClient(endpoint) as c:
            run = c.start("maxsize")
        rows = tuple(wire.Reading(1_700_000_000 * 10**9 + k, "e78f135624ce", -60)
                     for k in range(wire.MAX_READINGS))

        def flood() -> None:
            end, seq = time.monotonic() + 6.0, 0
            while time.monotonic() < end:
                payload = wire.to_wire(wire.Batch("pi-bad", bad.boot, "ff0000000000", seq, rows, floor=0))
                bad.session.put(wire.data_key("default", "pi-bad", "ff0000000000"), payload,
                                congestion_control=zenoh.CongestionControl.BLOCK)
                seq += 1

        flooder = threading.Thread(target=flood)
        flooder.start()
        sent = [with_floor(make_batch(i, agent="pi-01", sensor=A), 0) for i in range(30)]
        for b in sent:
            honest.put(b)
            time.sleep(0.15)
        flooder.join()
        end = time.monotonic() + 60
        while honest.acked(A) < 29:  # what a real agent's spool does: re-send the unacknowledged
            assert time.monotonic() < end, f"honest acks stuck at {honest.acked(A)}"
            for b in sent[honest.acked(A) + 1:]:
                honest.put(b)
            time.sleep(0.5)
        with CollectorClient(endpoint) as c:
            c.stop()
    finally:
        for a in (honest, bad):
            if a is not None:
                a.close()
        done.set()
        proc.send_signal(signal.SIGINT)
        try:
            _out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 0, err
    assert 0 < peak[0] < 512 * 1024, f"collector RSS peaked at {peak[0] / 1024:.0f} MiB"
    got = (Path(run["run_dir"]) / "rssi" / "pi-01" / f"{A}.mbd").read_text().splitlines()
    # 0 lost, 0 duplicated (a re-sent batch may land after later ones)
    assert Counter(got) == Counter(expected_lines(sent))
