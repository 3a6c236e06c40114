"""The three hosts: each an overlay of the cached root file system booted by systemd-nspawn under a
supervisor of its own (so a reboot inside boots it again), brought up and powered off together."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

from deploy.testbed import config, network, rootfs
from deploy.testbed.config import log

# The script whose `_supervise` command runs one host's container.
SCRIPT = Path(__file__).resolve().with_name("bgt_testbed.py")


def hostdir(h: config.Host) -> Path:
    return config.STATE / "hosts" / h.name


def merged(h: config.Host) -> Path:
    """The host's root directory as seen from this machine (while it is up)."""
    return hostdir(h) / "root"


def _keygen(path: Path, comment: str) -> None:
    """A new ed25519 key pair without a passphrase at ``path`` (and ``path``.pub)."""
    config.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", comment, "-f", str(path)])


def _prepare_host(h: config.Host, lower: Path) -> None:
    d = hostdir(h)
    for sub in ("upper", "work", "root"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    root = merged(h)
    if not os.path.ismount(root):
        config.run(
            [
                "mount",
                "-t",
                "overlay",
                "overlay",
                "-o",
                f"lowerdir={lower},upperdir={d / 'upper'},workdir={d / 'work'}",
                str(root),
            ]
        )
    config.write_file(root / "etc/hostname", h.name + "\n")
    hosts = "127.0.0.1 localhost\n" + "".join(f"{x.address} {x.name}\n" for x in config.HOSTS)
    config.write_file(root / "etc/hosts", hosts)
    if not (root / "etc/machine-id").read_text().strip():
        config.write_file(root / "etc/machine-id", uuid.uuid4().hex + "\n", 0o444)
    if not (root / "etc/ssh/ssh_host_ed25519_key").exists():
        _keygen(root / "etc/ssh/ssh_host_ed25519_key", h.name)
    ak = root / "root/.ssh/authorized_keys"
    config.write_file(ak, (config.STATE / "id_ed25519.pub").read_text(), 0o600)
    ak.parent.chmod(0o700)


def _write_inventory() -> Path:
    lines = [
        "# Written by deploy/testbed/bgt_testbed.py: the test bed's fleet.",
        "all:",
        "  vars:",
        "    ansible_user: root",
        f"    ansible_ssh_private_key_file: {config.STATE / 'id_ed25519'}",
        f'    ansible_ssh_common_args: "-o UserKnownHostsFile={config.STATE / "known_hosts"}'
        ' -o StrictHostKeyChecking=yes -o ConnectTimeout=10"',
        "    ansible_python_interpreter: /usr/bin/python3",
        "    bgt_site: testbed",
        f"    bgt_lan_cidr: {config.NET}.0/24",
        "    bgt_pki_dir: pki",
        "  children:",
        "    collector:",
        "      hosts:",
    ]
    for h in config.HOSTS:
        if h.role == "collector":
            lines += [f"        {h.name}:", f"          ansible_host: {h.address}"]
    lines += [
        "    agents:",
        "      vars:",
        "        bgt_backend: simulated",
        "        bgt_sim_site: tetam",
        "      hosts:",
    ]
    for h in config.HOSTS:
        if h.role == "agent":
            lines += [
                f"        {h.name}:",
                f"          ansible_host: {h.address}",
                f"          agent_id: {h.agent_id}",
                "          adapters: []",
                f"          bgt_sim_sensors: {json.dumps(config.SIM_SENSORS[h.agent_id])}",
            ]
    inv = config.STATE / "inventory.yml"
    config.write_file(inv, "\n".join(lines) + "\n")
    return inv


# Supervisors this process started (reaped when stopped).
_SUPERVISORS: dict[int, subprocess.Popen[bytes]] = {}


def pidfile(h: config.Host) -> Path:
    return hostdir(h) / "supervisor.pid"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _running(h: config.Host) -> int | None:
    try:
        pid = int(pidfile(h).read_text())
    except (OSError, ValueError):
        return None
    return pid if _alive(pid) else None


def nspawn_argv(h: config.Host) -> list[str]:
    return [
        "systemd-nspawn",
        "--boot",
        "--register=no",
        "--keep-unit",
        "--quiet",
        f"--machine={h.name}",
        f"--directory={merged(h)}",
        f"--network-namespace-path=/run/netns/{h.netns}",
        # zenoh's runtime locks memory; nspawn's default filter refuses mlock.
        "--system-call-filter=@memlock",
        "--resolv-conf=off",
        "--timezone=off",
        "--link-journal=no",
        "--console=read-only",
    ]


def supervise(name: str) -> int:
    """Run one host's container; a `systemctl reboot` inside it (exit 133) boots it again."""
    h = config.host(name)
    child: subprocess.Popen[bytes] | None = None
    stopping = False

    def on_term(_sig: int, _frm: object) -> None:
        nonlocal stopping
        stopping = True
        if child is not None and child.poll() is None:
            child.send_signal(signal.SIGTERM)  # nspawn powers the container off cleanly

    signal.signal(signal.SIGTERM, on_term)
    signal.signal(signal.SIGINT, on_term)
    with open(hostdir(h) / "console.log", "ab") as out:
        while True:
            child = subprocess.Popen(
                nspawn_argv(h), stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT
            )
            rc = child.wait()
            log.info("%s: container exited %d", name, rc)
            if stopping or rc != 133:
                return rc
            out.write(b"\n--- reboot ---\n")


def wait_ssh(h: config.Host, timeout: float = 180.0) -> None:
    end = time.monotonic() + timeout
    while True:
        res = network.ssh(h, ["systemctl", "is-system-running", "--wait"], check=False, timeout=120)
        if res.returncode == 0 or res.stdout.strip() in ("running", "degraded"):
            return
        if time.monotonic() > end:
            raise config.TestbedError(
                f"{h.name} did not come up in {timeout:.0f} s (see {hostdir(h) / 'console.log'})"
            )
        if _running(h) is None:
            raise config.TestbedError(
                f"{h.name}: container exited (see {hostdir(h) / 'console.log'})"
            )
        time.sleep(1.0)


def start_host(h: config.Host) -> None:
    if _running(h):
        return
    with open(hostdir(h) / "supervisor.log", "ab") as out:
        proc = subprocess.Popen(
            [sys.executable, str(SCRIPT), "_supervise", h.name],
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "BGT_TESTBED_STATE": str(config.STATE)},
        )
    _SUPERVISORS[proc.pid] = proc
    config.write_file(pidfile(h), f"{proc.pid}\n")


