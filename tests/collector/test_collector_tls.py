"""The collector behind mutual TLS and the ACL that deploy/ generates: an agent certificate may
publish its own data and receive its acks, the operator certificate drives runs, others get nothing."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from bgt_core.zenoh_config import TlsFiles
from collector.client import CollectorClient
from collector.config import CollectorConfig
from collector.errors import Unreachable
from collector.service import Collector
from collector_helpers import FakeAgent, expected_lines, make_batch, wait_for
from deploy import pki
from deploy.acl import build_acl
from loopback import free_port


def files(d: Path, cn: str) -> TlsFiles:
    return TlsFiles(str(d / "ca.crt"), str(d / f"{cn}.crt"), str(d / f"{cn}.key"))


@pytest.fixture(scope="module")
def site_pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("collector-pki")
    now = dt.datetime.now(dt.UTC)
    pki.issue(d, "collector", ["collector", "localhost", "127.0.0.1"], now)
    for cn in ("operator", "pi-01", "pi-02"):
        pki.issue(d, cn, [cn], now)
    return d


@pytest.mark.slow
def test_capture_over_mtls_with_the_generated_acl(tmp_path, site_pki) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    acl = tmp_path / "acl.json5"
    acl.write_text(json.dumps(build_acl("default", ["pi-01"], ["collector", "operator"])))
    cfg = CollectorConfig(
        data_dir=tmp_path / "data",
        listen=(endpoint,),
        tls=files(site_pki, "collector"),
        acl=acl,
        fsync_interval_s=0.1,
    )
    with Collector(cfg):
        with pytest.raises(Unreachable):  # no certificate, no session
            with CollectorClient(endpoint, connect_timeout_s=1.0) as c:
                c.status()
        agent = FakeAgent(endpoint, tls=files(site_pki, "pi-01"))
        try:
            with CollectorClient(endpoint, tls=files(site_pki, "operator")) as op:
                run = op.start("tls")
                batches = [make_batch(i) for i in range(3)]
                for b in batches:
                    agent.put(b)
                wait_for(lambda: agent.acked(batches[0].sensor) == 2, what="acks through the ACL")
                stopped = op.stop()
            # The agent may not drive the collector (its certificate only covers its own keys).
            with (
                CollectorClient(endpoint, tls=files(site_pki, "pi-01")) as impostor,
                pytest.raises(Unreachable, match="not allowed for this certificate") as refused,
            ):
                impostor.start("not allowed")
            assert "is `collector serve` running" not in str(refused.value)
        finally:
            agent.close()
    lines = (
        (Path(run["run_dir"]) / "rssi" / "pi-01" / f"{batches[0].sensor}.mbd")
        .read_text()
        .splitlines()
    )
    assert lines == expected_lines(batches)
    assert stopped["readings"] == 15


@pytest.mark.slow
def test_an_agent_cannot_write_into_another_agents_file_or_metadata(tmp_path, site_pki) -> None:
    """pi-01 (a valid certificate, within its own keys) publishes with pi-02's adapter MAC and
    answers status queries claiming to be pi-02: pi-02's file and run.yaml entry stay its own."""
    from bgt_core import wire
    from collector_helpers import run_yaml_doc

    endpoint = f"tls/127.0.0.1:{free_port()}"
    acl = tmp_path / "acl.json5"
    acl.write_text(json.dumps(build_acl("default", ["pi-01", "pi-02"], ["collector", "operator"])))
    cfg = CollectorConfig(
        data_dir=tmp_path / "data",
        listen=(endpoint,),
        tls=files(site_pki, "collector"),
        acl=acl,
        fsync_interval_s=0.1,
    )
    mac_b = "000000000202"  # pi-02's adapter
    honest = [make_batch(i, agent="pi-02", sensor=mac_b) for i in range(4)]
    forged = [make_batch(i, agent="pi-01", sensor=mac_b, first=1000 + 5 * i) for i in range(3)]
    with Collector(cfg) as c:
        a1 = FakeAgent(endpoint, agent="pi-01", tls=files(site_pki, "pi-01"))
        a2 = FakeAgent(endpoint, agent="pi-02", tls=files(site_pki, "pi-02"))
        lie = {
            "agent_id": "pi-02",
            "hostname": "forged-host",
            "version": "6.6.6",
            "backend": "bleak",
            "adapters": [{"name": "hci9", "mac": mac_b, "backend": "bleak", "mode": "active"}],
        }
        key1 = wire.agent_status_key("default", "pi-01")
        q = a1.session.declare_queryable(key1, lambda query: query.reply(key1, wire.to_json(lie)))
        truth = {
            "agent_id": "pi-02",
            "hostname": "pi-02-host",
            "version": "1.0",
            "backend": "replay",
            "adapters": [{"name": "hci0", "mac": mac_b, "backend": "replay", "mode": "passive"}],
        }
        key2 = wire.agent_status_key("default", "pi-02")
        q2 = a2.session.declare_queryable(
            key2, lambda query: query.reply(key2, wire.to_json(truth))
        )
        try:
            a1.declare_token()
            a2.declare_token()
            with CollectorClient(endpoint, tls=files(site_pki, "operator")) as op:
                run = op.start("owners")
                for f, h in zip(forged, honest, strict=False):
                    a1.put(f)
                    a2.put(h)
                a2.put(honest[-1])
                wait_for(lambda: a1.acked(mac_b) == 2 and a2.acked(mac_b) == 3, what="acks of both")
                status = op.status()
                op.stop()
        finally:
            q.undeclare()
            q2.undeclare()
            a1.close()
            a2.close()
    assert c is not None
    run_dir = Path(run["run_dir"])
    assert (run_dir / "rssi" / "pi-02" / f"{mac_b}.mbd").read_text().splitlines() == expected_lines(
        honest
    )
    assert (run_dir / "rssi" / "pi-01" / f"{mac_b}.mbd").read_text().splitlines() == expected_lines(
        forged
    )
    assert status["shared_sensors"] == {mac_b: ["pi-01", "pi-02"]}
    doc = run_yaml_doc(run_dir)
    assert doc["shared_sensors"] == {mac_b: ["pi-01", "pi-02"]}
    a2_doc = doc["agents"]["pi-02"]
    assert (a2_doc["hostname"], a2_doc["version"]) == ("pi-02-host", "1.0")  # not the forged ones
    assert a2_doc["sensors"][mac_b]["readings"] == 20
    assert a2_doc["sensors"][mac_b]["adapter"] == "hci0"
    # What pi-01 said about itself is credited to pi-01, the agent its key names.
    assert doc["agents"]["pi-01"]["hostname"] == "forged-host"
    assert doc["agents"]["pi-01"]["sensors"][mac_b]["readings"] == 15


