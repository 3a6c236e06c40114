"""`collector fleet status` on loopback: mTLS router with the generated ACL, fake agents that
declare a token and answer status with a clock set off by a known amount."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
import yaml
import zenoh
from typer.testing import CliRunner

from bgt_core import wire
from bgt_core.zenoh_config import SessionSpec, TlsFiles, build_config
from collector.fleet import app, query_fleet
from deploy.acl import build_acl
from deploy.inventory import InventoryError, load_inventory
from deploy_helpers import ADMINS, free_port, wait_until

SITE = "default"
OFFSETS_MS = {"a1": 250.0, "a2": -1200.0}


def tls_for(pki_dir: Path, cn: str) -> TlsFiles:
    return TlsFiles(str(pki_dir / "ca.crt"), str(pki_dir / f"{cn}.crt"), str(pki_dir / f"{cn}.key"))


def write_inventory(path: Path, pki_dir: Path, port: int, agents: list[str]) -> Path:
    doc = {
        "all": {
            "vars": {"bgt_site": SITE, "bgt_zenoh_port": port, "bgt_pki_dir": str(pki_dir)},
            "children": {
                "collector": {"hosts": {"col": {"ansible_host": "127.0.0.1"}}},
                "agents": {
                    "hosts": {f"host-{a}": {"agent_id": a, "adapters": ["hci0"]} for a in agents}
                },
            },
        }
    }
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture
def site(pki_dir: Path, tmp_path: Path):
    """Router (collector) + agents a1, a2 running; the inventory also lists a3, which is down."""
    port = free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    acl = json.dumps(build_acl(SITE, ["a1", "a2", "a3"], list(ADMINS)))
    router = zenoh.open(
        build_config(
            SessionSpec(
                mode="router", listen=[endpoint], tls=tls_for(pki_dir, "collector"), acl=acl
            )
        )
    )
    agents, keep = [], []
    for a, off in OFFSETS_MS.items():
        s = zenoh.open(
            build_config(SessionSpec(mode="client", connect=[endpoint], tls=tls_for(pki_dir, a)))
        )
        key = wire.agent_status_key(SITE, a)

        def answer(q: zenoh.Query, a: str = a, off: float = off, key: str = key) -> None:
            status = {
                "agent_id": a,
                "boot_id": "0123456789abcdef",
                "version": "9.9.9",
                "backend": "simulated",
                "hostname": f"host-{a}",
                "started_ns": 0,
                "now_ns": time.time_ns() + int(off * 1e6),
                "adapters": [
                    {
                        "name": "hci0",
                        "mac": "aabbccddeeff",
                        "mode": "passive",
                        "adverts_per_s": 42.0,
                    }
                ],
                "chrony": {"ref_id": "C0A8320A (192.168.50.10)", "system_time_offset_s": 2.5e-5},
            }
            q.reply(key, wire.to_json(status))

        clock_key = wire.agent_clock_key(SITE, a)

        def answer_clock(q: zenoh.Query, off: float = off, key: str = clock_key) -> None:
            t2 = time.time_ns() + int(off * 1e6)
            t1 = json.loads(q.payload.to_bytes())["t1"]
            t3 = time.time_ns() + int(off * 1e6)
            q.reply(key, wire.to_json({"t1": t1, "t2": t2, "t3": t3, "chrony": None}))

        keep += [
            s.declare_queryable(key, answer),
            s.declare_queryable(clock_key, answer_clock),
            s.liveliness().declare_token(wire.agent_token_key(SITE, a)),
        ]
        agents.append(s)
    inv = write_inventory(tmp_path / "inventory.yml", pki_dir, port, ["a1", "a2", "a3"])
    op = zenoh.open(
        build_config(
            SessionSpec(mode="client", connect=[endpoint], tls=tls_for(pki_dir, "operator"))
        )
    )
    try:
        assert wait_until(
            lambda: (
                len(list(op.liveliness().get(wire.agent_token_selector(SITE), timeout=1.0))) == 2
            ),
            step=0.1,
        )
        yield inv, op
    finally:
        op.close()
        for obj in keep:
            obj.undeclare()
        for s in agents:
            s.close()
        router.close()


def test_query_fleet_reports_alive_version_and_clock_offset(site) -> None:
    _, op = site
    states = {
        s.agent_id: s for s in query_fleet(op, SITE, ["a1", "a2", "a3"], time.time_ns, timeout=2.0)
    }
    assert set(states) == {"a1", "a2", "a3"}
    for a, off in OFFSETS_MS.items():
        s = states[a]
        assert s.alive
        assert s.answered
        assert s.version == "9.9.9"
        assert s.adapters[0].name == "hci0"
        assert s.ntp_source == "C0A8320A (192.168.50.10)"
        assert s.ntp_offset_ms == pytest.approx(0.025)
        # The four-timestamp estimate is off by at most half the round trip (+1 ms of rounding).
        assert abs(s.offset_ms - off) <= s.rtt_ms / 2 + 1.0, (a, s.offset_ms, s.rtt_ms)
    assert not states["a3"].alive
    assert not states["a3"].answered
    assert states["a3"].offset_ms is None


def test_cli_status_prints_table_and_fails_for_missing_agent(site) -> None:
    inv, _ = site
    res = CliRunner().invoke(
        app, ["status", "--inventory", str(inv), "--timeout", "2"], terminal_width=200
    )
    assert res.exit_code == 1, res.output
    assert "a1" in res.output
    assert "a2" in res.output
    assert "9.9.9" in res.output
    assert "+250" in res.output or "+249" in res.output or "+251" in res.output
    assert "1 of 3 agents not answering: a3" in res.output
    assert "+0.025 ms" in res.output
    assert "42/s" in res.output


def test_cli_status_bad_inventory_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "inventory.yml"
    bad.write_text("all:\n  children:\n    agents:\n      hosts: {pi-01: {}}\n")
    res = CliRunner().invoke(app, ["status", "--inventory", str(bad)])
    assert res.exit_code == 1
    assert "group 'collector' is missing" in res.output
    assert "Traceback" not in res.output


@pytest.mark.parametrize(
    ("hosts", "message"),
    [
        (
            {"p1": {"agent_id": "x"}, "p2": {"agent_id": "x"}},
            "agent ids must be unique, repeated: x",
        ),
        ({"p1": {"agent_id": "bad id"}}, "agents.p1.agent_id must be 1-64 characters"),
        ({"p1": {"agent_id": "collector"}}, "is reserved for the collector"),
        ({"p1": {"adapters": "hci0"}}, "agents.p1.adapters must be a list"),
    ],
)
def test_inventory_errors_name_the_field(tmp_path: Path, hosts: dict, message: str) -> None:
    inv = tmp_path / "inventory.yml"
    inv.write_text(
        yaml.safe_dump(
            {"all": {"children": {"collector": {"hosts": {"c": None}}, "agents": {"hosts": hosts}}}}
        )
    )
    with pytest.raises(InventoryError, match=message):
        load_inventory(inv)


def test_example_inventory_reads_as_documented() -> None:
    fleet = load_inventory(Path(__file__).resolve().parents[2] / "deploy/inventory.example.yml")
    assert fleet.endpoint == "tls/192.168.50.10:7447"
    assert [(a.agent_id, a.adapters) for a in fleet.agents] == [
        ("pi-01", ("hci0",)),
        ("pi-02", ("hci0", "hci1")),
        ("pi-03", ()),
    ]
    assert fleet.pki_dir.name == "pki"
    assert fleet.pki_dir.parent.name == "deploy"
