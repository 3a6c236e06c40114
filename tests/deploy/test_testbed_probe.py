"""The test bed's probe: where the machine cannot boot containers it names what is missing in one
line (the boot test then skips with that line)."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest

from testbed_loader import load_testbed

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def tb():
    mod = load_testbed("bgt_testbed_probe")
    yield mod
    del sys.modules["bgt_testbed_probe"]


def test_probe_names_a_missing_tool_and_its_package(tb, monkeypatch: pytest.MonkeyPatch) -> None:
    if os.geteuid() != 0:
        assert tb.missing_capability().startswith("not root")
        return
    real = shutil.which
    monkeypatch.setattr(
        tb.probe.shutil, "which", lambda name: None if name == "systemd-nspawn" else real(name)
    )
    why = tb.missing_capability()
    assert why == "no systemd-nspawn (Debian package systemd-container)"


def test_probe_names_a_missing_apt_source(tb, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("BGT_TESTBED_MIRROR", raising=False)
    monkeypatch.setattr(tb.rootfs, "_sources_entries", lambda: [])
    with pytest.raises(tb.TestbedError, match=r"no apt source for Debian bookworm main"):
        tb.apt_source()
