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
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import logging
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import asdict, dataclass
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
    **kw,
) -> subprocess.CompletedProcess[str]:
    log.debug("$ %s", " ".join(argv))
    res = subprocess.run(
        argv, text=True, capture_output=capture, timeout=timeout, check=False, **kw
    )
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


# --- probe ----------------------------------------------------------------------------------


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
    res = run(["ip", "netns", "add", ns], check=False, capture=True)
    if res.returncode != 0:
        return f"cannot create a network namespace: {res.stderr.strip()}"
    try:
        res = run(
            ["ip", "-n", ns, "link", "add", "p0", "type", "veth", "peer", "name", "p1"],
            check=False,
            capture=True,
        )
        if res.returncode != 0:
            return f"cannot create a veth pair: {res.stderr.strip()}"
        res = run(
            ["ip", "-n", ns, "link", "add", "b0", "type", "bridge"], check=False, capture=True
        )
        if res.returncode != 0:
            return f"cannot create a bridge: {res.stderr.strip()}"
    finally:
        run(["ip", "netns", "del", ns], check=False, capture=True)
    try:
        apt_source()
    except TestbedError as e:
        return str(e)
    return None


# --- rootfs ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class AptSource:
    uri: str
    keyring: str | None


def _sources_entries() -> list[dict[str, str]]:
    """Every `deb` entry of the machine's apt configuration, one-line and deb822 forms."""
    out: list[dict[str, str]] = []
    files = [Path("/etc/apt/sources.list")]
    d = Path("/etc/apt/sources.list.d")
    if d.is_dir():
        files += sorted(d.glob("*.list")) + sorted(d.glob("*.sources"))
    for f in files:
        if not f.is_file():
            continue
        text = f.read_text(encoding="utf-8", errors="replace")
        if f.suffix == ".sources":
            for stanza in re.split(r"\n\s*\n", text):
                fields: dict[str, str] = {}
                for line in stanza.splitlines():
                    m = re.match(r"^([A-Za-z-]+):\s*(.*)$", line)
                    if m and not line.startswith("#"):
                        fields[m[1].lower()] = m[2].strip()
                if (
                    "deb" in fields.get("types", "").split()
                    and fields.get("enabled", "yes").lower() != "no"
                ):
                    out.append(fields)
        else:
            for line in text.splitlines():
                m = re.match(r"^\s*deb\s+(\[[^\]]*\]\s+)?(\S+)\s+(\S+)\s+(.*)$", line)
                if m:
                    opts = dict(re.findall(r"([\w-]+)=(\S+)", m[1] or ""))
                    out.append(
                        {
                            "uris": m[2],
                            "suites": m[3],
                            "components": m[4],
                            "signed-by": opts.get("signed-by", ""),
                        }
                    )
    return out


def apt_source() -> AptSource:
    """The machine's apt source for Debian bookworm main, read at run time (never stored)."""
    override = os.environ.get("BGT_TESTBED_MIRROR")
    if override:
        return AptSource(override, None)
    for e in _sources_entries():
        if SUITE in e.get("suites", "").split() and "main" in e.get("components", "").split():
            key = e.get("signed-by") or None
            return AptSource(e["uris"].split()[0], key if key and Path(key).is_file() else None)
    raise TestbedError(
        f"no apt source for Debian {SUITE} main in /etc/apt (set BGT_TESTBED_MIRROR)"
    )


def rootfs_key() -> str:
    arch = run(["dpkg", "--print-architecture"], capture=True).stdout.strip()
    blob = json.dumps({"suite": SUITE, "arch": arch, "packages": PACKAGES, "recipe": RECIPE})
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def rootfs_path() -> Path:
    return CACHE / f"rootfs-{rootfs_key()}"


