"""The systemd units: `systemd-analyze verify` accepts them and the offline security score is low."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
UNITS = ("sensor-agent.service", "collector.service")
MAX_EXPOSURE = 4.5

pytestmark = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="needs systemd-analyze"
)


def _system_unit_dir() -> Path:
    for d in (Path("/usr/lib/systemd/system"), Path("/lib/systemd/system")):
        if (d / "sysinit.target").exists():
            return d
    pytest.skip("no systemd unit directory on this machine")


@pytest.fixture
def root(tmp_path: Path) -> Path:
    """A throw-away root holding the host's stock units, ours, and stand-ins for the venv
    executables, so `verify --root` checks the unit files exactly as shipped."""
    shutil.copytree(_system_unit_dir(), tmp_path / "usr/lib/systemd/system", symlinks=True)
    bindir = tmp_path / "opt/ble-groundtruth/venv/bin"
    bindir.mkdir(parents=True)
    for exe in ("sensor-agent", "collector"):
        (bindir / exe).write_text("#!/bin/sh\n")
        (bindir / exe).chmod(0o755)
    (tmp_path / "etc/systemd/system").mkdir(parents=True)
    return tmp_path


def verify(root: Path, unit_text: str, name: str) -> subprocess.CompletedProcess[str]:
    (root / "etc/systemd/system" / name).write_text(unit_text)
    return subprocess.run(
        ["systemd-analyze", "verify", f"--root={root}", name],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.parametrize("unit", UNITS)
def test_unit_verifies_cleanly(root: Path, unit: str) -> None:
    res = verify(root, (REPO / "systemd" / unit).read_text(), unit)
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip() == "", res.stderr  # not even warnings (unknown keys, etc.)


def test_verify_catches_a_broken_unit(root: Path) -> None:
    # The check above must be able to fail: a relative ExecStart is rejected.
    text = (REPO / "systemd/collector.service").read_text()
    text = text.replace(
        "ExecStart=/opt/ble-groundtruth/venv/bin/collector", "ExecStart=collector-nowhere"
    )
    res = verify(root, text, "collector.service")
    assert res.returncode != 0
    assert "collector-nowhere" in res.stderr


@pytest.mark.parametrize("unit", UNITS)
def test_security_exposure_is_at_most_4_5(unit: str) -> None:
    res = subprocess.run(
        [
            "systemd-analyze",
            "security",
            "--offline=yes",
            "--no-pager",
            str(REPO / "systemd" / unit),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", res.stdout)
    assert m, res.stdout + res.stderr
    score = float(m.group(1))
    print(f"{unit}: systemd-analyze security exposure {score}")
    assert score <= MAX_EXPOSURE


@pytest.mark.parametrize("unit", UNITS)
def test_unit_has_the_contracted_settings(unit: str) -> None:
    text = (REPO / "systemd" / unit).read_text()
    settings = {}
    for line in text.splitlines():
        if "=" in line and not line.startswith("#"):
            key, _, value = line.partition("=")
            settings.setdefault(key, []).append(value)
    assert settings["Type"] == ["notify"]
    assert settings["Restart"] == ["always"]
    assert settings["KillSignal"] == ["SIGINT"]
    assert settings["StateDirectory"] == ["ble-groundtruth"]
    assert "/etc/ble-groundtruth/" in settings["ExecStart"][0]
    assert int(settings["WatchdogSec"][0]) > 0
    families = set(settings["RestrictAddressFamilies"][0].split())
    assert {"AF_UNIX", "AF_INET", "AF_INET6"} <= families
    assert ("AF_BLUETOOTH" in families) == (unit == "sensor-agent.service")
    if unit == "sensor-agent.service":
        assert settings["SupplementaryGroups"] == ["bluetooth"]
        assert "bluetooth.service" in settings["After"][0]
    assert "network-online.target" in settings["After"][0]
    # Bounded resources (issue 11): descriptors, memory (throttled before killed), threads, and
    # a stop timeout that fits the collector's worst-case drain (60 s stop + closing files).
    limits = {
        k: settings[k]
        for k in ("LimitNOFILE", "MemoryHigh", "MemoryMax", "TasksMax", "TimeoutStopSec")
    }
    if unit == "collector.service":
        assert limits == {
            "LimitNOFILE": ["4096"],
            "MemoryHigh": ["512M"],
            "MemoryMax": ["768M"],
            "TasksMax": ["256"],
            "TimeoutStopSec": ["120"],
        }
    else:
        assert limits == {
            "LimitNOFILE": ["1024"],
            "MemoryHigh": ["256M"],
            "MemoryMax": ["384M"],
            "TasksMax": ["128"],
            "TimeoutStopSec": ["45"],
        }
