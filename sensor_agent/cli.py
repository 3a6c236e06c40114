"""`sensor-agent` command line: thin typer commands that forward to sensor_agent.app / config."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from bgt_core.cli_help import flow_command_help
from sensor_agent.config import AgentConfig, load_config, with_overrides
from sensor_agent.errors import AgentError

app = typer.Typer(
    name="sensor-agent",
    help="Scan BLE adapters (or replay / simulate them) and publish RSSI batches over Zenoh.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    add_completion=False,
)
err = Console(stderr=True, emoji=False)
out = Console(emoji=False)

ConfigOpt = Annotated[
    Path | None,
    typer.Option(
        "--config",
        "-c",
        help="Agent YAML file (e.g. /etc/ble-groundtruth/agent.yaml); flags override it.",
        dir_okay=False,
    ),
]


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


def _fail(e: AgentError) -> typer.Exit:
    err.print(f"[red]{e}", highlight=False, soft_wrap=True)
    return typer.Exit(1)


@app.command()
def run(
    config: ConfigOpt = None,
    agent_id: Annotated[
        str | None,
        typer.Option(
            help="This agent's id ([A-Za-z0-9_.-], up to 64); default: config, else the host name."
        ),
    ] = None,
    site: Annotated[str | None, typer.Option(help="Site name in every key expression.")] = None,
    connect: Annotated[
        list[str] | None,
        typer.Option(
            help="Zenoh endpoint of the collector's router, e.g. tcp/192.168.1.10:7447 (repeatable)."
        ),
    ] = None,
    backend: Annotated[
        str | None,
        typer.Option(
            help="bleak (real adapters) | replay (.mbd files) | simulated (moving beacon)."
        ),
    ] = None,
    adapter: Annotated[
        list[str] | None,
        typer.Option(
            help="Adapter name (hci0) or MAC to scan with (repeatable); default: every adapter."
        ),
    ] = None,
    replay: Annotated[
        list[Path] | None,
        typer.Option(help="An .mbd file to replay (repeatable); selects the replay backend."),
    ] = None,
    replay_speed: Annotated[
        float | None,
        typer.Option(help="Replay pace relative to the recording; 0 = as fast as possible."),
    ] = None,
    replay_keep_time: Annotated[
        bool,
        typer.Option(
            "--replay-keep-time", help="Keep the files' timestamps instead of shifting them to now."
        ),
    ] = False,
    scan_mode: Annotated[
        str | None,
        typer.Option(help="active | passive (passive needs BlueZ advertisement monitors)."),
    ] = None,
    no_wait_ack: Annotated[
        bool,
        typer.Option(
            "--no-wait-ack",
            help="At the end of a replay, exit without waiting for the collector's acks.",
        ),
    ] = False,
    ack_timeout: Annotated[
        float | None,
        typer.Option(
            help="Seconds to wait for the collector's acks at the end of a replay (default 30)."
        ),
    ] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log debug messages.")] = False,
) -> None:
    """Run the agent until the source ends (replay) or SIGINT/SIGTERM (which flush and stop cleanly).

    A replay exits 0 only once the collector acknowledged every batch, 1 otherwise.
    """
    from sensor_agent.app import run_agent

    _setup_logging(verbose)
    try:
        cfg = with_overrides(
            load_config(config),
            agent_id=agent_id,
            site=site,
            connect=connect or (),
            backend=backend,
            adapters=adapter or (),
            replay=replay or (),
            replay_speed=replay_speed,
            replay_keep_time=True if replay_keep_time else None,
            scan_mode=scan_mode,
            ack_timeout_s=ack_timeout,
        )
        result = asyncio.run(run_agent(cfg, wait_ack=not no_wait_ack, handle_signals=True))
    except AgentError as e:
        raise _fail(e) from None
    logging.getLogger("sensor_agent").info("done: %d readings", result.readings)


@app.command()
def adapters() -> None:
    """List the local Bluetooth adapters (over BlueZ's D-Bus API) with their MACs.

    One line per adapter: name, MAC as used in the data, MAC as BlueZ writes it, power, alias.
    """
    from sensor_agent.scanning.bleak_backend import list_adapters

    try:
        found = asyncio.run(list_adapters())
    except AgentError as e:
        raise _fail(e) from None
    if not found:
        err.print("[red]BlueZ reports no Bluetooth adapter")
        raise typer.Exit(1)
    from bgt_core.wire import colon_mac

    # Tab-separated so scripts (deploy/) can cut it: name, sensor id, BlueZ spelling, power, alias.
    for a in found:
        typer.echo(
            f"{a.name}\t{a.address}\t{colon_mac(a.address)}\t"
            f"{'powered' if a.powered else 'off'}\t{a.alias}"
        )


@app.command()
def check(config: ConfigOpt = None) -> None:
    """Validate a config file and print the resolved configuration (defaults filled in)."""
    from bgt_core.safe_yaml import dump

    try:
        cfg: AgentConfig = with_overrides(load_config(config))
    except AgentError as e:
        raise _fail(e) from None
    out.print(dump(cfg.to_dict(), sort_keys=False), end="", highlight=False)


flow_command_help(app)  # after every command is declared


def main() -> None:
    app()
