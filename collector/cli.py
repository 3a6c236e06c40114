"""`collector` command line: a thin typer app over collector.service (serve, record) and
collector.client (start, stop, status, runs, live)."""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bgt_core.cli_help import flow_command_help
from bgt_core.control_messages import check_run_name, check_run_notes
from bgt_core.display import shown
from bgt_core.wire import WireError
from collector.errors import CollectorError, ConfigError
from collector.fleet import app as fleet_app

if TYPE_CHECKING:
    from collector.client import CollectorClient
    from collector.config import CollectorConfig

app = typer.Typer(
    name="collector",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
    help="Receives BLE RSSI batches from sensor agents over Zenoh and writes one "
    ".mbd file per sensor per capture run.",
)
app.add_typer(
    fleet_app,
    name="fleet",
    help="The fleet in a deploy/ inventory: agents alive, versions, adapters, clocks.",
)
# emoji off: text from outside (names, errors) is never read as ':shortcode:'.
console = Console(emoji=False)
err_console = Console(stderr=True, emoji=False)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
ConfigOpt = Annotated[
    Path | None, typer.Option("--config", help="collector.yaml; flags override it.")
]
ConnectOpt = Annotated[str, typer.Option("--connect", help="Endpoint of the running collector.")]
SiteOpt = Annotated[str, typer.Option("--site", help="Site name (the first part of every key).")]
RootCaOpt = Annotated[
    Path | None, typer.Option("--root-ca", help="Site CA certificate, for a tls/... collector.")
]
CertOpt = Annotated[
    Path | None, typer.Option("--cert", help="Operator certificate (PEM), for a tls/... collector.")
]
KeyOpt = Annotated[
    Path | None, typer.Option("--key", help="Operator private key (PEM), for a tls/... collector.")
]
InsecureOpt = Annotated[
    bool, typer.Option("--insecure", help="Allow plain TCP listening on a non-loopback address.")
]


def _fail(e: Exception) -> typer.Exit:
    err_console.print(f"[red]{escape(shown(e, None))}", highlight=False, soft_wrap=True)
    return typer.Exit(1)


@app.callback()
def _root(
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log debug messages.")] = False,
) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("zenoh").setLevel(logging.WARNING)


def _load(
    config: Path | None,
    data_dir: Path | None,
    listen: list[str] | None,
    site: str | None,
    insecure: bool,
) -> CollectorConfig:
    from collector.config import CollectorConfig, load_config

    cfg = load_config(config) if config is not None else CollectorConfig()
    return cfg.with_overrides(data_dir=data_dir, listen=listen, site=site, insecure=insecure)


def _wait_for_signal(seconds: float | None = None) -> None:
    """Block until SIGINT/SIGTERM (or `seconds`), so shutdown goes through drain/flush/close."""
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    # Short waits, never one long one: Python runs a signal's handler on the main thread only
    # when that thread runs bytecode. The kernel may deliver the signal to any thread (Zenoh's
    # included), and then nothing wakes a main thread parked in an untimed wait: SIGINT was lost.
    end = None if seconds is None else time.monotonic() + seconds
    while end is None or (left := end - time.monotonic()) > 0:
        if done.wait(0.2 if end is None else min(0.2, left)):
            return


