"""The hosts' root file system: debootstrap from this machine's own Debian mirror, made bootable,
cached under a key of its inputs."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

from deploy.testbed import config
from deploy.testbed.config import log


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
        if (
            config.SUITE in e.get("suites", "").split()
            and "main" in e.get("components", "").split()
        ):
            key = e.get("signed-by") or None
            return AptSource(e["uris"].split()[0], key if key and Path(key).is_file() else None)
    raise config.TestbedError(
        f"no apt source for Debian {config.SUITE} main in /etc/apt (set BGT_TESTBED_MIRROR)"
    )


def rootfs_key() -> str:
    arch = config.run(["dpkg", "--print-architecture"], capture=True).stdout.strip()
    blob = json.dumps(
        {"suite": config.SUITE, "arch": arch, "packages": config.PACKAGES, "recipe": config.RECIPE}
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def rootfs_path() -> Path:
    return config.CACHE / f"rootfs-{rootfs_key()}"


def _customise(root: Path) -> None:
    """Turn the debootstrapped tree into a bootable container image (no chroot needed)."""
    # chronyd cannot set the clock in a container: -x keeps it serving and measuring without
    # touching the clock, and the capability condition would otherwise skip the unit.
    config.write_file(root / "etc/default/chrony", 'DAEMON_OPTS="-F 1 -x"\n')
    config.write_file(
        root / "etc/systemd/system/chrony.service.d/container.conf",
        "[Unit]\nConditionCapability=\n",
    )
    # Each host gets its own host keys and machine id when it is created.
    for k in (root / "etc/ssh").glob("ssh_host_*"):
        k.unlink()
    config.write_file(root / "etc/machine-id", "")
    config.write_file(
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
    config.write_file(root / "etc/apt/apt.conf.d/99testbed", 'Acquire::Retries "0";\n')
    # The address comes from the namespace, configured from outside before boot.
    config.write_file(root / "etc/network/interfaces", "auto lo\niface lo inet loopback\n")


def build_rootfs(force: bool = False) -> tuple[Path, float, bool]:
    """The cached root file system: (path, seconds taken, built now?)."""
    dest = rootfs_path()
    if dest.is_dir() and not force:
        log.info("rootfs cached: %s", dest)
        return dest, 0.0, False
    src = apt_source()
    config.CACHE.mkdir(parents=True, exist_ok=True)
    tmp = config.CACHE / f"{dest.name}.tmp{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    argv = [
        "debootstrap",
        "--variant=minbase",
        f"--include={','.join(config.PACKAGES)}",
        config.SUITE,
        str(tmp),
        src.uri,
    ]
    if src.keyring:
        argv.insert(1, f"--keyring={src.keyring}")
    log.info("debootstrap %s (a few minutes the first time)", config.SUITE)
    t0 = time.monotonic()
    try:
        res = config.run(argv, check=False, capture=True)
        if res.returncode != 0:
            tail = res.stdout.strip().splitlines()[-3:] + res.stderr.strip().splitlines()[-3:]
            raise config.TestbedError(f"debootstrap failed: {' | '.join(tail)}")
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
