"""`collector fleet`: the deployed fleet as the inventory describes it, checked live over Zenoh.

Asks every agent of the inventory for its status (``wire.agent_status_key``) and its clock
(``wire.agent_clock_key``, the same four-timestamp exchange the collector makes) and looks at the
liveliness tokens; shows alive/version/adapters and the agent's clock offset from this host.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bgt_core import wire
from bgt_core.messages import AdapterStatus, AgentStatus, ClockReply, ClockRequest, ClockSample
from bgt_core.zenoh_config import SessionSpec, TlsFiles, build_config, zenoh_reason
from deploy.inventory import InventoryError, load_inventory

if TYPE_CHECKING:
    import zenoh

app = typer.Typer(
    name="fleet", no_args_is_help=True, help="The deployed fleet (reads deploy/'s inventory)."
)
console = Console(emoji=False)
err_console = Console(stderr=True, emoji=False)


@app.callback()
def _fleet() -> None:
    """The deployed fleet, as described by deploy/'s inventory."""
    # A callback keeps `status` a subcommand even while it is the only one.


@dataclass(frozen=True, slots=True)
class AgentState:
    """What one agent said (or did not say)."""

    agent_id: str
    in_inventory: bool
    alive: bool  # its liveliness token is present
    answered: bool  # its status queryable replied
    version: str | None = None
    hostname: str | None = None
    adapters: tuple[AdapterStatus, ...] = ()
    offset_ms: float | None = None  # agent clock minus ours (four-timestamp exchange)
    rtt_ms: float | None = None
    ntp_source: str | None = None  # the agent's chrony reference (should be the collector)
    ntp_offset_ms: float | None = None  # chrony's own estimate of the agent's clock error
    error: str | None = None


def _clock_of(
    session: zenoh.Session, site: str, agent_id: str, clock: Callable[[], int], timeout: float
) -> ClockSample | None:
    """The four-timestamp clock exchange with one agent (as the collector does it); None if it
    did not answer."""
    t1 = clock()
    payload = wire.to_json(ClockRequest(t1).to_dict())
    for r in session.get(wire.agent_clock_key(site, agent_id), payload=payload, timeout=timeout):
        t4 = clock()
        if r.ok is None:
            return None
        reply = ClockReply.from_dict(wire.from_json(r.ok.payload.to_bytes(), "clock reply"))
        return ClockSample.measure(reply, t1, t4, "")
    return None


def _status_of(
    session: zenoh.Session, site: str, agent_id: str, clock: Callable[[], int], timeout: float
) -> dict[str, Any]:
    """One status query and one clock exchange; returns the fields of AgentState it learnt."""
    replies = list(session.get(wire.agent_status_key(site, agent_id), timeout=timeout))
    for r in replies:
        if r.ok is None:
            continue
        try:
            st = AgentStatus.from_dict(wire.from_json(r.ok.payload.to_bytes(), "agent status"))
        except wire.WireError as e:
            return {"answered": True, "error": f"bad status reply: {e}"}
        try:
            smp = _clock_of(session, site, agent_id, clock, timeout)
        except wire.WireError as e:
            return {"answered": True, "error": f"bad clock reply: {e}"}
        chrony = st.chrony or {}
        ntp_off = chrony.get("system_time_offset_s")
        ref = chrony.get("ref_id")
        return {
            "ntp_source": ref if isinstance(ref, str) else None,
            "ntp_offset_ms": ntp_off * 1e3 if isinstance(ntp_off, int | float) else None,
            "answered": True,
            "version": st.version,
            "hostname": st.hostname,
            "adapters": st.adapters,
            "offset_ms": None if smp is None else smp.offset_ms,
            "rtt_ms": None if smp is None else smp.rtt_ms,
        }
    return {"answered": False}


def query_fleet(
    session: zenoh.Session,
    site: str,
    agent_ids: Sequence[str],
    clock: Callable[[], int] = time.time_ns,
    timeout: float = 3.0,
) -> list[AgentState]:
    """Status of the inventory's agents, plus any live agent the inventory does not know."""
    alive: set[str] = set()
    for r in session.liveliness().get(wire.agent_token_selector(site), timeout=timeout):
        if r.ok is not None:
            alive.add(str(r.ok.key_expr).rsplit("/", 1)[-1])
    out = []
    for agent_id in list(agent_ids) + sorted(alive - set(agent_ids)):
        fields = _status_of(session, site, agent_id, clock, timeout)
        out.append(AgentState(agent_id, agent_id in agent_ids, agent_id in alive, **fields))
    return out