@app.command()
def serve(
    config: ConfigOpt = None,
    data_dir: Annotated[
        Path | None, typer.Option("--data-dir", help="Where run directories go (default ./data).")
    ] = None,
    listen: Annotated[
        list[str] | None,
        typer.Option(
            "--listen", help="Endpoint to listen on; repeatable (default tcp/127.0.0.1:7447)."
        ),
    ] = None,
    site: Annotated[
        str | None,
        typer.Option("--site", help="Site name (default: from the config, else 'default')."),
    ] = None,
    insecure: InsecureOpt = False,
    check: Annotated[
        bool,
        typer.Option(
            "--check",
            help="Only validate the config (and its TLS and ACL files), print the resolved settings as JSON and exit.",
        ),
    ] = False,
    web: Annotated[
        str | None,
        typer.Option("--web", help="Also serve the operator's console on HOST:PORT (web extra)."),
    ] = None,
) -> None:
    """Run the collector: the Zenoh router agents connect to. Stops cleanly on Ctrl-C / SIGTERM.

    A run left active by a killed collector is resumed on the same data directory."""
    from collector.service import Collector

    try:
        cfg = _load(config, data_dir, listen, site, insecure)
        if check:
            from collector.config import check_files

            check_files(cfg)
            console.print_json(json.dumps(cfg.describe()))
            return
        collector = Collector(cfg).open()
    except CollectorError as e:
        raise _fail(e) from None
    console.print(
        f"collector listening on {', '.join(cfg.listen)}, site {cfg.site!r}, data in {cfg.data_dir}"
    )
    if collector.resumed_run is not None:
        err_console.print(
            f"[yellow]resumed run {collector.resumed_run} (the collector was not stopped cleanly)"
        )
    child = None
    try:
        if web is not None:
            from collector.web.launch import spawn_console

            child = spawn_console(list(cfg.listen), web, cfg.site)
        _wait_for_signal()
    except CollectorError as e:
        raise _fail(e) from None
    finally:
        if child is not None:
            child.terminate()
            child.wait(10)
        collector.close()


@app.command()
def record(
    name: Annotated[str, typer.Option("--name", help="Run name (part of the run id).")],
    duration: Annotated[
        float | None, typer.Option("--duration", help="Seconds to record (default: until Ctrl-C).")
    ] = None,
    config: ConfigOpt = None,
    data_dir: Annotated[
        Path | None, typer.Option("--data-dir", help="Where run directories go.")
    ] = None,
    listen: Annotated[
        list[str] | None, typer.Option("--listen", help="Endpoint to listen on; repeatable.")
    ] = None,
    site: Annotated[str | None, typer.Option("--site", help="Site name.")] = None,
    insecure: InsecureOpt = False,
) -> None:
    """Serve, start a run, record until --duration or Ctrl-C, stop it, exit: all in the foreground."""
    from collector.service import Collector

    try:
        cfg = _load(config, data_dir, listen, site, insecure)
        collector = Collector(cfg).open()
    except CollectorError as e:
        raise _fail(e) from None
    try:
        started = collector.start_run(name)
        console.print(f"recording run {started['run_id']} (Ctrl-C to stop)")
        _wait_for_signal(duration)
        stopped = collector.stop_run()  # a run is active: never None
        if stopped is not None:
            console.print(f"{stopped['readings']} readings in {stopped['run_dir']}")
    except CollectorError as e:
        raise _fail(e) from None
    finally:
        collector.close()


def _client(
    connect: str, site: str, root_ca: Path | None, cert: Path | None, key: Path | None
) -> CollectorClient:
    from bgt_core.zenoh_config import TlsFiles
    from collector.client import CollectorClient
    from collector.errors import ConfigError

    files = {"--root-ca": root_ca, "--cert": cert, "--key": key}
    given = [k for k, v in files.items() if v is not None]
    if given and len(given) != 3:
        raise ConfigError(
            "--root-ca, --cert and --key go together (a tls/... collector needs all three)"
        )
    for flag, path in files.items():
        if path is not None and not path.is_file():
            raise ConfigError(f"{flag}: file not found: {path}")
    tls = TlsFiles(str(root_ca), str(cert), str(key)) if given else None
    return CollectorClient(connect, site, tls=tls)


