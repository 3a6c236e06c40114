"""``python -m deploy``: the control-node steps the Ansible playbook calls.

Each command is idempotent and says on its last line ``changed`` or ``unchanged`` so Ansible's
``changed_when`` can tell; known problems end as one red line and exit code 1.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from bgt_core.cli_help import flow_command_help
from deploy import pki
from deploy.acl import build_acl
from deploy.inventory import ADMIN_CNS, Fleet, InventoryError, load_inventory

app = typer.Typer(
    help="Fleet deployment helpers (site PKI, Zenoh ACL, project wheel, wheelhouse).",
    no_args_is_help=True,
)
err = Console(stderr=True, emoji=False)
MANIFEST = "SHA256SUMS"  # in a wheelhouse: `sha256  file` per wheel
REQUEST = "request.json"  # in a wheelhouse: the extras, platforms and Python it was made for

InventoryOpt = Annotated[
    Path,
    typer.Option("--inventory", "-i", help="The fleet's YAML inventory (deploy/inventory.yml)."),
]


def _fail(e: Exception) -> typer.Exit:
    # soft_wrap: one line however narrow the (non-)terminal, so Ansible shows it whole.
    err.print(f"[red]{e}[/red]", highlight=False, soft_wrap=True)
    return typer.Exit(1)


def _check_present(d: Path, fleet: Fleet) -> None:
    """Every file the playbook will copy exists; else PkiError naming the file and its host."""
    need = [("ca.crt", "every host"), ("collector.crt", fleet.collector_host)]
    need += [("collector.key", fleet.collector_host), ("operator.crt", fleet.collector_host)]
    need += [("operator.key", fleet.collector_host)]
    for a in fleet.agents:
        need += [(f"{a.agent_id}.crt", a.host), (f"{a.agent_id}.key", a.host)]
    for name, who in need:
        if not (d / name).is_file():
            raise pki.PkiError(
                f"certificate file {d / name} (for {who}) is missing, and issuing is off "
                "(bgt_issue_certs: false)"
            )


@app.command("pki")
def pki_cmd(
    inventory: InventoryOpt,
    out: Annotated[
        Path | None, typer.Option(help="PKI directory (default: bgt_pki_dir of the inventory).")
    ] = None,
    issue: Annotated[
        bool,
        typer.Option(
            "--issue/--no-issue",
            help="Issue missing certificates (--no-issue: only check that every host's "
            "certificate and key are there, for a CA kept elsewhere).",
        ),
    ] = True,
) -> None:
    """Create the site CA (once) and a certificate per agent (CN = agent id), for the collector
    (with its host name and address as SANs) and for the operator CLI. Existing fitting
    certificates are kept."""
    try:
        fleet = load_inventory(inventory)
        d = out or fleet.pki_dir
        if not issue:
            _check_present(d, fleet)
            typer.echo(str(d))
            typer.echo("unchanged")
            return
        before = {f.name: f.read_bytes() for f in d.glob("*.crt")} if d.is_dir() else {}
        now = dt.datetime.now(dt.UTC)
        pki.issue(d, "collector", ["collector", fleet.collector_host, fleet.collector_address], now)
        pki.issue(d, "operator", ["operator"], now)
        for a in fleet.agents:
            pki.issue(d, a.agent_id, [a.agent_id, a.host], now)
        after = {f.name: f.read_bytes() for f in d.glob("*.crt")}
    except (InventoryError, pki.PkiError, OSError) as e:
        raise _fail(e) from None
    typer.echo(str(d))
    typer.echo("changed" if after != before else "unchanged")


@app.command("acl")
def acl_cmd(
    inventory: InventoryOpt,
    out: Annotated[Path, typer.Option(help="Where to write the collector's ACL (JSON5).")],
) -> None:
    """Write the collector's Zenoh ACL: each agent may only publish, declare and answer under
    its own id; only the collector and operator certificates may control runs."""
    try:
        fleet = load_inventory(inventory)
        ids = [a.agent_id for a in fleet.agents]
        text = json.dumps(build_acl(fleet.site, ids, list(ADMIN_CNS)), indent=2) + "\n"
    except (InventoryError, ValueError) as e:
        raise _fail(e) from None
    changed = not out.exists() or out.read_text(encoding="utf-8") != text
    if changed:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text, encoding="utf-8")
    typer.echo("changed" if changed else "unchanged")


def _same_wheel(a: Path, b: Path) -> bool:
    # Zip timestamps differ between builds; compare what is inside instead.
    with zipfile.ZipFile(a) as za, zipfile.ZipFile(b) as zb:
        if sorted(za.namelist()) != sorted(zb.namelist()):
            return False
        return all(za.read(n) == zb.read(n) for n in za.namelist())


@app.command("wheel")
def wheel_cmd(
    src: Annotated[Path, typer.Option(help="Project checkout (with pyproject.toml).")],
    out: Annotated[Path, typer.Option(help="Directory for the wheel.")],
) -> None:
    """Build the project wheel from the checkout; keep the existing file if its contents are
    the same, so re-running the playbook does not reinstall every host."""
    if not (src / "pyproject.toml").is_file():
        raise _fail(FileNotFoundError(f"{src}: no pyproject.toml, not a project checkout"))
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", tmp, str(src)]
        res = subprocess.run(
            cmd,
            capture_output=True,
            text=True,
            check=False,
            env={**os.environ, "SOURCE_DATE_EPOCH": "315532800"},
        )
        built = sorted(Path(tmp).glob("*.whl"))
        if res.returncode != 0 or len(built) != 1:
            tail = (res.stderr.strip().splitlines() or ["no wheel produced"])[-1]
            raise _fail(RuntimeError(f"building the wheel from {src} failed: {tail}"))
        new = built[0]
        out.mkdir(parents=True, exist_ok=True)
        dest = out / new.name
        changed = not (dest.exists() and _same_wheel(dest, new))
        if changed:
            dest.write_bytes(new.read_bytes())
    typer.echo(str(dest))
    typer.echo("changed" if changed else "unchanged")


def _has_build_backend() -> bool:
    """setuptools here can build our wheel by itself (>= 70.1 carries bdist_wheel)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        major, minor = (int(x) for x in version("setuptools").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return False
    return (major, minor) >= (70, 1)


def _build_project_wheel(src: Path, into: Path) -> Path:
    """pip wheel of the checkout alone (reproducible zip times); the built file."""
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(into), str(src)]
    if _has_build_backend():
        # No throw-away build environment (and no package index needed to make one).
        cmd.insert(4, "--no-build-isolation")
    res = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "SOURCE_DATE_EPOCH": "315532800"},
    )
    built = sorted(into.glob("*.whl"))
    if res.returncode != 0 or len(built) != 1:
        tail = (res.stderr.strip().splitlines() or ["no wheel produced"])[-1]
        raise RuntimeError(f"building the wheel from {src} failed: {tail}")
    return built[0]


