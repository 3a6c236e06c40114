"""`python -m deploy wheelhouse` (the offline install set the playbook copies) and
`pki --no-issue` (a CA kept elsewhere: a missing certificate is named, not made)."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def deploy_cli(*argv: str, timeout: float = 280) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "deploy", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.fixture(scope="module")
def house(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("wheelhouse") / "wh"
    res = deploy_cli("wheelhouse", "--src", str(REPO), "--out", str(out), "--extras", "agent")
    assert res.returncode == 0, res.stderr
    name, where, state = res.stdout.splitlines()[-3:]
    assert Path(where) == out
    assert state == "changed"
    return out, name


@pytest.mark.slow
def test_wheelhouse_holds_the_project_and_its_dependencies(house: tuple[Path, str]) -> None:
    out, name = house
    names = sorted(f.name for f in out.glob("*.whl"))
    assert name in names
    assert name.startswith("ble_groundtruth-")
    for dep in ("eclipse_zenoh-", "pyyaml-", "bleak-", "dbus_fast-", "typer-", "rich-"):
        assert any(n.lower().startswith(dep) for n in names), (dep, names)
    # The collector-only dependency is not pulled in for the agent extra alone.
    assert not any(n.startswith("cryptography-") for n in names)
    listed = dict(
        reversed(line.split("  ", 1)) for line in (out / "SHA256SUMS").read_text().splitlines()
    )
    assert sorted(listed) == names
    for n, digest in listed.items():
        assert hashlib.sha256((out / n).read_bytes()).hexdigest() == digest


@pytest.mark.slow
def test_rerun_is_unchanged_and_stale_wheels_go(house: tuple[Path, str]) -> None:
    out, _ = house
    res = deploy_cli("wheelhouse", "--src", str(REPO), "--out", str(out), "--extras", "agent")
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1] == "unchanged"
    stale = out / "ble_groundtruth-0.0.1-py3-none-any.whl"
    shutil.copy(out / "SHA256SUMS", stale)  # any file: it is not part of the set
    res = deploy_cli("wheelhouse", "--src", str(REPO), "--out", str(out), "--extras", "agent")
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1] == "changed"
    assert not stale.exists()
    assert "0.0.1" not in (out / "SHA256SUMS").read_text()


@pytest.mark.slow
def test_agent_installs_from_the_wheelhouse_without_an_index(
    house: tuple[Path, str], tmp_path: Path
) -> None:
    out, name = house
    venv.create(tmp_path / "v", with_pip=True)
    py = tmp_path / "v" / "bin" / "python"
    # No pip configuration (this machine's may name extra wheel folders): the wheelhouse only;
    # no PYTHONPATH (a checkout on it would look like an installed project to pip).
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PIP_CONFIG_FILE"] = os.devnull
    res = subprocess.run(
        [str(py), "-m", "pip", "install", "-q", "--no-index", "--find-links", str(out),
         f"{out / name}[agent]"],
        capture_output=True, text=True, timeout=280, check=False, env=env,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    res = subprocess.run(
        [str(tmp_path / "v" / "bin" / "sensor-agent"), "--help"],
        capture_output=True, text=True, timeout=60, check=False, env=env,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "run" in res.stdout


def test_wheelhouse_of_a_non_project_fails_in_one_line(tmp_path: Path) -> None:
    res = deploy_cli("wheelhouse", "--src", str(tmp_path), "--out", str(tmp_path / "wh"))
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "no pyproject.toml" in lines[0]
    assert not (tmp_path / "wh").exists()


def test_pki_no_issue_names_the_missing_certificate(tmp_path: Path) -> None:
    shutil.copy(REPO / "deploy" / "inventory.example.yml", tmp_path / "inventory.yml")
    inv = str(tmp_path / "inventory.yml")
    res = deploy_cli("pki", "--inventory", inv)
    assert res.returncode == 0, res.stderr
    res = deploy_cli("pki", "--inventory", inv, "--no-issue")
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1] == "unchanged"
    (tmp_path / "pki" / "pi-02.key").unlink()
    res = deploy_cli("pki", "--inventory", inv, "--no-issue")
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert "pi-02.key (for pi-02) is missing" in lines[0]
    assert not (tmp_path / "pki" / "pi-02.key").exists()  # checked, not issued
