"""End to end with real processes and the files the playbook renders: `collector serve` behind
mutual TLS + the generated ACL, two `sensor-agent run` processes, an impostor agent using
pi-01's certificate to pose as pi-02, and the operator CLI driving a run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from deploy_helpers import free_port, wait_until

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
BIN = Path(sys.executable).parent
SENSORS = {"pi-01": ["sensor10", "sensor11"], "pi-02": ["sensor20"], "impostor": ["sensor30"]}
MACS = {
    "sensor10": "b827eb4521b4",
    "sensor11": "000000000101",
    "sensor20": "b827eb917e19",
    "sensor30": "b827ebf7d096",
}

pytestmark = pytest.mark.slow


def exe(name: str) -> str:
    path = BIN / name
    if not path.exists():
        pytest.skip(f"{name} is not installed next to {sys.executable}")
    return str(path)


def env() -> dict[str, str]:
    return {
        **os.environ,
        "ANSIBLE_CONFIG": str(DEPLOY / "ansible.cfg"),
        "ANSIBLE_NOCOLOR": "1",
        "COLUMNS": "400",
    }


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Render an inventory whose collector is 127.0.0.1:<free port>; derive agent configs."""
    work = tmp_path_factory.mktemp("e2e")
    port = free_port()
    inv = yaml.safe_load((DEPLOY / "inventory.example.yml").read_text())
    inv["all"]["vars"]["bgt_zenoh_port"] = port
    inv["all"]["children"]["collector"]["hosts"] = {"bgt-collector": {"ansible_host": "127.0.0.1"}}
    agents = inv["all"]["children"]["agents"]["hosts"]
    for host in list(agents):
        if host not in SENSORS:
            del agents[host]
    (work / "inventory.yml").write_text(yaml.safe_dump(inv))
    res = subprocess.run(
        [exe("ansible-playbook"), "-i", str(work / "inventory.yml"), "render.yml",
         "-e", f"bgt_render_dir={work / 'out'}", "-e", f"bgt_state_dir={work / 'state'}"],
        cwd=DEPLOY, env=env(), capture_output=True, text=True, timeout=280, check=False,
    )  # fmt: skip
    assert res.returncode == 0, res.stdout[-3000:]
    out = work / "out"
    # Same files the hosts get, switched to the simulated backend so no radio is needed.
    configs = {}
    for name, host, agent_id in (
        ("pi-01", "pi-01", "pi-01"),
        ("pi-02", "pi-02", "pi-02"),
        ("impostor", "pi-01", "pi-02"),
    ):
        cfg = yaml.safe_load((out / host / "agent.yaml").read_text())
        assert cfg["connect"] == [f"tls/127.0.0.1:{port}"]
        cfg.update(agent_id=agent_id, backend="simulated", adapters=[])
        cfg["simulated"]["sensors"] = SENSORS[name]
        cfg["spool"]["dir"] = str(work / "spool" / name)
        configs[name] = out / host / f"{name}.yaml"  # beside agent.yaml: relative tls/ paths hold
        configs[name].write_text(yaml.safe_dump(cfg))
    tls = out / "bgt-collector/tls"
    return {
        "port": port,
        "collector_yaml": out / "bgt-collector/collector.yaml",
        "data": work / "data",
        "agents": configs,
        "inventory": work / "inventory.yml",
        "operator": ["--root-ca", str(tls / "ca.crt"), "--cert", str(tls / "operator.crt"), "--key", str(tls / "operator.key")],
        "agent_certs": ["--root-ca", str(out / "pi-01/tls/ca.crt"), "--cert", str(out / "pi-01/tls/agent.crt"),
                        "--key", str(out / "pi-01/tls/agent.key")],
    }  # fmt: skip


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def cli(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [exe("collector"), *args],
        env=env(),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_capture_through_mtls_and_acl(site: dict) -> None:
    ep = f"tls/127.0.0.1:{site['port']}"
    procs: list[subprocess.Popen] = []
    log_path = site["data"].parent / "collector.log"
    log = log_path.open("w")
    try:
        server = subprocess.Popen(
            [exe("collector"), "serve", "--config", str(site["collector_yaml"]), "--listen", ep,
             "--data-dir", str(site["data"])],
            env=env(), stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        procs.append(server)

        def status() -> dict | None:
            res = cli(["status", "--json", "--connect", ep, *site["operator"]])
            return json.loads(res.stdout) if res.returncode == 0 else None

        assert wait_until(lambda: status() is not None, timeout=30, step=0.5), (
            "collector never answered"
        )
        for name in ("pi-01", "pi-02", "impostor"):
            procs.append(
                subprocess.Popen(
                    [
                        exe("sensor-agent"),
                        "run",
                        "--config",
                        str(site["agents"][name]),
                        "--ack-timeout",
                        "3",
                    ],
                    env=env(),
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )  # fmt: skip
            )
        started = cli(["start", "--name", "e2e", "--connect", ep, *site["operator"]])
        assert started.returncode == 0, started.stdout + started.stderr

        def recording(st: dict | None) -> set[str]:
            if not st:
                return set()
            return {
                mac
                for agent in st["agents"].values()
                for mac, s in agent.get("sensors", {}).items()
                if s.get("readings", 0) > 0
            }

        legit = {MACS[s] for s in SENSORS["pi-01"] + SENSORS["pi-02"]}
        assert wait_until(lambda: legit <= recording(status()), timeout=40, step=0.5), status()

        # An agent certificate cannot drive the collector.
        for cmd in (["start", "--name", "evil"], ["stop"]):
            res = cli([*cmd, "--connect", ep, *site["agent_certs"]])
            assert res.returncode == 1, res.stdout + res.stderr
            assert "Traceback" not in res.stderr

        # Fleet status through the same ACL: both real agents answer with their clocks.
        fleet = subprocess.run(
            [exe("collector"), "fleet", "status", "--inventory", str(site["inventory"]),
             "--root-ca", site["operator"][1], "--cert", site["operator"][3], "--key", site["operator"][5]],
            env=env(), capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        if "No such command" not in fleet.stderr:
            assert fleet.returncode == 0, fleet.stdout + fleet.stderr
            assert "pi-01" in fleet.stdout
            assert "pi-02" in fleet.stdout

        # Every agent process is still up: the impostor connected (valid certificate) and ran.
        assert [p.poll() for p in procs] == [None] * 4
        stopped = cli(["stop", "--connect", ep, *site["operator"]])
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
        run_dir = Path(stopped.stdout.strip())
        files = {p.stem for p in (run_dir / "rssi").glob("*/*.mbd")}
        assert files == legit  # the impostor's sensor30 never made it in
        for mac in legit:
            (path,) = (run_dir / "rssi").glob(f"*/{mac}.mbd")
            rows = path.read_text().splitlines()
            assert rows
            assert all(r.split(",")[1] == mac for r in rows if r and not r.startswith("#"))
    finally:
        for p in reversed(procs):
            stop(p)
        log.close()