def _same_file(a: Path, b: Path) -> bool:
    if a.suffix == ".whl" and b.suffix == ".whl":
        try:
            return _same_wheel(a, b)
        except zipfile.BadZipFile:
            return False
    return a.read_bytes() == b.read_bytes()


def _collect_deps(
    req: str, into: Path, platform: list[str], python_version: str | None, offline: Path | None
) -> None:
    """Wheels of `req` and all its dependencies into `into` (binary only for another platform);
    with `offline`, from that directory alone (no package index)."""
    if platform:
        cmd = [sys.executable, "-m", "pip", "download", "-q", "--only-binary=:all:"]
        cmd += ["-d", str(into)]
        for plat in platform:
            cmd += ["--platform", plat]
        if python_version:
            cmd += ["--python-version", python_version, "--implementation", "cp"]
    else:
        cmd = [sys.executable, "-m", "pip", "wheel", "-q", "-w", str(into)]
    if offline is not None:
        if not offline.is_dir():
            raise RuntimeError(f"{offline}: no wheelhouse yet")
        cmd += ["--no-index", "--find-links", str(offline)]
    res = subprocess.run([*cmd, req], capture_output=True, text=True, check=False)
    if res.returncode != 0:
        tail = (res.stderr.strip().splitlines() or ["pip failed"])[-1]
        raise RuntimeError(f"collecting the dependencies of {req} failed: {tail}")