def _adapters_text(adapters: Sequence[AdapterStatus]) -> str:
    parts = []
    for a in adapters:
        rate_s = "" if a.adverts_per_s is None else f" {a.adverts_per_s:.0f}/s"
        parts.append(f"{a.name or '?'} {a.mode or ''}{rate_s}".strip())
    return ", ".join(parts) or "-"


def _table(states: Sequence[AgentState]) -> Table:
    t = Table("agent", "alive", "version", "host", "adapters", "clock offset", "rtt", "chrony")
    for s in states:
        name = s.agent_id if s.in_inventory else f"{s.agent_id} (not in inventory)"
        alive = (
            "[green]yes[/]"
            if s.alive and s.answered
            else ("[yellow]token only[/]" if s.alive else "[red]no[/]")
        )
        offset = "-" if s.offset_ms is None else f"{s.offset_ms:+.1f} ms"
        rtt = "-" if s.rtt_ms is None else f"{s.rtt_ms:.1f} ms"
        ntp = "-"
        if s.ntp_source or s.ntp_offset_ms is not None:
            off = "?" if s.ntp_offset_ms is None else f"{s.ntp_offset_ms:+.3f} ms"
            ntp = f"{s.ntp_source or '?'} {off}"
        t.add_row(
            escape(name),
            alive,
            escape(s.version or "-"),
            escape(s.hostname or "-"),
            escape(s.error or _adapters_text(s.adapters)),
            offset,
            rtt,
            escape(ntp),
        )
    return t


@app.command()
def status(
    inventory: Annotated[
        Path,
        typer.Option(
            "--inventory", "-i", help="The fleet's YAML inventory (deploy/inventory.yml)."
        ),
    ],
    connect: Annotated[
        str | None,
        typer.Option(
            "--connect",
            help="Collector endpoint (default: tls/<collector>:<port> from the inventory).",
        ),
    ] = None,
    root_ca: Annotated[
        Path | None, typer.Option("--root-ca", help="Site CA (default: <pki>/ca.crt).")
    ] = None,
    cert: Annotated[
        Path | None,
        typer.Option("--cert", help="Client certificate (default: <pki>/operator.crt)."),
    ] = None,
    key: Annotated[
        Path | None, typer.Option("--key", help="Client key (default: <pki>/operator.key).")
    ] = None,
    timeout: Annotated[
        float, typer.Option("--timeout", help="Seconds to wait for each agent's answer.")
    ] = 3.0,
) -> None:
    """Which agents are alive, their version, adapters and clock offset from this host
    (agent clock minus ours, corrected for half the round trip), plus what the agent's chrony
    reports (its reference and its own offset estimate).

    Exit code 1 if any agent of the inventory does not answer.
    """
    import zenoh

    try:
        fleet = load_inventory(inventory)
    except InventoryError as e:
        err_console.print(f"[red]{escape(str(e))}[/red]")
        raise typer.Exit(1) from None
    endpoint = connect or fleet.endpoint
    tls = None
    if endpoint.startswith(("tls/", "quic/")):
        files = [
            root_ca or fleet.pki_dir / "ca.crt",
            cert or fleet.pki_dir / "operator.crt",
            key or fleet.pki_dir / "operator.key",
        ]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            err_console.print(
                f"[red]TLS file not found: {escape(', '.join(missing))} (see --root-ca/--cert/--key)[/red]"
            )
            raise typer.Exit(1)
        tls = TlsFiles(*(str(f) for f in files))
    try:
        session = zenoh.open(build_config(SessionSpec(mode="client", connect=[endpoint], tls=tls)))
    except zenoh.ZError as e:
        err_console.print(
            f"[red]cannot reach the collector at {escape(endpoint)}: {escape(zenoh_reason(e))}[/red]"
        )
        raise typer.Exit(1) from None
    try:
        states = query_fleet(
            session, fleet.site, [a.agent_id for a in fleet.agents], time.time_ns, timeout
        )
    finally:
        session.close()
    console.print(_table(states))
    down = [s.agent_id for s in states if s.in_inventory and not s.answered]
    if down:
        err_console.print(
            f"[red]{len(down)} of {len(fleet.agents)} agents not answering: {escape(', '.join(down))}[/red]"
        )
        raise typer.Exit(1)
