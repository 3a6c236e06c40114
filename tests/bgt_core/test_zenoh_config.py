"""The one endpoint rule (bgt_core.zenoh_config.endpoint_problem): the agent's connect and the
collector's listen accept and refuse the same endpoints, each with one line."""

from __future__ import annotations

import pytest

from bgt_core.zenoh_config import endpoint_problem

# One endpoint rule for the agent's connect and the collector's listen (issue 32).
ENDPOINTS = [
    ("tcp/127.0.0.1:7447", True),
    ("tls/collector.lab:7447", True),
    ("tcp/[::1]:7447", True),
    ("udp/10.0.0.2:7447#iface=eth0", True),
    ("unixsock-stream//run/zenoh.sock", True),
    ("localhost", False),
    ("tcp/127.0.0.1", False),
    ("tcp/127.0.0.1:0", False),
    ("tcp/127.0.0.1:70000", False),
    ("tcp/:7447", False),
    ("TCP/host:7447", False),
    ("tcp/host name:7447", False),
]


@pytest.mark.parametrize(("endpoint", "ok"), ENDPOINTS)
def test_agent_and_collector_agree_on_endpoints(endpoint: str, ok: bool, tmp_path) -> None:
    from collector.config import parse_config as parse_collector
    from collector.errors import ConfigError as CollectorError
    from sensor_agent.config import check_endpoint
    from sensor_agent.errors import ConfigError as AgentError

    assert (endpoint_problem(endpoint) is None) == ok
    verdicts = []
    try:
        check_endpoint(endpoint)
        verdicts.append(True)
    except AgentError:
        verdicts.append(False)
    try:
        parse_collector({"listen": [endpoint], "insecure": True}, base=tmp_path)
        verdicts.append(True)
    except CollectorError as e:
        verdicts.append("listen entry" not in str(e))  # refused for another reason (no tls files)
    assert verdicts == [ok, ok]
