"""Each role's extra alone is enough for that role. One wheel of the project is built; a fresh
venv per extra installs it with `[agent]`, `[collector]`, `[annotator]` or `[deploy]` only (the
four installs run at once). In each venv: every third-party module the role's code imports
anywhere imports (the collector extra once lacked `cryptography`, imported only when a TLS config
is checked), the role's command answers `--help`, its config check accepts a real config (mutual
TLS for the collector and the agent) and refuses a broken one in one line.

The installs need the package index pip is configured with (CI's pip cache is warm from
installing `.[dev]`). Without it they fail with pip's own reason: nothing is skipped.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import venv
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import yaml

import import_closure
from deploy import pki
from deploy.acl import build_acl

REPO = Path(__file__).resolve().parents[2]
# extra -> the package (and sub-packages left to another role) its venv must import whole
EXTRAS = {
    "agent": "sensor_agent",
    "collector": "collector -collector.web",
    "annotator": "annotator -annotator.dataset",
    "dataset": "annotator.dataset",
    "deploy": "deploy",
    "web": "collector.web",
}
PIP = ("-m", "pip", "--disable-pip-version-check")


def clean_env() -> dict[str, str]:
    """This environment without PYTHONPATH: a checkout on it would stand in for the install."""
    return {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def run(argv: list[str], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        argv, cwd=cwd, env=clean_env(), capture_output=True, text=True, timeout=timeout, check=False
    )


def build_wheel(out: Path) -> Path:
    """The project wheel, made the way the playbook makes it (`python -m deploy wheel`)."""
    res = subprocess.run(
        [sys.executable, "-m", "deploy", "wheel", "--src", str(REPO), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert res.returncode == 0, f"building the project wheel failed:\n{res.stderr[-3000:]}"
    return Path(res.stdout.splitlines()[-2])


def install(where: Path, wheel: Path, extra: str) -> Path | str:
    """A fresh venv with ``wheel[extra]`` installed: its bin folder, or what went wrong. This
    pip installs into it (``--python``): no second pip to bootstrap, the same cache; no .pyc
    compiling (the venv is thrown away)."""
    venv.create(where, with_pip=False)
    py = where / "bin" / "python"
    res = run(
        [
            sys.executable,
            *PIP,
            "--python",
            str(py),
            "install",
            "-q",
            "--no-compile",
            f"{wheel}[{extra}]",
        ],
        cwd=where,
        timeout=600,
    )
    if res.returncode != 0:
        return (
            f"pip could not install the project with [{extra}] in a fresh venv (this test needs "
            f"the package index pip is configured with, or a warm pip cache):\n"
            f"{res.stderr.strip()[-3000:]}"
        )
    return where / "bin"


@pytest.fixture(scope="module")
def venvs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Path | str]]:
    root = tmp_path_factory.mktemp("extras")
    wheel = build_wheel(root / "wheel")
    with ThreadPoolExecutor(len(EXTRAS)) as pool:
        jobs = {extra: pool.submit(install, root / extra, wheel, extra) for extra in EXTRAS}
        got = {extra: job.result() for extra, job in jobs.items()}
    yield got
    with ThreadPoolExecutor(len(EXTRAS)) as pool:  # four venvs, over a GB: unlink them at once
        list(pool.map(lambda d: shutil.rmtree(d, ignore_errors=True), root.iterdir()))


def bin_of(venvs: dict[str, Path | str], extra: str) -> Path:
    got = venvs[extra]
    assert isinstance(got, Path), got
    return got


def one_line_error(res: subprocess.CompletedProcess[str], *words: str) -> str:
    assert res.returncode == 1, (res.returncode, res.stdout, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert all(w in lines[0] for w in words), lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A site PKI (CA, collector, operator, pi-01) and the collector's ACL, as deploy makes them."""
    d = tmp_path_factory.mktemp("site")
    now = dt.datetime.now(dt.UTC)
    pki.issue(d / "tls", "collector", ["collector", "localhost", "127.0.0.1"], now)
    for cn in ("operator", "pi-01"):
        pki.issue(d / "tls", cn, [cn], now)
    (d / "acl.json5").write_text(
        json.dumps(build_acl("default", ["pi-01"], ["collector", "operator"]))
    )
    return d