@pytest.mark.slow
def test_agent_whose_id_is_not_its_certificate_cn_warns_naming_both(
    tmp_path, site_pki, caplog
) -> None:
    """pi-01's certificate on an agent configured as pi-02: the ACL drops its puts. The agent
    must say so at WARNING (both names), not lose everything with INFO lines only."""
    import asyncio
    import logging

    from bgt_core.formats.mbd import format_row
    from sensor_agent.app import Agent
    from sensor_agent.config import AgentConfig, ReplayConfig
    from sensor_agent.errors import AckTimeout
    from sensor_agent.scanning.replay import ReplayBackend

    endpoint = f"tls/127.0.0.1:{free_port()}"
    acl = tmp_path / "acl.json5"
    acl.write_text(json.dumps(build_acl("default", ["pi-01", "pi-02"], ["collector", "operator"])))
    cfg = CollectorConfig(
        data_dir=tmp_path / "data",
        listen=(endpoint,),
        tls=files(site_pki, "collector"),
        acl=acl,
        fsync_interval_s=0.1,
    )
    rec = tmp_path / "rec.mbd"
    rec.write_text(
        "".join(
            format_row(1_700_000_000 * 10**9 + i * 10**8, "b827eb4521b4", "e78f135624ce", -60)
            for i in range(5)
        )
    )
    acfg = AgentConfig(
        agent_id="pi-02",
        connect=(endpoint,),
        backend="replay",
        replay=ReplayConfig((rec,), speed=0.0, keep_time=True),
        tls=files(site_pki, "pi-01"),
        ack_timeout_s=4.0,
    )
    caplog.set_level(logging.INFO)
    with Collector(cfg) as c:
        c.start_run("cn")
        agent = Agent(acfg, ReplayBackend(acfg.replay.paths, 0.0, True))
        agent.no_ack_warn_s = 1.0
        with pytest.raises(AckTimeout) as e:
            asyncio.run(agent.run())
        status = c.status()
        c.stop_run()
    warnings = [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and r.name == "sensor_agent.app"
    ]
    assert any("agent id 'pi-02' is not the CN 'pi-01'" in w for w in warnings), warnings
    assert any(
        "no acknowledgement from the collector" in w and "'pi-02'" in w and "'pi-01'" in w
        for w in warnings
    ), warnings
    assert "connected, but no acknowledgement at all: agent id 'pi-02' differs" in str(e.value)
    assert status["run"]["readings"] == 0


def test_certificate_cn_reader_agrees_with_cryptography(site_pki, tmp_path) -> None:
    from bgt_core.certname import CertificateError, certificate_cn

    for name in ("ca", "collector", "operator", "pi-01", "pi-02"):
        assert certificate_cn(site_pki / f"{name}.crt") == pki.common_name(site_pki / f"{name}.crt")
    bad = tmp_path / "x.crt"
    bad.write_text("-----BEGIN CERTIFICATE-----\nAAAA\n-----END CERTIFICATE-----\n")
    with pytest.raises(CertificateError):
        certificate_cn(bad)
