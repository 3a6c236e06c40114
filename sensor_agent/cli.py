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


@app.command()
def doctor(
    seconds: Annotated[
        float, typer.Option(help="How long each mode scans.", min=2.0, max=600.0)
    ] = 20.0,
    adapter: Annotated[
        list[str] | None,
        typer.Option(help="Adapter name (hci0) or MAC; repeatable. Default: every adapter."),
    ] = None,
) -> None:
    """Tell whether this machine hands in every advertisement, and which backend to use.

    Scans SECONDS with each mode it can use (the kernel's management socket, bleak active, bleak
    passive) while beacons advertise nearby, then prints per adapter and beacon: reports per
    second, the share of reports repeating the previous RSSI exactly, and the largest gap.
    A mode under half the best one's rate, or with gaps over 5 s, is throttled (a controller's
    duplicate filter, or BlueZ reporting only 8 dB changes). Recommends a mode for agent.yaml's
    `backend:`; exits 1 without Bluetooth, 2 when every mode is throttled.
    """
    from rich.table import Table

    from sensor_agent.doctor import diagnose
    from sensor_agent.scanning.bleak_backend import BleakBackend
    from sensor_agent.scanning.mgmt_backend import MgmtBackend

    wanted = tuple(adapter or ())
    modes = [
        ("mgmt", lambda: MgmtBackend(wanted)),
        ("bleak active", lambda: BleakBackend(wanted, "active")),
        ("bleak passive", lambda: BleakBackend(wanted, "passive")),
    ]
    with err.status("scanning ...") as status:  # transient: gone once the answer is printed
        diagnosis = asyncio.run(
            diagnose(
                modes, seconds, lambda m: status.update(f"scanning {seconds:g} s with {m} ...")
            )
        )
    if not diagnosis.usable:
        why = "; ".join(f"{m.mode}: {m.error}" for m in diagnosis.modes)
        err.print(
            f"no usable Bluetooth here ({why})", markup=False, highlight=False, soft_wrap=True
        )
        raise typer.Exit(1)
    table = Table(title=f"reports over {seconds:g} s per mode, adapter and beacon")
    for col in ("mode", "adapter", "beacon", "reports/s", "same RSSI as previous", "largest gap"):
        table.add_column(col, justify="right" if col[0] in "rsl" and col != "mode" else "left")
    for m in diagnosis.modes:
        if m.error is not None:
            table.add_row(m.mode, "-", "-", "-", "-", f"unavailable: {m.error}")
            continue
        for (ad, beacon), f in sorted(m.beacons.items()):
            table.add_row(
                m.mode,
                ad,
                beacon,
                f"{f.per_s:.2f}",
                f"{f.repeated_share:.0%}",
                f"{f.largest_gap_s:.1f} s",
            )
        verdict = "THROTTLED" if m.throttled else "ok"
        table.add_row(m.mode, "", "median", f"{m.median_rate:.2f}", "", verdict, end_section=True)
    out.print(table)
    if diagnosis.recommended is None:
        out.print(
            "every mode is throttled: no beacon in range, or a controller that filters "
            "duplicates in every mode (try a USB dongle)",
            markup=False,
        )
        raise typer.Exit(2)
    backend = "mgmt" if diagnosis.recommended == "mgmt" else "bleak"
    mode = "" if backend == "mgmt" else f", scan_mode: {diagnosis.recommended.split()[1]}"
    out.print(
        f"recommended: {diagnosis.recommended} (agent.yaml: backend: {backend}{mode})", markup=False
    )


flow_command_help(app)  # after every command is declared


def main() -> None:
    app()