def _up_to_date(out: Path, proj: Path, request: str) -> bool:
    """The wheelhouse was made for this request, holds this very project wheel, and every wheel
    its manifest lists is there with the listed hash."""
    try:
        if (out / REQUEST).read_text(encoding="utf-8") != request:
            return False
        if not (out / proj.name).exists() or not _same_wheel(out / proj.name, proj):
            return False
        listed = {}
        for line in (out / MANIFEST).read_text(encoding="utf-8").splitlines():
            digest, name = line.split("  ", 1)
            listed[name] = digest
    except (OSError, ValueError, zipfile.BadZipFile):
        return False
    present = {f.name for f in out.glob("*.whl")}
    if present != set(listed):
        return False
    return all(hashlib.sha256((out / n).read_bytes()).hexdigest() == d for n, d in listed.items())


@app.command("wheelhouse")
def wheelhouse_cmd(
    src: Annotated[Path, typer.Option(help="Project checkout (with pyproject.toml).")],
    out: Annotated[Path, typer.Option(help="Wheelhouse directory (made to hold exactly the set).")],
    extras: Annotated[
        str, typer.Option(help="Comma-separated extras whose dependencies go in.")
    ] = "agent,collector",
    platform: Annotated[
        list[str] | None,
        typer.Option(
            "--platform",
            help="Target platform tag, e.g. manylinux_2_17_aarch64 (repeatable); default: "
            "this machine. Foreign platforms take binary wheels only.",
        ),
    ] = None,
    python_version: Annotated[
        str | None, typer.Option(help="Target Python version, e.g. 3.11 (with --platform).")
    ] = None,
) -> None:
    """Build an offline install set: the project wheel plus a wheel of every dependency of the
    given extras, for the target platform, so hosts install with `pip --no-index`. Files whose
    contents did not change are kept, stale ones removed."""
    if not (src / "pyproject.toml").is_file():
        raise _fail(FileNotFoundError(f"{src}: no pyproject.toml, not a project checkout"))
    wanted = [e.strip() for e in extras.split(",") if e.strip()]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            t = Path(tmp)
            (t / "proj").mkdir()
            proj = _build_project_wheel(src, t / "proj")
            (t / "house").mkdir()
            req = f"{proj}[{','.join(wanted)}]" if wanted else str(proj)
            # Same project wheel (so the same requirements), same request, complete manifest:
            # nothing to fetch, and a re-run of the playbook costs one build.
            request = json.dumps([wanted, platform or [], python_version]) + "\n"
            if _up_to_date(out, proj, request):
                typer.echo(proj.name)
                typer.echo(str(out))
                typer.echo("unchanged")
                return
            # A wheelhouse that already holds every dependency is refreshed without any index
            # (a control machine on the fleet's own network); otherwise pip asks its index.
            try:
                _collect_deps(req, t / "house", platform or [], python_version, offline=out)
            except RuntimeError:
                for f in (t / "house").glob("*"):
                    f.unlink()
                _collect_deps(req, t / "house", platform or [], python_version, offline=None)
            new = {f.name: f for f in (t / "house").glob("*.whl")}
            new[proj.name] = proj
            out.mkdir(parents=True, exist_ok=True)
            changed = False
            for old in out.glob("*.whl"):
                if old.name not in new:
                    old.unlink()
                    changed = True
            for name, f in sorted(new.items()):
                dest = out / name
                if not (dest.exists() and _same_file(dest, f)):
                    shutil.copyfile(f, dest)
                    changed = True
        # The manifest lets the playbook skip copying an unchanged wheelhouse file by file.
        sums = "".join(
            f"{hashlib.sha256(f.read_bytes()).hexdigest()}  {f.name}\n"
            for f in sorted(out.glob("*.whl"))
        )
        manifest = out / MANIFEST
        if not manifest.exists() or manifest.read_text(encoding="utf-8") != sums:
            manifest.write_text(sums, encoding="utf-8")
            changed = True
        (out / REQUEST).write_text(request, encoding="utf-8")
    except (RuntimeError, OSError) as e:
        raise _fail(e) from None
    typer.echo(proj.name)
    typer.echo(str(out))
    typer.echo("changed" if changed else "unchanged")


flow_command_help(app)  # after every command is declared


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    app()