def stop_host(h: config.Host, timeout: float = 90.0) -> None:
    pid = _running(h)
    if pid is None:
        return
    os.kill(pid, signal.SIGTERM)
    proc = _SUPERVISORS.pop(pid, None)
    end = time.monotonic() + timeout
    while _alive(pid) and time.monotonic() < end:
        if proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(0.3)
            continue
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)
        time.sleep(0.3)
    if _alive(pid):
        log.warning("%s did not power off in %.0f s; killing its process group", h.name, timeout)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(pid, signal.SIGKILL)
        if proc is not None:
            proc.wait(10)
    pidfile(h).unlink(missing_ok=True)


def up() -> dict[str, float]:
    t0 = time.monotonic()
    lower, _took, _built = rootfs.build_rootfs()
    config.STATE.mkdir(parents=True, exist_ok=True)
    if not (config.STATE / "id_ed25519").exists():
        _keygen(config.STATE / "id_ed25519", "bgt-testbed")
    network.setup_network()
    known = []
    for h in config.HOSTS:
        _prepare_host(h, lower)
        pub = (merged(h) / "etc/ssh/ssh_host_ed25519_key.pub").read_text().split()
        known.append(f"{h.address},{h.name} {pub[0]} {pub[1]}\n")
    config.write_file(config.STATE / "known_hosts", "".join(known))
    t1 = time.monotonic()
    for h in config.HOSTS:
        start_host(h)
    for h in config.HOSTS:
        wait_ssh(h)
    inv = _write_inventory()
    figures = {"prepare_s": t1 - t0, "boot_s": time.monotonic() - t1}
    log.info(
        "up: %s booted in %.0f s; inventory %s",
        ", ".join(h.name for h in config.HOSTS),
        figures["boot_s"],
        inv,
    )
    return figures


def down() -> None:
    for h in config.HOSTS:
        stop_host(h)
    for h in config.HOSTS:
        root = merged(h)
        if os.path.ismount(root):
            config.run(["umount", str(root)], check=False)
            if os.path.ismount(root):
                config.run(["umount", "-l", str(root)], check=False)
        if network.netns_exists(h.netns):
            config.run(["ip", "netns", "del", h.netns], check=False)
    if network.netns_exists(config.CONTROL_NS):
        config.run(["ip", "netns", "del", config.CONTROL_NS], check=False)