@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("extra", EXTRAS)
def test_the_extra_installs_every_module_its_role_imports(venvs, extra, tmp_path) -> None:
    bin_dir = bin_of(venvs, extra)
    res = run(
        [str(bin_dir / "python"), import_closure.__file__, *EXTRAS[extra].split()], cwd=tmp_path
    )
    assert res.returncode == 0, (
        f"[{extra}] misses modules its code imports:\n{res.stdout}{res.stderr}"
    )
    found = json.loads(res.stdout)
    # The installed package was checked, not the checkout.
    assert Path(found["package_dir"]).is_relative_to(bin_dir.parent), found["package_dir"]
    assert found["missing"] == {}


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_collector_extra_help_and_tls_config_check(venvs, site) -> None:
    collector = str(bin_of(venvs, "collector") / "collector")
    res = run([collector, "--help"], cwd=site)
    assert res.returncode == 0, res.stderr
    assert "serve" in res.stdout
    assert "start" in res.stdout

    conf = {
        "site": "default",
        "data_dir": "data",
        "listen": ["tls/127.0.0.1:7447"],
        "tls": {"root_ca": "tls/ca.crt", "cert": "tls/collector.crt", "key": "tls/collector.key"},
        "insecure": False,
        "acl": "acl.json5",
    }
    (site / "collector.yaml").write_text(yaml.safe_dump(conf))
    res = run([collector, "serve", "--config", "collector.yaml", "--check"], cwd=site)
    assert res.returncode == 0, res.stderr
    resolved = json.loads(res.stdout)
    assert resolved["tls"]["key"].endswith("collector.key")
    assert resolved["listen"] == ["tls/127.0.0.1:7447"]
    assert not (site / "data").exists()  # a check records nothing

    # The certificate where the key belongs: read with cryptography, refused in one line.
    conf["tls"]["key"] = "tls/collector.crt"
    (site / "collector_bad.yaml").write_text(yaml.safe_dump(conf))
    res = run([collector, "serve", "--config", "collector_bad.yaml", "--check"], cwd=site)
    one_line_error(res, "tls.key", "not a usable PEM file")

    # The console is the web extra's: without it, one line saying what to install.
    res = run([collector, "web"], cwd=site)
    one_line_error(res, "collector web needs the web extra", "pip install")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_agent_extra_help_and_tls_config_check(venvs, site) -> None:
    agent = str(bin_of(venvs, "agent") / "sensor-agent")
    res = run([agent, "--help"], cwd=site)
    assert res.returncode == 0, res.stderr
    assert "run" in res.stdout
    assert "check" in res.stdout

    conf = {
        "agent_id": "pi-01",
        "site": "default",
        "connect": ["tls/127.0.0.1:7447"],
        "backend": "simulated",
        "spool": {"dir": "spool", "max_mb": 16},
        "tls": {"root_ca": "tls/ca.crt", "cert": "tls/pi-01.crt", "key": "tls/pi-01.key"},
    }
    (site / "agent.yaml").write_text(yaml.safe_dump(conf))
    res = run([agent, "check", "--config", "agent.yaml"], cwd=site)
    assert res.returncode == 0, res.stderr
    resolved = yaml.safe_load(res.stdout)
    assert resolved["agent_id"] == "pi-01"
    assert resolved["backend"] == "simulated"
    assert resolved["tls"]["cert"].endswith("pi-01.crt")

    (site / "agent_bad.yaml").write_text(yaml.safe_dump({**conf, "batch_ms": -5}))
    res = run([agent, "check", "--config", "agent_bad.yaml"], cwd=site)
    one_line_error(res, "batch_ms")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_annotator_extra_help_and_experiment_check(venvs, tmp_path) -> None:
    """The annotator has no separate config check: `track` loads and validates experiment.yaml
    (rig, calibrations, marker map, videos) before it reads a frame, so a tiny rendered experiment
    is tracked for a few frames, and a broken one is refused in one line."""
    annotator = str(bin_of(venvs, "annotator") / "annotator")
    res = run([annotator, "--help"], cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "track" in res.stdout
    assert "simulate" in res.stdout

    res = run(
        [
            annotator,
            "simulate",
            "--out",
            "exp",
            "--duration",
            "2",
            "--width",
            "320",
            "--height",
            "180",
        ],
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    res = run(
        [annotator, "track", "exp/experiment.yaml", "--out", "tr", "--max-frames", "10"],
        cwd=tmp_path,
        timeout=300,
    )
    assert res.returncode == 0, res.stderr
    with (tmp_path / "tr" / "trajectory.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows, "no trajectory rows"
    assert any(r["x"] for r in rows), "no frame gave a pose"

    exp = yaml.safe_load((tmp_path / "exp" / "experiment.yaml").read_text())
    del exp["markers"]
    (tmp_path / "exp" / "broken.yaml").write_text(yaml.safe_dump(exp))
    res = run([annotator, "track", "exp/broken.yaml", "--out", "tr2"], cwd=tmp_path)
    one_line_error(res, "markers")
    # building a dataset on Dask is the dataset extra's: without it, one line
    res = run([annotator, "dataset", "build", "c.yaml", "--out", "ds"], cwd=tmp_path)
    one_line_error(res, "needs Dask", "pip install")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_deploy_extra_help_and_inventory_check(venvs, tmp_path) -> None:
    """The operator's tools: the example inventory yields a site PKI and the collector's ACL."""
    py = str(bin_of(venvs, "deploy") / "python")
    res = run([py, "-m", "deploy", "--help"], cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "pki" in res.stdout
    assert "acl" in res.stdout

    shutil.copy(REPO / "deploy" / "inventory.example.yml", tmp_path / "inventory.yml")
    res = run([py, "-m", "deploy", "pki", "--inventory", "inventory.yml"], cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines()[-1] == "changed"
    for cn in ("ca", "collector", "operator", "pi-01", "pi-02", "pi-03"):
        assert (tmp_path / "pki" / f"{cn}.crt").is_file(), cn
    res = run(
        [py, "-m", "deploy", "acl", "--inventory", "inventory.yml", "--out", "acl.json5"],
        cwd=tmp_path,
    )
    assert res.returncode == 0, res.stderr
    assert "pi-03" in (tmp_path / "acl.json5").read_text()

    (tmp_path / "broken.yml").write_text("all: [not, a, mapping]\n")
    res = run(
        [py, "-m", "deploy", "acl", "--inventory", "broken.yml", "--out", "acl2.json5"],
        cwd=tmp_path,
    )
    one_line_error(res, "broken.yml")
    assert not (tmp_path / "acl2.json5").exists()


# -- the import scan itself (fast) ---------------------------------------------------------------


def _package(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)


def test_import_scan_finds_imports_inside_functions_and_through_project_modules(tmp_path) -> None:
    _package(
        tmp_path,
        {
            "collector/__init__.py": "",
            "collector/config.py": (
                "import json\nfrom . import util\n\n"
                "def check():\n    from cryptography import x509\n"
            ),
            "collector/util.py": "from bgt_core.tls import load\n",
            "bgt_core/__init__.py": "",
            "bgt_core/tls.py": "import os\n\ndef load():\n    import not_installed_xyz.sub\n",
            "bgt_core/unused.py": "import never_reached_xyz\n",
        },
    )
    found = import_closure.third_party_imports(tmp_path, "collector")
    assert found == {"cryptography": "collector.config", "not_installed_xyz": "bgt_core.tls"}


def test_import_scan_leaves_out_optional_and_type_checking_imports(tmp_path) -> None:
    _package(
        tmp_path,
        {
            "annotator/__init__.py": (
                "try:\n    import optional_xyz\nexcept ImportError:\n"
                "    optional_xyz = None\nimport numpy\n"
            ),
            "annotator/types.py": (
                "import typing\nfrom typing import TYPE_CHECKING\n"
                "if TYPE_CHECKING:\n    import pandas\n"
                "if typing.TYPE_CHECKING:\n    from scipy import stats\n"
            ),
        },
    )
    assert import_closure.third_party_imports(tmp_path, "annotator") == {"numpy": "annotator"}


def test_import_scan_reports_a_module_that_does_not_import(tmp_path, monkeypatch) -> None:
    _package(tmp_path, {"deploy_probe_xyz/__init__.py": "def f():\n    import not_installed_xyz\n"})
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(import_closure, "PROJECT", ("deploy_probe_xyz",))
    folder, missing = import_closure.missing_imports("deploy_probe_xyz")
    assert folder == tmp_path / "deploy_probe_xyz"
    assert list(missing) == ["not_installed_xyz"]
    assert missing["not_installed_xyz"].startswith("deploy_probe_xyz: ModuleNotFoundError")