@app.command(short_help="Start a capture run on a running collector; prints the run id.")
def start(
    name: Annotated[
        str | None, typer.Option("--name", help="Run name (part of the run id).")
    ] = None,
    max_offset_ms: Annotated[
        float,
        typer.Option(
            "--max-offset-ms",
            help="Warn about agents whose clock is off by more than this (measured at start).",
        ),
    ] = 50.0,
    strict: Annotated[
        bool,
        typer.Option(
            "--strict",
            help="Refuse to start (exit 1) if an agent's clock is off by more than --max-offset-ms.",
        ),
    ] = False,
    notes: Annotated[
        str | None,
        typer.Option(
            "--notes", help="Free text about the run (who walked, what changed), in run.yaml."
        ),
    ] = None,
    connect: ConnectOpt = DEFAULT_ENDPOINT,
    site: SiteOpt = "default",
    root_ca: RootCaOpt = None,
    cert: CertOpt = None,
    key: KeyOpt = None,
) -> None:
    """Start a capture run on a running collector; prints the run id. Agents' clocks are
    checked first: one warning line per agent off by more than --max-offset-ms."""
    if not (math.isfinite(max_offset_ms) and 0 <= max_offset_ms <= 86_400_000):
        raise _fail(
            ConfigError(
                f"--max-offset-ms must be a finite number in 0..86400000, not {max_offset_ms}"
            )
        )
    try:
        check_run_name(name)
    except WireError as e:
        raise _fail(ConfigError(f"--name: {e}")) from None
    try:
        check_run_notes(notes)
    except WireError as e:
        raise _fail(ConfigError(f"--notes: {e}")) from None
    try:
        with _client(connect, site, root_ca, cert, key) as c:
            reply = c.start_typed(name, max_offset_ms=max_offset_ms, strict=strict, notes=notes)
    except (CollectorError, WireError) as e:
        raise _fail(e) from None
    for w in reply.clock_warnings:
        err_console.print(f"[yellow]warning: {escape(w)}", highlight=False, soft_wrap=True)
    console.print(reply.run_id, highlight=False)


@app.command()
def stop(
    connect: ConnectOpt = DEFAULT_ENDPOINT,
    site: SiteOpt = "default",
    root_ca: RootCaOpt = None,
    cert: CertOpt = None,
    key: KeyOpt = None,
) -> None:
    """Stop the current run after draining what is in flight; prints the run directory."""
    try:
        with _client(connect, site, root_ca, cert, key) as c:
            reply = c.stop_typed()
    except (CollectorError, WireError) as e:
        raise _fail(e) from None
    if reply.missing_batches:
        err_console.print(f"[yellow]{reply.missing_batches} batches never arrived (see run.yaml)")
    console.print(reply.run_dir, highlight=False, soft_wrap=True)


@app.command()
def status(
    connect: ConnectOpt = DEFAULT_ENDPOINT,
    site: SiteOpt = "default",
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the raw status reply as JSON.")
    ] = False,
    root_ca: RootCaOpt = None,
    cert: CertOpt = None,
    key: KeyOpt = None,
) -> None:
    """Agents alive, per-sensor reading rates and last-seen times, and the current run."""
    from bgt_core.control_messages import CollectorStatus
    from collector.live import render

    try:
        with _client(connect, site, root_ca, cert, key) as c:
            reply = c.status()
            view = None if as_json else render(CollectorStatus.from_dict(reply))
    except (CollectorError, WireError) as e:
        raise _fail(e) from None
    if view is None:
        console.print_json(json.dumps(reply))
    else:
        console.print(view)


@app.command()
def runs(
    connect: ConnectOpt = DEFAULT_ENDPOINT,
    site: SiteOpt = "default",
    as_json: Annotated[bool, typer.Option("--json", help="Print the list as JSON.")] = False,
    root_ca: RootCaOpt = None,
    cert: CertOpt = None,
    key: KeyOpt = None,
) -> None:
    """List the runs in the collector's data directory, oldest first."""
    try:
        with _client(connect, site, root_ca, cert, key) as c:
            items = c.runs()
    except CollectorError as e:
        raise _fail(e) from None
    if as_json:
        console.print_json(json.dumps(items))
        return
    table = Table()
    for col in ("run id", "name", "start", "stop", "readings"):
        table.add_column(col, overflow="fold")
    for r in items:
        table.add_row(
            escape(shown(r["run_id"])),
            escape(shown(r.get("name") or "")),
            escape(shown(r.get("start") or "")),
            escape(shown(r.get("stop"))) if r.get("stop") else "[yellow]not stopped",
            escape(shown(r.get("readings") or 0)),
        )
    console.print(table)


