"""Issue 5, collector side, with real failures: `kill -9` of a `collector serve` process mid-run
and a restart on the same data directory; a really full file system (a small tmpfs, when this
machine lets the tests mount one)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
import yaml

from collector.client import CollectorClient
from collector.config import CollectorConfig
from collector.errors import CollectorError
from collector.service import Collector
from collector.store import STATE_FILE
from collector_helpers import (
    FakeAgent,
    expected_lines,
    make_batch,
    resend_until_acked,
    wait_for,
    with_floor,
)

A = "b827eb4521b4"


def _reachable(endpoint: str) -> bool:
    try:
        with CollectorClient(endpoint, connect_timeout_s=0.5) as c:
            c.status()
    except CollectorError:
        return False
    return True


def _serve(cfg: Path) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "collector.cli", "serve", "--config", str(cfg)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_kill_9_mid_run_then_restart_loses_and_duplicates_nothing(tmp_path, endpoint) -> None:
    cfg = tmp_path / "collector.yaml"
    cfg.write_text(f"data_dir: data\nlisten: [{endpoint}]\nfsync_interval_s: 0.2\n")
    sent = [with_floor(make_batch(i, sensor=A), 0) for i in range(60)]
    proc = _serve(cfg)
    agent = None
    try:
        wait_for(lambda: proc.poll() is not None or _reachable(endpoint), 30, "collector serve")
        assert proc.poll() is None, proc.stderr.read()
        agent = FakeAgent(endpoint)
        with CollectorClient(endpoint) as c:
            run = c.start("kill9")
        for b in sent[:30]:
            agent.put(b)
        wait_for(lambda: agent.acked(A) >= 10, what="some acks before the kill")
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=10)
        state = json.loads((Path(run["run_dir"]) / STATE_FILE).read_text())
        assert state["active"] is True
        assert yaml.safe_load((Path(run["run_dir"]) / "run.yaml").read_text())["stop"] is None
        proc = _serve(cfg)
        wait_for(lambda: proc.poll() is not None or _reachable(endpoint), 30, "restarted collector")
        assert proc.poll() is None, proc.stderr.read()
        resend_until_acked(agent, sent)  # what the agent's spool does after an outage
        with CollectorClient(endpoint) as c:
            assert c.status()["run"]["run_id"] == run["run_id"]
            stopped = c.stop()
    finally:
        if agent is not None:
            agent.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert stopped["run_id"] == run["run_id"]
    got = (Path(run["run_dir"]) / "rssi" / "pi-01" / f"{A}.mbd").read_text().splitlines()
    assert len(got) == len(expected_lines(sent))  # nothing twice
    assert sorted(got) == sorted(expected_lines(sent))  # nothing missing
    doc = yaml.safe_load((Path(run["run_dir"]) / "run.yaml").read_text())
    assert (doc["restarts"], doc["readings"], doc["missing_batches"]) == (1, 300, 0)


@pytest.fixture
def small_fs(tmp_path):
    """A 256 KiB tmpfs mounted for this test only (needs root); skipped where mounting is refused."""
    mnt = tmp_path / f"fs-{uuid.uuid4().hex[:8]}"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)],
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(path: Path) -> None:
    with path.open("wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError:
            pass


def test_really_full_disk_stops_cleanly_and_resumes(small_fs, endpoint) -> None:
    c = Collector(
        CollectorConfig(data_dir=small_fs / "data", listen=(endpoint,), fsync_interval_s=0.1),
        drain_timeout_s=2.0,
    ).open()
    agent = FakeAgent(endpoint)
    try:
        run = c.start_run("tmpfs")
        sent = [with_floor(make_batch(i, sensor=A, n=20), 0) for i in range(60)]
        for b in sent[:5]:
            agent.put(b)
        wait_for(lambda: agent.acked(A) == 4, what="acks while there is space")
        _fill(small_fs / "filler")
        for b in sent[5:]:
            agent.put(b)
        wait_for(lambda: c.status()["disk_full"], what="disk_full in status")
        stuck = agent.acked(A)
        mbd = Path(run["run_dir"]) / "rssi" / "pi-01" / f"{A}.mbd"
        on_disk = mbd.read_text()
        assert on_disk.endswith("\n")  # no torn line, even though the fs took part of a write
        assert on_disk.splitlines() == expected_lines(sent)[: len(on_disk.splitlines())]
        state = json.loads((Path(run["run_dir"]) / STATE_FILE).read_text())
        assert state["files"][f"pi-01/{A}"] <= len(on_disk)
        assert not list(Path(run["run_dir"]).glob("*.tmp"))  # failed state writes left nothing
        assert stuck < 59
        (small_fs / "filler").unlink()
        resend_until_acked(agent, sent)
        assert not c.status()["disk_full"]
        stopped = c.stop_run()
    finally:
        agent.close()
        c.close()
    got = (Path(run["run_dir"]) / "rssi" / "pi-01" / f"{A}.mbd").read_text().splitlines()
    assert len(got) == 60 * 20
    assert sorted(got) == sorted(expected_lines(sent))
    assert stopped["readings"] == 1200