def _write(path: Path, text: str, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    path.chmod(mode)


def _customise(root: Path) -> None:
    """Turn the debootstrapped tree into a bootable container image (no chroot needed)."""
    # chronyd cannot set the clock in a container: -x keeps it serving and measuring without
    # touching the clock, and the capability condition would otherwise skip the unit.
    _write(root / "etc/default/chrony", 'DAEMON_OPTS="-F 1 -x"\n')
    _write(
        root / "etc/systemd/system/chrony.service.d/container.conf",
        "[Unit]\nConditionCapability=\n",
    )
    # Each host gets its own host keys and machine id when it is created.
    for k in (root / "etc/ssh").glob("ssh_host_*"):
        k.unlink()
    _write(root / "etc/machine-id", "")
    _write(
        root / "etc/ssh/sshd_config.d/testbed.conf",
        "PasswordAuthentication no\nPermitRootLogin prohibit-password\nUseDNS no\n",
    )
    # No periodic apt work or consoles to wait for in the test bed.
    for unit in (
        "apt-daily.timer",
        "apt-daily-upgrade.timer",
        "getty@tty1.service",
        "systemd-networkd-wait-online.service",
    ):
        link = root / "etc/systemd/system" / unit
        link.unlink(missing_ok=True)
        link.symlink_to("/dev/null")
    _write(root / "etc/apt/apt.conf.d/99testbed", 'Acquire::Retries "0";\n')
    # The address comes from the namespace, configured from outside before boot.
    _write(root / "etc/network/interfaces", "auto lo\niface lo inet loopback\n")


def build_rootfs(force: bool = False) -> tuple[Path, float, bool]:
    """The cached root file system: (path, seconds taken, built now?)."""
    dest = rootfs_path()
    if dest.is_dir() and not force:
        log.info("rootfs cached: %s", dest)
        return dest, 0.0, False
    src = apt_source()
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = CACHE / f"{dest.name}.tmp{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    argv = [
        "debootstrap",
        "--variant=minbase",
        f"--include={','.join(PACKAGES)}",
        SUITE,
        str(tmp),
        src.uri,
    ]
    if src.keyring:
        argv.insert(1, f"--keyring={src.keyring}")
    log.info("debootstrap %s (a few minutes the first time)", SUITE)
    t0 = time.monotonic()
    try:
        res = run(argv, check=False, capture=True)
        if res.returncode != 0:
            tail = res.stdout.strip().splitlines()[-3:] + res.stderr.strip().splitlines()[-3:]
            raise TestbedError(f"debootstrap failed: {' | '.join(tail)}")
        _customise(tmp)
        # Drop downloaded packages: the cache keeps only the tree.
        for deb in (tmp / "var/cache/apt/archives").glob("*.deb"):
            deb.unlink()
        if force and dest.exists():
            shutil.rmtree(dest)
        tmp.rename(dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    took = time.monotonic() - t0
    log.info("rootfs built in %.0f s: %s", took, dest)
    return dest, took, True


# --- up / down ------------------------------------------------------------------------------


def hostdir(h: Host) -> Path:
    return STATE / "hosts" / h.name


def merged(h: Host) -> Path:
    """The host's root directory as seen from this machine (while it is up)."""
    return hostdir(h) / "root"


def _netns_exists(name: str) -> bool:
    return Path("/run/netns", name).exists()


def _setup_network() -> None:
    if not _netns_exists(CONTROL_NS):
        run(["ip", "netns", "add", CONTROL_NS])
    ip = ["ip", "-n", CONTROL_NS]
    run([*ip, "link", "set", "lo", "up"])
    if run([*ip, "link", "show", BRIDGE], check=False, capture=True).returncode != 0:
        run([*ip, "link", "add", BRIDGE, "type", "bridge"])
        run([*ip, "addr", "add", f"{NET}.1/24", "dev", BRIDGE])
    run([*ip, "link", "set", BRIDGE, "up"])
    for h in HOSTS:
        if not _netns_exists(h.netns):
            run(["ip", "netns", "add", h.netns])
        hip = ["ip", "-n", h.netns]
        run([*hip, "link", "set", "lo", "up"])
        if run([*hip, "link", "show", "host0"], check=False, capture=True).returncode != 0:
            run(
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
                    CONTROL_NS,
                ]
            )
            run([*hip, "addr", "add", f"{h.address}/24", "dev", "host0"])
            run([*ip, "link", "set", h.veth, "master", BRIDGE])
        run([*hip, "link", "set", "host0", "up"])
        run([*ip, "link", "set", h.veth, "up"])