@app.command()
def live(
    connect: ConnectOpt = DEFAULT_ENDPOINT,
    site: SiteOpt = "default",
    interval: Annotated[float, typer.Option("--interval", help="Seconds between refreshes.")] = 0.5,
    duration: Annotated[
        float | None, typer.Option("--duration", help="Quit after this many seconds.")
    ] = None,
    root_ca: RootCaOpt = None,
    cert: CertOpt = None,
    key: KeyOpt = None,
) -> None:
    """Live view: per sensor its reading rate, last RSSI and an RSSI sparkline (Ctrl-C quits)."""
    from collector.live import run_live

    try:
        with _client(connect, site, root_ca, cert, key) as c:
            run_live(c.status, interval_s=interval, duration_s=duration)
    except (CollectorError, WireError) as e:
        raise _fail(e) from None


def _listen_address(listen: str) -> tuple[str, str]:
    """--listen HOST:PORT split, or the one-line error."""
    host, sep, port_text = listen.rpartition(":")
    if not sep or not port_text.isdigit() or not 0 < int(port_text) < 65536 or not host:
        raise _fail(ConfigError(f"--listen {listen!r}: expected HOST:PORT, e.g. 127.0.0.1:8080"))
    return host, port_text


@app.command(short_help="The operator's console in a browser: fleet, live RSSI, start and stop.")
def web(
    listen: Annotated[
        str,
        typer.Option(
            "--listen",
            help="HOST:PORT to serve the page on. Beyond 127.0.0.1 it needs --tls-cert/--tls-key "
            "and the access token printed at start.",
        ),
    ] = "127.0.0.1:8080",
    tls_cert: Annotated[
        Path | None,
        typer.Option(
            "--tls-cert", help="HTTPS certificate (PEM), for --listen beyond this machine."
        ),
    ] = None,
    tls_key: Annotated[
        Path | None, typer.Option("--tls-key", help="Its private key (PEM).")
    ] = None,
    silent_s: Annotated[
        float, typer.Option("--silent-s", help="A sensor unheard this long turns red.", min=1.0)
    ] = 10.0,
    plan: Annotated[
        str | None,
        typer.Option(
            "--plan",
            help="Floor plan to draw the sensors on: a built-in site (tetam, the demo's) or a "
            "folder with the site's .dev, .par and map .png.",
        ),
    ] = None,
    radiomap: Annotated[
        Path | None,
        typer.Option(
            "--radiomap",
            help="A radio map folder (.grd files, `annotator radiomap`): the live position of each "
            "beacon by the grid-HMM baseline is drawn on the plan with its spread. Needs the "
            "annotator extra.",
        ),
    ] = None,
    connect: ConnectOpt = DEFAULT_ENDPOINT,
    site: SiteOpt = "default",
    root_ca: RootCaOpt = None,
    cert: CertOpt = None,
    key: KeyOpt = None,
) -> None:
    """Serve one page that shows every agent and sensor (readings/s, last RSSI, seconds since the
    last reading; silent ones in red), a sensor x beacon matrix of readings/s, the RSSI of the last
    five minutes, the runs, and takes start (name, notes) and stop. Updated once a second by
    server-sent events; the collector is asked, never the agents."""
    import secrets

    try:
        import uvicorn

        from collector.web.server import Console as WebConsole
        from collector.web.server import build_app, is_loopback
    except ModuleNotFoundError as e:
        raise _fail(
            ConfigError(
                f"collector web needs the web extra ({e.name} is missing): pip install '.[web]'"
            )
        ) from None
    host, port_text = _listen_address(listen)
    local = is_loopback(host)
    if not local and (tls_cert is None or tls_key is None):
        raise _fail(
            ConfigError(
                f"--listen {listen}: beyond this machine the console needs HTTPS: "
                "give --tls-cert and --tls-key"
            )
        )
    for flag, path in (("--tls-cert", tls_cert), ("--tls-key", tls_key)):
        if path is not None and not path.is_file():
            raise _fail(ConfigError(f"{flag}: no such file {path}"))
    from collector.web.plan import PlanError, load_plan

    try:
        floor = None if plan is None else load_plan(plan)
    except (PlanError, ValueError, OSError) as e:
        raise _fail(ConfigError(str(e).splitlines()[0])) from None
    live = None
    if radiomap is not None:
        try:
            from annotator.errors import AnnotatorError
            from collector.web.position import LivePositions
        except ModuleNotFoundError as e:
            raise _fail(
                ConfigError(f"--radiomap needs the annotator extra ({e.name} is missing)")
            ) from None
        try:
            live = LivePositions(radiomap)
        except (AnnotatorError, ValueError, OSError) as e:
            raise _fail(ConfigError(f"--radiomap: {str(e).splitlines()[0]}")) from None
    try:
        client = _client(connect, site, root_ca, cert, key).__enter__()
    except CollectorError as e:
        raise _fail(e) from None
    access = None if local else secrets.token_urlsafe(24)
    console_ = WebConsole(
        client, silent_s=silent_s, access_token=access, plan=floor, positions=live
    )
    scheme = "https" if tls_cert is not None else "http"
    url = f"{scheme}://{host}:{port_text}/" + (f"?token={access}" if access else "")
    console.print(
        f"console on {url}  (Ctrl-C stops it)", highlight=False, markup=False, soft_wrap=True
    )
    try:
        uvicorn.run(
            build_app(console_),
            host=host.strip("[]"),
            port=int(port_text),
            ssl_certfile=None if tls_cert is None else str(tls_cert),
            ssl_keyfile=None if tls_key is None else str(tls_key),
            log_level="warning",
            timeout_graceful_shutdown=2,  # open pages hold event streams: do not wait for them
        )
    finally:
        client.__exit__(None, None, None)


