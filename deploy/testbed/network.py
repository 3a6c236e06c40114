"""The test bed's private network (a namespace per host, a bridge in a control namespace) and
reaching the hosts over it with ssh."""

from __future__ import annotations

import shlex
import subprocess
from pathlib import Path

from deploy.testbed import config


def netns_exists(name: str) -> bool:
    return Path("/run/netns", name).exists()


def setup_network() -> None:
    if not netns_exists(config.CONTROL_NS):
        config.run(["ip", "netns", "add", config.CONTROL_NS])
    ip = ["ip", "-n", config.CONTROL_NS]
    config.run([*ip, "link", "set", "lo", "up"])
    if config.run([*ip, "link", "show", config.BRIDGE], check=False, capture=True).returncode != 0:
        config.run([*ip, "link", "add", config.BRIDGE, "type", "bridge"])
        config.run([*ip, "addr", "add", f"{config.NET}.1/24", "dev", config.BRIDGE])
    config.run([*ip, "link", "set", config.BRIDGE, "up"])
    for h in config.HOSTS:
        if not netns_exists(h.netns):
            config.run(["ip", "netns", "add", h.netns])
        hip = ["ip", "-n", h.netns]
        config.run([*hip, "link", "set", "lo", "up"])
        if config.run([*hip, "link", "show", "host0"], check=False, capture=True).returncode != 0:
            config.run(
                [
                    *hip,
                    "link",
                    "add",
                    "host0",
                    "type",
                    "veth",
                    "peer",
                    "name",
                    h.veth,
                    "netns",
                    config.CONTROL_NS,
                ]
            )
            config.run([*hip, "addr", "add", f"{h.address}/24", "dev", "host0"])
            config.run([*ip, "link", "set", h.veth, "master", config.BRIDGE])
        config.run([*hip, "link", "set", "host0", "up"])
        config.run([*ip, "link", "set", h.veth, "up"])


def ssh_args() -> list[str]:
    return [
        "-i",
        str(config.STATE / "id_ed25519"),
        "-o",
        f"UserKnownHostsFile={config.STATE / 'known_hosts'}",
        "-o",
        "StrictHostKeyChecking=yes",
        "-o",
        "BatchMode=yes",
        "-o",
        "ConnectTimeout=5",
        "-o",
        "LogLevel=ERROR",
    ]


def in_control_ns(argv: list[str]) -> list[str]:
    """Prefix argv so that it runs on the test bed's network (the control address)."""
    return ["ip", "netns", "exec", config.CONTROL_NS, *argv]


def ssh(
    h: config.Host,
    argv: list[str],
    *,
    check: bool = True,
    timeout: float = 120,
    input_text: str | None = None,
) -> subprocess.CompletedProcess[str]:
    # ssh hands the remote shell one string: quote, so that argv arrives as it is here.
    cmd = in_control_ns(["ssh", *ssh_args(), f"root@{h.address}", "--", shlex.join(argv)])
    res = subprocess.run(
        cmd, text=True, capture_output=True, timeout=timeout, check=False, input=input_text
    )
    if check and res.returncode != 0:
        raise config.TestbedError(
            f"{h.name}: {' '.join(argv)} exited {res.returncode}: "
            f"{(res.stderr or res.stdout).strip()[-400:]}"
        )
    return res