def _prepare_host(h: Host, lower: Path) -> None:
    d = hostdir(h)
    for sub in ("upper", "work", "root"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    root = merged(h)
    if not os.path.ismount(root):
        run(
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
    _write(root / "etc/hostname", h.name + "\n")
    hosts = "127.0.0.1 localhost\n" + "".join(f"{x.address} {x.name}\n" for x in HOSTS)
    _write(root / "etc/hosts", hosts)
    if not (root / "etc/machine-id").read_text().strip():
        _write(root / "etc/machine-id", uuid.uuid4().hex + "\n", 0o444)
    if not (root / "etc/ssh/ssh_host_ed25519_key").exists():
        run(
            [
                "ssh-keygen",
                "-q",
                "-t",
                "ed25519",
                "-N",
                "",
                "-C",
                h.name,
                "-f",
                str(root / "etc/ssh/ssh_host_ed25519_key"),
            ]
        )
    ak = root / "root/.ssh/authorized_keys"
    _write(ak, (STATE / "id_ed25519.pub").read_text(), 0o600)
    ak.parent.chmod(0o700)


def _ssh_args() -> list[str]:
    return [
        "-i",
        str(STATE / "id_ed25519"),
        "-o",
        f"UserKnownHostsFile={STATE / 'known_hosts'}",
        "-o",
        "StrictHostKeyChecking=yes",
        "-o",
        "BatchMode=yes",
        "-o",
        "ConnectTimeout=5",
        "-o",
        "LogLevel=ERROR",
    ]


def _write_inventory() -> Path:
    lines = [
        "# Written by deploy/testbed/bgt_testbed.py: the test bed's fleet.",
        "all:",
        "  vars:",
        "    ansible_user: root",
        f"    ansible_ssh_private_key_file: {STATE / 'id_ed25519'}",
        f'    ansible_ssh_common_args: "-o UserKnownHostsFile={STATE / "known_hosts"}'
        ' -o StrictHostKeyChecking=yes -o ConnectTimeout=10"',
        "    ansible_python_interpreter: /usr/bin/python3",
        "    bgt_site: testbed",
        f"    bgt_lan_cidr: {NET}.0/24",
        "    bgt_pki_dir: pki",
        "  children:",
        "    collector:",
        "      hosts:",
    ]
    for h in HOSTS:
        if h.role == "collector":
            lines += [f"        {h.name}:", f"          ansible_host: {h.address}"]
    lines += [
        "    agents:",
        "      vars:",
        "        bgt_backend: simulated",
        "        bgt_sim_site: tetam",
        "      hosts:",
    ]
    for h in HOSTS:
        if h.role == "agent":
            lines += [
                f"        {h.name}:",
                f"          ansible_host: {h.address}",
                f"          agent_id: {h.agent_id}",
                "          adapters: []",
                f"          bgt_sim_sensors: {json.dumps(SIM_SENSORS[h.agent_id])}",
            ]
    inv = STATE / "inventory.yml"
    _write(inv, "\n".join(lines) + "\n")
    return inv


# Supervisors this process started (reaped when stopped).
_SUPERVISORS: dict[int, subprocess.Popen[bytes]] = {}


def pidfile(h: Host) -> Path:
    return hostdir(h) / "supervisor.pid"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _running(h: Host) -> int | None:
    try:
        pid = int(pidfile(h).read_text())
    except (OSError, ValueError):
        return None
    return pid if _alive(pid) else None


def nspawn_argv(h: Host) -> list[str]:
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
    h = host(name)
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


def wait_ssh(h: Host, timeout: float = 180.0) -> None:
    end = time.monotonic() + timeout
    while True:
        res = ssh(h, ["systemctl", "is-system-running", "--wait"], check=False, timeout=120)
        if res.returncode == 0 or res.stdout.strip() in ("running", "degraded"):
            return
        if time.monotonic() > end:
            raise TestbedError(
                f"{h.name} did not come up in {timeout:.0f} s (see {hostdir(h) / 'console.log'})"
            )
        if _running(h) is None:
            raise TestbedError(f"{h.name}: container exited (see {hostdir(h) / 'console.log'})")
        time.sleep(1.0)


def start_host(h: Host) -> None:
    if _running(h):
        return
    with open(hostdir(h) / "supervisor.log", "ab") as out:
        proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve()), "_supervise", h.name],
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "BGT_TESTBED_STATE": str(STATE)},
        )
    _SUPERVISORS[proc.pid] = proc
    _write(pidfile(h), f"{proc.pid}\n")


def stop_host(h: Host, timeout: float = 90.0) -> None:
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
    lower, _took, _built = build_rootfs()
    STATE.mkdir(parents=True, exist_ok=True)
    if not (STATE / "id_ed25519").exists():
        run(
            [
                "ssh-keygen",
                "-q",
                "-t",
                "ed25519",
                "-N",
                "",
                "-C",
                "bgt-testbed",
                "-f",
                str(STATE / "id_ed25519"),
            ]
        )
    _setup_network()
    known = []
    for h in HOSTS:
        _prepare_host(h, lower)
        pub = (merged(h) / "etc/ssh/ssh_host_ed25519_key.pub").read_text().split()
        known.append(f"{h.address},{h.name} {pub[0]} {pub[1]}\n")
    _write(STATE / "known_hosts", "".join(known))
    t1 = time.monotonic()
    for h in HOSTS:
        start_host(h)
    for h in HOSTS:
        wait_ssh(h)
    inv = _write_inventory()
    figures = {"prepare_s": t1 - t0, "boot_s": time.monotonic() - t1}
    log.info(
        "up: %s booted in %.0f s; inventory %s",
        ", ".join(h.name for h in HOSTS),
        figures["boot_s"],
        inv,
    )
    return figures


