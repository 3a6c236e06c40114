"""``python -m deploy``: the control-node steps the Ansible playbook calls.

Each command is idempotent and says on its last line ``changed`` or ``unchanged`` so Ansible's
``changed_when`` can tell; known problems end as one red line and exit code 1.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from deploy import pki
from deploy.acl import build_acl
from deploy.inventory import ADMIN_CNS, InventoryError, load_inventory

app = typer.Typer(
    help="Fleet deployment helpers (site PKI, Zenoh ACL, project wheel).", no_args_is_help=True
)
err = Console(stderr=True)

InventoryOpt = Annotated[
    Path,
    typer.Option("--inventory", "-i", help="The fleet's YAML inventory (deploy/inventory.yml)."),
]


def _fail(e: Exception) -> typer.Exit:
    err.print(f"[red]{e}[/red]", highlight=False)
    return typer.Exit(1)


@app.command("pki")
def pki_cmd(
    inventory: InventoryOpt,
    out: Annotated[
        Path | None, typer.Option(help="PKI directory (default: bgt_pki_dir of the inventory).")
    ] = None,
) -> None:
    """Create the site CA (once) and a certificate per agent (CN = agent id), for the collector
    (with its host name and address as SANs) and for the operator CLI. Existing fitting
    certificates are kept."""
    try:
        fleet = load_inventory(inventory)
        d = out or fleet.pki_dir
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


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    app()