@app.command(short_help="A full-screen clock slate for the cameras to film (sync.mode: slate).")
def slate(
    listen: Annotated[
        str,
        typer.Option(
            "--listen",
            help="HOST:PORT to serve the slate on; 0.0.0.0:PORT lets a tablet or phone on the "
            "network be the screen (the page shows only the time and takes no input).",
        ),
    ] = "127.0.0.1:8090",
) -> None:
    """Serve a page that shows this host's clock as a time code, refreshed every frame: open it
    full screen (click it), film it with every camera of the bundle for a second before the walk
    and again after it, and set `sync: {mode: slate}` in experiment.yaml. Keep this host's clock
    and the agents' on the same NTP source (sensor-agent doctor shows an agent's offset)."""
    try:
        import uvicorn

        from collector.web.slate import build_slate_app
    except ModuleNotFoundError as e:
        raise _fail(
            ConfigError(
                f"collector slate needs the web extra ({e.name} is missing): pip install '.[web]'"
            )
        ) from None
    host, port_text = _listen_address(listen)
    shown = "127.0.0.1" if host in ("0.0.0.0", "::", "[::]") else host
    console.print(
        f"clock slate on http://{shown}:{port_text}/  (Ctrl-C stops it)",
        highlight=False,
        markup=False,
        soft_wrap=True,
    )
    uvicorn.run(build_slate_app(), host=host.strip("[]"), port=int(port_text), log_level="warning")


@app.command(short_help="Write a run in the published layout: one <sensor_mac>.mbd per sensor.")
def export(
    run_dir: Annotated[
        Path, typer.Argument(help="A run directory (holds run.yaml and rssi/<agent>/).")
    ],
    out: Annotated[
        Path | None,
        typer.Option(
            "--out", help="Where to write <sensor_mac>.mbd files (default RUN_DIR/merged)."
        ),
    ] = None,
) -> None:
    """Write the published layout, one <sensor_mac>.mbd per sensor, merging the per-agent files
    of a run in time order (a sensor heard by two agents gets both agents' rows)."""
    from collector.store import export_merged

    dest = out if out is not None else run_dir / "merged"
    try:
        counts = export_merged(run_dir, dest)
    except CollectorError as e:
        raise _fail(e) from None
    console.print(
        f"{sum(counts.values())} readings of {len(counts)} sensor(s) in {dest}",
        highlight=False,
        soft_wrap=True,
    )


flow_command_help(app)  # after every command is declared


def main() -> None:
    app()


if __name__ == "__main__":
    main()
