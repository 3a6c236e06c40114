"""A real `sensor-agent run` on the simulated backend: status queryable, liveliness token,
continuous batches, and a clean SIGTERM stop that flushes what it has."""

from __future__ import annotations

import signal
import subprocess
from pathlib import Path

import pytest

from agent_testing import AGENT, FakeCollector, agent_env
from bgt_core import wire
from polling import wait_for

pytestmark = pytest.mark.slow


def test_simulated_agent_status_token_and_sigterm(endpoint: str, tmp_path: Path) -> None:
    cfg = tmp_path / "agent.yaml"
    cfg.write_text(f"""\
agent_id: sim-01
site: lab
connect: [{endpoint}]
backend: simulated
batch_ms: 50
simulated: {{seed: 3, sensors: [sensor10, sensor40], drop_prob: 0.0}}
""")
    collector = FakeCollector(endpoint, "lab")
    log = (tmp_path / "agent.log").open("w")
    proc = subprocess.Popen(
        AGENT + ["run", "--config", str(cfg)], stdout=log, stderr=log, env=agent_env()
    )
    try:
        wait_for(
            lambda: len(collector.batches) >= 20, 30, "20 batches", step=0.01, poll=collector.poll
        )

        tokens = [
            r.ok.key_expr
            for r in collector.session.liveliness().get(wire.agent_token_selector("lab"), timeout=5)
            if r.ok is not None
        ]
        assert [str(k) for k in tokens] == [wire.agent_token_key("lab", "sim-01")]

        replies = [
            r.ok
            for r in collector.session.get(wire.agent_status_key("lab", "sim-01"), timeout=5)
            if r.ok is not None
        ]
        assert len(replies) == 1
        status = wire.from_json(replies[0].payload.to_bytes())
        assert status["agent_id"] == "sim-01"
        assert status["backend"] == "simulated"
        assert status["boot_id"] == collector.batches[0].boot_id
        assert len(status["boot_id"]) == 16
        assert status["started_ns"] <= status["now_ns"]
        ads = {a["mac"]: a for a in status["adapters"]}
        assert set(ads) == {"b827eb4521b4", "b827ebfd7811"}
        for a in ads.values():
            assert (a["backend"], a["mode"], a["restarts"]) == ("simulated", "simulated", 0)
            assert a["readings_total"] > 0
            assert a["last_advert_age_s"] is not None
            assert a["last_advert_age_s"] < 2
        assert set(status) >= {"version", "hostname"}

        proc.send_signal(signal.SIGTERM)
        proc.wait(20)
        collector.poll()
        # a stopped agent's liveliness token is gone
        gone = [
            r
            for r in collector.session.liveliness().get(wire.agent_token_selector("lab"), timeout=2)
            if r.ok is not None
        ]
        assert gone == []
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
        log.close()
        collector.close()
    assert proc.returncode == 0, (tmp_path / "agent.log").read_text()
    per_stream: dict[str, list[int]] = {}
    for b in collector.batches:
        per_stream.setdefault(b.sensor, []).append(b.seq)
        assert all(-127 <= r.rssi <= 20 for r in b.readings)
    assert set(per_stream) == {"b827eb4521b4", "b827ebfd7811"}
    for seqs in per_stream.values():
        assert seqs == list(range(len(seqs)))