def down() -> None:
    for h in HOSTS:
        stop_host(h)
    for h in HOSTS:
        root = merged(h)
        if os.path.ismount(root):
            run(["umount", str(root)], check=False)
            if os.path.ismount(root):
                run(["umount", "-l", str(root)], check=False)
        if _netns_exists(h.netns):
            run(["ip", "netns", "del", h.netns], check=False)
    if _netns_exists(CONTROL_NS):
        run(["ip", "netns", "del", CONTROL_NS], check=False)


# --- use ------------------------------------------------------------------------------------


def in_control_ns(argv: list[str]) -> list[str]:
    """Prefix argv so that it runs on the test bed's network (the control address)."""
    return ["ip", "netns", "exec", CONTROL_NS, *argv]


def ssh(
    h: Host,
    argv: list[str],
    *,
    check: bool = True,
    timeout: float = 120,
    input_text: str | None = None,
) -> subprocess.CompletedProcess[str]:
    # ssh hands the remote shell one string: quote, so that argv arrives as it is here.
    cmd = in_control_ns(["ssh", *_ssh_args(), f"root@{h.address}", "--", shlex.join(argv)])
    res = subprocess.run(
        cmd, text=True, capture_output=True, timeout=timeout, check=False, input=input_text
    )
    if check and res.returncode != 0:
        raise TestbedError(
            f"{h.name}: {' '.join(argv)} exited {res.returncode}: "
            f"{(res.stderr or res.stdout).strip()[-400:]}"
        )
    return res


def ansible_playbook() -> str:
    exe = Path(sys.executable).parent / "ansible-playbook"
    found = str(exe) if exe.exists() else shutil.which("ansible-playbook")
    if not found:
        raise TestbedError("no ansible-playbook (pip install 'ble-groundtruth[deploy]')")
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
        run(
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
    run(
        [
            sys.executable,
            "-m",
            "deploy",
            "wheelhouse",
            "--src",
            str(REPO),
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
    inv = inventory or STATE / "inventory.yml"
    prebuild_wheelhouse(inv)
    env = {
        **os.environ,
        "ANSIBLE_CONFIG": str(REPO / "deploy/ansible.cfg"),
        "ANSIBLE_NOCOLOR": "1",
        "ANSIBLE_FORCE_COLOR": "0",
        "PATH": f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}",
        # The control namespace has no route to any package index: pip uses local files only.
        "PIP_NO_INDEX": "1",
        "PIP_FIND_LINKS": f"{inv.parent / 'build/build-tools'} {inv.parent / 'build/wheelhouse'}",
    }
    argv = in_control_ns([ansible_playbook(), "-i", str(inv), playbook, *extra])
    t0 = time.monotonic()
    res = subprocess.run(
        argv,
        cwd=REPO / "deploy",
        env=env,
        text=True,
        capture_output=True,
        check=False,
        timeout=1800,
    )
    took = time.monotonic() - t0
    out = res.stdout + res.stderr
    return PlaybookResult(res.returncode, took, out, parse_recap(out))


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
            why = missing_capability()
            if why:
                log.error("cannot boot the test bed: %s", why)
                return 1
            log.info("this machine can boot the test bed (rootfs %s)", rootfs_path())
        elif a.cmd == "rootfs":
            path, took, built = build_rootfs(a.force)
            if built:
                log.info("built in %.0f s: %s", took, path)
            else:
                log.info("cached: %s", path)
        elif a.cmd == "up":
            log.info("%s", json.dumps(up()))
        elif a.cmd == "deploy":
            res = deploy(a.args)
            sys.stdout.write(res.output)
            log.info("playbook exit %d in %.1f s", res.returncode, res.seconds)
            return res.returncode
        elif a.cmd == "ssh":
            h = host(a.host)
            cmd = in_control_ns(["ssh", *_ssh_args(), f"root@{h.address}", "--", *a.command])
            return subprocess.run(cmd, check=False).returncode
        elif a.cmd == "down":
            down()
        elif a.cmd == "_supervise":
            return supervise(a.host)
    except TestbedError as e:
        log.error("%s", e)  # noqa: TRY400 - one line for the user, no traceback
        return 1
    return 0


__all__ = [
    "HOSTS",
    "Host",
    "PlaybookResult",
    "TestbedError",
    "asdict",
    "build_rootfs",
    "deploy",
    "down",
    "host",
    "merged",
    "missing_capability",
    "ssh",
    "up",
]

if __name__ == "__main__":
    sys.exit(main())
