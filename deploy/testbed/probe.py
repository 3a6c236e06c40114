"""Whether this machine can boot the test bed: one line naming what is missing."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

from deploy.testbed import config, rootfs


def missing_capability() -> str | None:
    """None if this machine can boot the test bed, else one line naming what is missing."""
    if sys.platform != "linux":
        return "not Linux"
    if os.geteuid() != 0:
        return "not root (network namespaces, mounts and systemd-nspawn need root)"
    for tool, pkg in (
        ("debootstrap", "debootstrap"),
        ("systemd-nspawn", "systemd-container"),
        ("ip", "iproute2"),
        ("ssh", "openssh-client"),
        ("ssh-keygen", "openssh-client"),
    ):
        if shutil.which(tool) is None:
            return f"no {tool} (Debian package {pkg})"
    if "overlay" not in Path("/proc/filesystems").read_text():
        return "no overlay file system in the kernel"
    if not Path("/sys/fs/cgroup").is_dir():
        return "no /sys/fs/cgroup (systemd in a container needs cgroups)"
    ns = f"bgt-tb-probe{os.getpid()}"
    res = config.run(["ip", "netns", "add", ns], check=False, capture=True)
    if res.returncode != 0:
        return f"cannot create a network namespace: {res.stderr.strip()}"
    try:
        res = config.run(
            ["ip", "-n", ns, "link", "add", "p0", "type", "veth", "peer", "name", "p1"],
            check=False,
            capture=True,
        )
        if res.returncode != 0:
            return f"cannot create a veth pair: {res.stderr.strip()}"
        res = config.run(
            ["ip", "-n", ns, "link", "add", "b0", "type", "bridge"], check=False, capture=True
        )
        if res.returncode != 0:
            return f"cannot create a bridge: {res.stderr.strip()}"
    finally:
        config.run(["ip", "netns", "del", ns], check=False, capture=True)
    try:
        rootfs.apt_source()
    except config.TestbedError as e:
        return str(e)
    return None
