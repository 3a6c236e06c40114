"""The Ansible playbook: syntax, ansible-lint, and configs rendered from the example inventory
that the agent's and collector's own checkers accept."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from deploy import pki
from deploy.acl import build_acl
from deploy.inventory import load_inventory

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
BIN = Path(sys.executable).parent


def tool(name: str) -> str:
    exe = BIN / name
    if not exe.exists():
        pytest.skip(f"{name} is not installed next to {sys.executable}")
    return str(exe)


def run(
    argv: list[str], cwd: Path = DEPLOY, timeout: float = 240
) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "ANSIBLE_CONFIG": str(DEPLOY / "ansible.cfg"), "ANSIBLE_NOCOLOR": "1"}
    return subprocess.run(
        argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False
    )


@pytest.mark.parametrize("playbook", ["site.yml", "render.yml"])
def test_syntax_check(playbook: str) -> None:
    res = run([tool("ansible-playbook"), "-i", "inventory.example.yml", playbook, "--syntax-check"])
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.slow
def test_ansible_lint_is_clean(tmp_path: Path) -> None:
    res = run(
        [tool("ansible-lint"), "--offline", "--nocolor", "site.yml", "render.yml"], timeout=280
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 failure(s), 0 warning(s)" in res.stdout + res.stderr


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """render.yml over a copy of the example inventory (so the PKI lands in tmp)."""
    work = tmp_path_factory.mktemp("render")
    shutil.copy(DEPLOY / "inventory.example.yml", work / "inventory.yml")
    res = run(
        [
            tool("ansible-playbook"),
            "-i",
            str(work / "inventory.yml"),
            "render.yml",
            "-e",
            f"bgt_render_dir={work / 'out'}",
            "-e",
            f"bgt_state_dir={work / 'state'}",
        ],
        timeout=280,
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    return work


@pytest.mark.slow
def test_rendered_files_match_the_inventory(rendered: Path) -> None:
    fleet = load_inventory(rendered / "inventory.yml")
    for a in fleet.agents:
        cfg = yaml.safe_load((rendered / "out" / a.host / "agent.yaml").read_text())
        assert cfg["agent_id"] == a.agent_id
        assert cfg["adapters"] == list(a.adapters)
        assert cfg["connect"] == ["tls/192.168.50.10:7447"]
        assert cfg["scan_mode"] == "passive"
        cert = rendered / "out" / a.host / "tls/agent.crt"
        assert pki.common_name(cert) == a.agent_id  # the CN the collector's ACL matches
    acl = json.loads((rendered / "out/bgt-collector/acl.json5").read_text())
    assert acl == build_acl("default", ["pi-01", "pi-02", "pi-03"], ["collector", "operator"])


@pytest.mark.slow
@pytest.mark.parametrize("host", ["pi-01", "pi-02", "pi-03"])
def test_sensor_agent_check_accepts_rendered_config(rendered: Path, host: str) -> None:
    res = run(
        [tool("sensor-agent"), "check", "--config", str(rendered / "out" / host / "agent.yaml")]
    )
    assert res.returncode == 0, res.stdout + res.stderr
    resolved = yaml.safe_load(res.stdout)
    assert resolved["agent_id"] == host
    assert Path(resolved["tls"]["cert"]) == rendered / "out" / host / "tls/agent.crt"


@pytest.mark.slow
def test_collector_check_accepts_rendered_config(rendered: Path) -> None:
    conf = rendered / "out/bgt-collector/collector.yaml"
    res = run([tool("collector"), "serve", "--check", "--config", str(conf)])
    assert res.returncode == 0, res.stdout + res.stderr


@pytest.mark.slow
def test_render_is_idempotent(rendered: Path) -> None:
    """A second run over the same inventory changes nothing (keys are not rotated)."""
    before = {p: p.read_bytes() for p in (rendered / "pki").iterdir()}
    res = run(
        [
            tool("ansible-playbook"),
            "-i",
            str(rendered / "inventory.yml"),
            "render.yml",
            "-e",
            f"bgt_render_dir={rendered / 'out'}",
            "-e",
            f"bgt_state_dir={rendered / 'state'}",
        ],
        timeout=280,
    )
    assert res.returncode == 0, res.stdout[-3000:]
    recap = [line for line in res.stdout.splitlines() if " : ok=" in line]
    assert len(recap) == 4
    assert all("changed=0" in line for line in recap), "\n".join(recap)
    assert {p: p.read_bytes() for p in (rendered / "pki").iterdir()} == before
