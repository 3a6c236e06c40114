"""A real `sensor-agent run` process (replay backend) against a bare Zenoh router session that
plays the collector: every row of the recording must arrive exactly once, timestamps exact."""

from __future__ import annotations

import subprocess
import time
from collections import Counter
from pathlib import Path

import pytest

from agent_testing import AGENT, FakeCollector, agent_env
from bgt_core.formats.mbd import read_rows

pytestmark = pytest.mark.slow


def _run_agent(
    args: list[str], collector: FakeCollector, log: Path, timeout_s: float = 60
) -> tuple[int, str]:
    """Run the agent to its end while the collector polls; returns (exit code, stderr)."""
    with log.open("w") as f:
        proc = subprocess.Popen(AGENT + args, stdout=f, stderr=f, env=agent_env())
        deadline = time.monotonic() + timeout_s
        while proc.poll() is None and time.monotonic() < deadline:
            collector.poll()
            time.sleep(0.005)
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
    collector.poll()
    return proc.returncode, log.read_text()


def test_replay_delivers_every_row_exactly_once(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    files = sorted((dataset_dir / "trk" / "straight_01").glob("*.mbd"))
    expected = Counter((r.t_ns, r.sensor, r.beacon, r.rssi) for r in read_rows(files))
    collector = FakeCollector(endpoint, "lab")
    try:
        args = [
            "run",
            "--agent-id",
            "pi-07",
            "--site",
            "lab",
            "--connect",
            endpoint,
            "--replay-keep-time",
            "--replay-speed",
            "0",
            "--ack-timeout",
            "20",
        ]
        for f in files:
            args += ["--replay", str(f)]
        rc, stderr = _run_agent(args, collector, tmp_path / "agent.log")
    finally:
        collector.close()
    assert rc == 0, stderr
    got = Counter(
        (r.t_ns, b.sensor, r.beacon, r.rssi) for b in collector.batches for r in b.readings
    )
    assert got == expected
    assert sum(expected.values()) == 1365
    # One boot, twelve streams, each numbered 0..n-1 without gaps or repeats.
    assert {b.agent_id for b in collector.batches} == {"pi-07"}
    assert len({b.boot_id for b in collector.batches}) == 1
    per_stream: dict[str, list[int]] = {}
    for b in collector.batches:
        per_stream.setdefault(b.sensor, []).append(b.seq)
    assert len(per_stream) == 12
    for seqs in per_stream.values():
        assert sorted(seqs) == list(range(len(seqs)))


def test_replay_without_acks_exits_1_with_one_line(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    f = dataset_dir / "trk" / "straight_01" / "sensor10_0.00_0.00_0.00.mbd"
    collector = FakeCollector(endpoint, "default", ack=False)
    try:
        rc, stderr = _run_agent(
            [
                "run",
                "--connect",
                endpoint,
                "--replay",
                str(f),
                "--replay-speed",
                "0",
                "--ack-timeout",
                "1",
            ],
            collector,
            tmp_path / "agent.log",
        )
    finally:
        collector.close()
    assert rc == 1, stderr
    assert "did not acknowledge" in stderr
    assert "Traceback" not in stderr
    assert sum(len(b.readings) for b in collector.batches) == 113


def test_no_wait_ack_exits_0_without_collector_acks(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    f = dataset_dir / "trk" / "straight_01" / "sensor11_0.00_0.00_0.00.mbd"
    collector = FakeCollector(endpoint, "default", ack=False)
    try:
        rc, stderr = _run_agent(
            [
                "run",
                "--connect",
                endpoint,
                "--replay",
                str(f),
                "--replay-speed",
                "0",
                "--no-wait-ack",
            ],
            collector,
            tmp_path / "agent.log",
        )
    finally:
        collector.close()
    assert rc == 0, stderr
    assert sum(len(b.readings) for b in collector.batches) == 118


def test_unreachable_router_keeps_recording_then_one_line(
    dataset_dir: Path, tmp_path: Path
) -> None:
    """No router at all: the agent still starts and records (it would publish once the router
    comes); a replay then ends with the bounded ack wait and one line, not a traceback."""
    from loopback import free_port

    f = dataset_dir / "trk" / "straight_01" / "sensor10_0.00_0.00_0.00.mbd"
    log = tmp_path / "agent.log"
    with log.open("w") as out:
        rc = subprocess.run(
            AGENT
            + [
                "run",
                "--connect",
                f"tcp/127.0.0.1:{free_port()}",
                "--replay",
                str(f),
                "--replay-speed",
                "0",
                "--ack-timeout",
                "1",
            ],
            stdout=out,
            stderr=out,
            env=agent_env(),
            timeout=60,
        ).returncode
    text = log.read_text()
    assert rc == 1
    assert "cannot reach the Zenoh router at tcp/127.0.0.1:" in text
    assert "did not acknowledge 1 batch(es) of 1 stream(s)" in text
    assert "no acknowledgement at all" in text
    assert "Traceback" not in text


def test_replay_of_a_track_with_an_absurd_rssi_delivers_every_other_reading(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    """trk/straight_05 as published holds a +42 dBm (and a +29 dBm) reading: they are skipped,
    counted and reported; every other reading arrives and the replay exits 0."""
    f = dataset_dir / "trk" / "straight_05" / "sensor30_0.00_0.00_0.00.mbd"
    rows = list(read_rows([f]))
    expected = Counter((r.t_ns, r.sensor, r.beacon, r.rssi) for r in rows if r.rssi <= 20)
    assert len(rows) - sum(expected.values()) == 2
    collector = FakeCollector(endpoint, "default")
    try:
        rc, stderr = _run_agent(
            [
                "run",
                "--connect",
                endpoint,
                "--replay",
                str(f),
                "--replay-speed",
                "0",
                "--replay-keep-time",
                "--ack-timeout",
                "20",
            ],
            collector,
            tmp_path / "agent.log",
        )
    finally:
        collector.close()
    assert rc == 0, stderr
    got = Counter(
        (r.t_ns, b.sensor, r.beacon, r.rssi) for b in collector.batches for r in b.readings
    )
    assert got == expected
    assert "skipped 2 implausible reading(s)" in stderr
    assert "Traceback" not in stderr
