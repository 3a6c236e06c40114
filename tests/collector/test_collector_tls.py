"""The collector behind mutual TLS and the ACL that deploy/ generates: an agent certificate may
publish its own data and receive its acks, the operator certificate drives runs, others get nothing."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest
from collector_helpers import FakeAgent, expected_lines, make_batch, wait_for

from ble_groundtruth.deploy import pki
from ble_groundtruth.deploy.acl import build_acl
from ble_groundtruth.zenoh_config import TlsFiles
from collector.client import CollectorClient
from collector.config import CollectorConfig
from collector.errors import Unreachable
from collector.server import Collector
from loopback import free_port


def files(d: Path, cn: str) -> TlsFiles:
    return TlsFiles(str(d / "ca.crt"), str(d / f"{cn}.crt"), str(d / f"{cn}.key"))


@pytest.fixture(scope="module")
def site_pki(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("collector-pki")
    now = dt.datetime.now(dt.UTC)
    pki.issue(d, "collector", ["collector", "localhost", "127.0.0.1"], now)
    for cn in ("operator", "pi-01"):
        pki.issue(d, cn, [cn], now)
    return d


@pytest.mark.slow
def test_capture_over_mtls_with_the_generated_acl(tmp_path, site_pki) -> None:
    endpoint = f"tls/127.0.0.1:{free_port()}"
    acl = tmp_path / "acl.json5"
    acl.write_text(json.dumps(build_acl("default", ["pi-01"], ["collector", "operator"])))
    cfg = CollectorConfig(data_dir=tmp_path / "data", listen=(endpoint,), tls=files(site_pki, "collector"),
                          acl=acl, fsync_interval_s=0.1)
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
            with CollectorClient(endpoint, tls=files(site_pki, "pi-01")) as impostor, \
                    pytest.raises(Unreachable):
                impostor.start("not allowed")
        finally:
            agent.close()
    lines = (Path(run["run_dir"]) / "rssi" / f"{batches[0].sensor}.mbd").read_text().splitlines()
    assert lines == expected_lines(batches)
    assert stopped["readings"] == 15
