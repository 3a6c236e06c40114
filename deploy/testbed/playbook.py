"""Running the playbook against the test bed as a user would: `ansible-playbook -i inventory
site.yml` from deploy/, on the test bed's network, with the wheels fetched beforehand."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from deploy.testbed import config, network
from deploy.testbed.config import log


def ansible_playbook() -> str:
    exe = Path(sys.executable).parent / "ansible-playbook"
    found = str(exe) if exe.exists() else shutil.which("ansible-playbook")
    if not found:
        raise config.TestbedError("no ansible-playbook (pip install 'ble-groundtruth[deploy]')")
    return found


@dataclass
class PlaybookResult:
    returncode: int
    seconds: float
    output: str
    recap: dict[str, dict[str, int]]


def parse_recap(text: str) -> dict[str, dict[str, int]]:
    recap: dict[str, dict[str, int]] = {}
    for m in re.finditer(r"^(\S+)\s+:\s+((?:\w+=\d+\s*)+)$", text, re.M):
        recap[m[1]] = {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", m[2])}
    return recap


def prebuild_wheelhouse(inventory: Path) -> None:
    """The control namespace has no route to a package index: fetch the dependencies once on
    this machine's network; the playbook then refreshes the wheelhouse offline."""
    out = inventory.parent / "build" / "wheelhouse"
    tools = inventory.parent / "build" / "build-tools"
    if not (tools.is_dir() and any(tools.glob("setuptools-*.whl"))):
        # What pip's isolated build of the project wheel installs (pyproject's build-system).
        config.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "-q",
                "-d",
                str(tools),
                "setuptools>=70.1",
                "wheel",
            ],
            capture=True,
        )
    if out.is_dir() and any(out.glob("*.whl")):
        return
    log.info("building the wheelhouse %s (package index of this machine)", out)
    config.run(
        [
            sys.executable,
            "-m",
            "deploy",
            "wheelhouse",
            "--src",
            str(config.REPO),
            "--out",
            str(out),
            "--extras",
            "agent,collector",
        ],
        capture=True,
    )


def deploy(
    extra: list[str], inventory: Path | None = None, playbook: str = "site.yml"
) -> PlaybookResult:
    """`ansible-playbook -i <inventory> site.yml` from deploy/, as the README runs it."""
    inv = inventory or config.STATE / "inventory.yml"
    prebuild_wheelhouse(inv)
    env = {
        **os.environ,
        "ANSIBLE_CONFIG": str(config.REPO / "deploy/ansible.cfg"),
        "ANSIBLE_NOCOLOR": "1",
        "ANSIBLE_FORCE_COLOR": "0",
        "PATH": f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}",
        # The control namespace has no route to any package index: pip uses local files only.
        "PIP_NO_INDEX": "1",
        "PIP_FIND_LINKS": f"{inv.parent / 'build/build-tools'} {inv.parent / 'build/wheelhouse'}",
    }
    argv = network.in_control_ns([ansible_playbook(), "-i", str(inv), playbook, *extra])
    t0 = time.monotonic()
    res = subprocess.run(
        argv,
        cwd=config.REPO / "deploy",
        env=env,
        text=True,
        capture_output=True,
        check=False,
        timeout=1800,
    )
    took = time.monotonic() - t0
    out = res.stdout + res.stderr
    return PlaybookResult(res.returncode, took, out, parse_recap(out))
