"""The test bed's fixed parts: where it keeps things, its hosts and network, and running a command
(one line for the user when it fails)."""

from __future__ import annotations

import logging
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("bgt-testbed")

REPO = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("BGT_TESTBED_CACHE", "/var/cache/bgt-testbed"))
STATE = Path(os.environ.get("BGT_TESTBED_STATE", "/var/tmp/bgt-testbed"))
SUITE = "bookworm"
# What the hosts carry beyond debootstrap's minbase: systemd as PID 1, sshd for Ansible, Python
# for its modules (python3-apt for the apt module), and the packages the role installs, so the
# role finds them present (the hosts have no route to any mirror).
PACKAGES = (
    "systemd",
    "systemd-sysv",
    "dbus",
    "openssh-server",
    "python3",
    "python3-venv",
    "python3-apt",
    "chrony",
    "bluez",
    "iproute2",
    "procps",
)
# Bump when the post-debootstrap setup below changes: it is part of the cache key.
RECIPE = 3
NET = "10.77.0"
CONTROL_NS = "bgt-tb-net"
BRIDGE = "br0"


@dataclass(frozen=True)
class Host:
    name: str
    address: str
    role: str  # collector | agent
    agent_id: str = ""

    @property
    def netns(self) -> str:
        return f"bgt-tb-{self.name.removeprefix('bgt-')}"

    @property
    def veth(self) -> str:
        return f"vb-{self.name.removeprefix('bgt-')}"[:15]


HOSTS = (
    Host("bgt-collector", f"{NET}.10", "collector"),
    Host("bgt-agent1", f"{NET}.21", "agent", "agent1"),
    Host("bgt-agent2", f"{NET}.22", "agent", "agent2"),
)
# Simulated sensors of the demo site, split between the two agents (each sensor has one agent).
SIM_SENSORS = {"agent1": ["sensor10", "sensor20"], "agent2": ["sensor30", "sensor40"]}


class TestbedError(RuntimeError):
    """Something this machine cannot do, or a step that failed; one line for the user."""


def run(
    argv: list[str],
    *,
    check: bool = True,
    capture: bool = False,
    timeout: float | None = None,
) -> subprocess.CompletedProcess[str]:
    log.debug("$ %s", " ".join(argv))
    res = subprocess.run(argv, text=True, capture_output=capture, timeout=timeout, check=False)
    if check and res.returncode != 0:
        tail = (
            ((res.stderr or "") + (res.stdout or "")).strip().splitlines()[-3:] if capture else []
        )
        raise TestbedError(f"{argv[0]} failed (exit {res.returncode}): {' | '.join(tail)}")
    return res


def host(name: str) -> Host:
    for h in HOSTS:
        if h.name == name:
            return h
    raise TestbedError(f"no host {name!r}; hosts: {', '.join(h.name for h in HOSTS)}")


def write_file(path: Path, text: str, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    path.chmod(mode)
