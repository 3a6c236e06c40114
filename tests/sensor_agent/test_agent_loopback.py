"""A real `sensor-agent run` process (replay backend) against a bare Zenoh router session that
plays the collector: every row of the recording must arrive exactly once, timestamps exact."""

from __future__ import annotations

import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from agent_testing import AGENT, FakeCollector, agent_env
from bgt_core.formats.mbd import read_rows

pytestmark = pytest.mark.slow


def _run_agent(
    args: list[str],
    collector: FakeCollector,
    log: Path,
    timeout_s: float = 60,
    under: list[str] | None = None,
) -> tuple[int, str]:
    """Run the agent (``under`` a launcher that execs it) to its end while the collector polls;
    returns (exit code, stderr)."""
    with log.open("w") as f:
        cmd = [*(under or []), *AGENT, *args]
        proc = subprocess.Popen(cmd, stdout=f, stderr=f, env=agent_env())
        deadline = time.monotonic() + timeout_s
        while proc.poll() is None and time.monotonic() < deadline:
            collector.poll()
            time.sleep(0.005)
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
    collector.poll()
    return proc.returncode, log.read_text()


def _replay_files(
    endpoint: str, files: list[Path], log: Path, under: list[str] | None = None
) -> tuple[int, str, FakeCollector]:
    """Replay ``files`` (their own times, no pacing) through a real agent to a fake collector;
    returns the agent's exit code and output, and the collector (closed)."""
    collector = FakeCollector(endpoint, "lab")
    try:
        args = ["run", "--agent-id", "pi-07", "--site", "lab", "--connect", endpoint]
        args += ["--replay-keep-time", "--replay-speed", "0", "--ack-timeout", "20"]
        for f in files:
            args += ["--replay", str(f)]
        rc, stderr = _run_agent(args, collector, log, under=under)
    finally:
        collector.close()
    return rc, stderr, collector


def _delivered(collector: FakeCollector) -> Counter[tuple[int, str, str, int]]:
    return Counter(
        (r.t_ns, b.sensor, r.beacon, r.rssi) for b in collector.batches for r in b.readings
    )


def test_replay_delivers_every_row_exactly_once(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    files = sorted((dataset_dir / "trk" / "straight_01").glob("*.mbd"))
    expected = Counter((r.t_ns, r.sensor, r.beacon, r.rssi) for r in read_rows(files))
    rc, stderr, collector = _replay_files(endpoint, files, tmp_path / "agent.log")
    assert rc == 0, stderr
    assert _delivered(collector) == expected
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


# The agent unit sets MemoryDenyWriteExecute=yes. The kernel's own form of it (prctl
# PR_SET_MDWE, Linux >= 6.3, kept across exec) refuses the same mappings: writable memory made
# executable. Python's ctypes (the management socket's bind), libffi, Zenoh and bleak must
# all do without them.
PR_SET_MDWE, PR_GET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN = 65, 66, 1
UNDER_MDWE = [
    sys.executable,
    "-c",
    "import ctypes, os, sys\n"
    "libc = ctypes.CDLL(None, use_errno=True)\n"
    f"if libc.prctl({PR_SET_MDWE}, {PR_MDWE_REFUSE_EXEC_GAIN}, 0, 0, 0) != 0:\n"
    "    sys.exit('no PR_SET_MDWE: ' + os.strerror(ctypes.get_errno()))\n"
    "os.execv(sys.argv[1], sys.argv[1:])\n",
]


def test_the_agent_runs_with_write_execute_memory_refused(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    probe = subprocess.run(
        [
            *UNDER_MDWE,
            sys.executable,
            "-c",
            f"import ctypes; print(ctypes.CDLL(None).prctl({PR_GET_MDWE}, 0, 0, 0, 0))",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    if "no PR_SET_MDWE" in probe.stderr:
        pytest.skip(f"this kernel cannot refuse write-execute memory ({probe.stderr.strip()})")
    assert probe.stdout.strip() == str(PR_MDWE_REFUSE_EXEC_GAIN), probe.stdout + probe.stderr
    files = sorted((dataset_dir / "trk" / "straight_01").glob("*.mbd"))[:3]
    expected = Counter((r.t_ns, r.sensor, r.beacon, r.rssi) for r in read_rows(files))
    rc, stderr, collector = _replay_files(endpoint, files, tmp_path / "agent.log", UNDER_MDWE)
    assert rc == 0, stderr
    assert _delivered(collector) == expected
