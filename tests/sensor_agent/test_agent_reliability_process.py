"""Real `sensor-agent run` processes: a kill -9 and a restart re-send the previous boot's spooled
batches under their old boot id; the status reply carries the spool; systemd hears from it."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from agent_testing import AGENT, FakeCollector, agent_env
from bgt_core import wire
from polling import wait_for
from sensor_agent.spool import Spool

pytestmark = pytest.mark.slow

SITE = "lab"
AGENT_ID = "pi-09"


def write_config(tmp_path: Path, endpoint: str) -> Path:
    cfg = tmp_path / "agent.yaml"
    cfg.write_text(
        json.dumps(
            {  # JSON is YAML
                "agent_id": AGENT_ID,
                "site": SITE,
                "connect": [endpoint],
                "backend": "simulated",
                "batch_ms": 50,
                "spool": {"dir": "spool", "max_mb": 8},
                "simulated": {"sensors": [], "rate_hz": 5.0},
            }
        )
    )
    return cfg


def spooled(spool_dir: Path) -> dict[tuple[str, str, int], bytes]:
    """(boot, sensor, seq) -> payload of every unacknowledged record in the spool."""
    with Spool(spool_dir, 8 << 20) as sp:
        out = {}
        for sid, seq, payload in sp.pending():
            boot, _, sensor = sid.partition("/")
            out[(boot, sensor, seq)] = payload
        return out


def test_kill9_then_restart_resends_the_old_boot_once(endpoint: str, tmp_path: Path) -> None:
    cfg = write_config(tmp_path, endpoint)
    log1 = tmp_path / "agent1.log"
    # Boot 1: no router anywhere. The agent records into its spool and is killed hard.
    with log1.open("w") as f:
        p1 = subprocess.Popen(AGENT + ["run", "-c", str(cfg)], stdout=f, stderr=f, env=agent_env())
    try:
        wait_for(lambda: "scanning" in log1.read_text() or "adapter" in log1.read_text(), 30)
        wait_for(lambda: sum(1 for _ in (tmp_path / "spool").glob("*.seg")) > 0, 10)
        time.sleep(1.5)
    finally:
        p1.send_signal(signal.SIGKILL)
        p1.wait(10)
    assert "cannot reach the Zenoh router" in log1.read_text()
    before = spooled(tmp_path / "spool")
    assert len(before) >= 10
    (old_boot,) = {k[0] for k in before}

    # Boot 2 with a collector: the old boot's batches arrive, byte for byte, and are acknowledged.
    col = FakeCollector(endpoint, SITE)
    log2 = tmp_path / "agent2.log"
    with log2.open("w") as f:
        p2 = subprocess.Popen(AGENT + ["run", "-c", str(cfg)], stdout=f, stderr=f, env=agent_env())
    try:

        def old_arrived() -> bool:
            got = {(b.boot_id, b.sensor, b.seq) for b in col.batches if b.boot_id == old_boot}
            return got >= before.keys()

        wait_for(old_arrived, 40, poll=col.poll)
        old = [
            (b, p) for b, p in zip(col.batches, col.payloads, strict=True) if b.boot_id == old_boot
        ]
        for b, p in old:
            assert p == before[(b.boot_id, b.sensor, b.seq)]
        # and the new boot publishes its own streams meanwhile
        wait_for(lambda: len({b.boot_id for b in col.batches}) == 2, 20, poll=col.poll)
        new_boots = {b.boot_id for b in col.batches} - {old_boot}
        # the collector has acknowledged the old streams completely
        wait_for(
            lambda: all(
                col.watermark((AGENT_ID, old_boot, s)) >= max(q for bt, s2, q in before if s2 == s)
                for s in {k[1] for k in before}
            ),
            20,
            poll=col.poll,
        )

        # the status reply reports the spool
        replies = []

        def ask() -> bool:
            replies[:] = list(col.session.get(wire.agent_status_key(SITE, AGENT_ID), timeout=2.0))
            return bool(replies) and replies[0].ok is not None

        wait_for(ask, 20, poll=col.poll)
        status = wire.from_json(replies[0].ok.payload.to_bytes())
        assert status["boot_id"] in new_boots
        sp = status["spool"]
        assert {"bytes", "records", "dropped_oldest", "disk_full", "unspooled"} <= sp.keys()
        assert (sp["dropped_oldest"], sp["disk_full"], sp["unspooled"]) == (0, False, 0)
        assert all("power_cycles" in a for a in status["adapters"])
        time.sleep(1.0)  # let the last acks reach the agent before it stops
        col.poll()
    finally:
        p2.send_signal(signal.SIGTERM)
        try:
            rc = p2.wait(20)
        finally:
            col.close()
    assert rc == 0, log2.read_text()
    left = spooled(tmp_path / "spool")
    assert not [k for k in left if k[0] == old_boot]
    # each old batch was published once on restart (a re-send after 5 s of silence is allowed)
    assert len({(b.sensor, b.seq) for b, _ in old}) == len(before)


def test_sd_notify_ready_watchdog_stopping(
    endpoint: str, dataset_dir: Path, tmp_path: Path
) -> None:
    sock_path = tmp_path / "notify.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    server.bind(str(sock_path))
    server.settimeout(0.2)
    f = dataset_dir / "trk" / "straight_01" / "sensor10_0.00_0.00_0.00.mbd"
    env = {**agent_env(), "NOTIFY_SOCKET": str(sock_path), "WATCHDOG_USEC": "200000"}
    env.pop("WATCHDOG_PID", None)
    col = FakeCollector(endpoint, "default")
    messages: list[str] = []
    try:
        proc = subprocess.Popen(
            AGENT
            + [
                "run",
                "--connect",
                endpoint,
                "--replay",
                str(f),
                "--replay-speed",
                "0",
                "--ack-timeout",
                "20",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
        )
        deadline = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < deadline:
            col.poll()
            try:
                messages.append(server.recv(4096).decode())
            except TimeoutError:
                pass
        proc.wait(10)
        while True:
            try:
                messages.append(server.recv(4096).decode())
            except (TimeoutError, BlockingIOError):
                break
    finally:
        col.close()
        server.close()
        os.unlink(sock_path)
    assert proc.returncode == 0, proc.stderr.read().decode()
    proc.stderr.close()
    fields = [line for m in messages for line in m.splitlines()]
    assert "READY=1" in fields
    assert "WATCHDOG=1" in fields
    assert "STOPPING=1" in fields
    assert fields.index("READY=1") < fields.index("STOPPING=1")
    assert any(x.startswith("STATUS=") and "readings" in x for x in fields)
