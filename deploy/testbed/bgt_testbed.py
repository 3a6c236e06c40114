#!/usr/bin/env python3
"""A fleet test bed: three Debian bookworm hosts (one collector, two agents) booted with systemd
under ``systemd-nspawn``, on a private network, for running ``site.yml`` as a user would.

    python deploy/testbed/bgt_testbed.py probe      # can this machine boot containers? (root)
    python deploy/testbed/bgt_testbed.py rootfs     # build (or reuse) the cached root file system
    python deploy/testbed/bgt_testbed.py up         # boot the hosts, write inventory.yml
    python deploy/testbed/bgt_testbed.py deploy     # ansible-playbook site.yml over SSH
    python deploy/testbed/bgt_testbed.py ssh bgt-agent1 systemctl status sensor-agent
    python deploy/testbed/bgt_testbed.py down       # stop the hosts, remove namespaces, mounts

Network: every host has a network namespace of its own (``ip netns``) whose only interface is
one end of a veth pair; the other ends sit on a bridge in a further namespace, which also holds
the control address that Ansible and ``ssh`` run from (``ip netns exec``). Nothing is added to
the machine's own network, and no namespace has a route out of 10.77.0.0/24.

The root file system is made with ``debootstrap`` from the Debian mirror of this machine's own
apt sources and cached under ``/var/cache/bgt-testbed/rootfs-<hash of its inputs>``; each host
boots an overlay of it, so a host's changes (and a reboot's) stay in its own upper directory.

This file is the command line; the stages are modules beside it (``deploy.testbed``, not shipped
in the wheel): ``config`` (paths, hosts, running a command), ``probe``, ``rootfs``, ``network``
(namespaces, ssh), ``hosts`` (boot, supervise, up, down) and ``playbook`` (ansible-playbook).
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
from pathlib import Path

# Run as a script (`python deploy/testbed/bgt_testbed.py`), the repository's root is not on the
# path: the stages import as deploy.testbed.*.
_ROOT = str(Path(__file__).resolve().parents[2])
if _ROOT not in sys.path:
    sys.path.insert(0, _ROOT)

from deploy.testbed import config, hosts, network, playbook, probe, rootfs  # noqa: E402
from deploy.testbed.config import HOSTS, Host, TestbedError, host, log  # noqa: E402
from deploy.testbed.hosts import down, merged, up, wait_ssh  # noqa: E402
from deploy.testbed.network import in_control_ns, ssh  # noqa: E402
from deploy.testbed.playbook import PlaybookResult, deploy  # noqa: E402
from deploy.testbed.probe import missing_capability  # noqa: E402
from deploy.testbed.rootfs import apt_source, build_rootfs  # noqa: E402


def use_state(path: Path) -> None:
    """Keep the hosts, keys and inventory under ``path`` (default: $BGT_TESTBED_STATE)."""
    config.STATE = Path(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("probe", help="say whether this machine can boot the test bed")
    r = sub.add_parser("rootfs", help="build (or reuse) the cached root file system")
    r.add_argument("--force", action="store_true", help="rebuild even if cached")
    sub.add_parser("up", help="boot the three hosts and write the inventory")
    d = sub.add_parser("deploy", help="run ansible-playbook site.yml against the hosts")
    d.add_argument("args", nargs=argparse.REMAINDER, help="extra ansible-playbook arguments")
    s = sub.add_parser("ssh", help="run a command on a host")
    s.add_argument("host")
    s.add_argument("command", nargs=argparse.REMAINDER)
    sub.add_parser("down", help="power the hosts off, remove namespaces and mounts")
    sv = sub.add_parser("_supervise", help=argparse.SUPPRESS)
    sv.add_argument("host")
    a = p.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if a.verbose else logging.INFO,
        format="%(asctime)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    try:
        if a.cmd == "probe":
            why = probe.missing_capability()
            if why:
                log.error("cannot boot the test bed: %s", why)
                return 1
            log.info("this machine can boot the test bed (rootfs %s)", rootfs.rootfs_path())
        elif a.cmd == "rootfs":
            path, took, built = rootfs.build_rootfs(a.force)
            if built:
                log.info("built in %.0f s: %s", took, path)
            else:
                log.info("cached: %s", path)
        elif a.cmd == "up":
            log.info("%s", json.dumps(hosts.up()))
        elif a.cmd == "deploy":
            res = playbook.deploy(a.args)
            sys.stdout.write(res.output)
            log.info("playbook exit %d in %.1f s", res.returncode, res.seconds)
            return res.returncode
        elif a.cmd == "ssh":
            h = config.host(a.host)
            cmd = network.in_control_ns(
                ["ssh", *network.ssh_args(), f"root@{h.address}", "--", *a.command]
            )
            return subprocess.run(cmd, check=False).returncode
        elif a.cmd == "down":
            hosts.down()
        elif a.cmd == "_supervise":
            return hosts.supervise(a.host)
    except config.TestbedError as e:
        log.error("%s", e)  # noqa: TRY400 - one line for the user, no traceback
        return 1
    return 0


__all__ = [
    "HOSTS",
    "Host",
    "PlaybookResult",
    "TestbedError",
    "apt_source",
    "build_rootfs",
    "config",
    "deploy",
    "down",
    "host",
    "hosts",
    "in_control_ns",
    "merged",
    "missing_capability",
    "network",
    "playbook",
    "probe",
    "rootfs",
    "ssh",
    "up",
    "use_state",
    "wait_ssh",
]

if __name__ == "__main__":
    sys.exit(main())
