"""Reads the fleet's Ansible inventory (YAML form) into typed records.

One inventory serves Ansible, the PKI/ACL generator and ``collector fleet status``; this module
reads only what those need (groups ``agents`` and ``collector``, per-host agent id, adapters,
address) with plain YAML, so the collector host does not need Ansible installed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bgt_core import wire

DEFAULT_PORT = 7447
# Certificate names with full rights on the site (the collector and the operator CLI).
ADMIN_CNS = ("collector", "operator")


class InventoryError(ValueError):
    """An inventory file that is missing, malformed, or lacks what the fleet needs."""


@dataclass(frozen=True, slots=True)
class AgentHost:
    host: str  # inventory hostname
    address: str  # what Ansible (and people) reach it by
    agent_id: str
    adapters: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class Fleet:
    path: Path
    site: str
    collector_host: str
    collector_address: str
    port: int
    agents: tuple[AgentHost, ...]
    pki_dir: Path  # where deploy/ keeps the CA and certificates (control node)

    @property
    def endpoint(self) -> str:
        """The endpoint agents and CLIs dial: mutual TLS to the collector."""
        host = (
            f"[{self.collector_address}]"
            if ":" in self.collector_address
            else self.collector_address
        )
        return f"tls/{host}:{self.port}"

    def agent(self, agent_id: str) -> AgentHost:
        for a in self.agents:
            if a.agent_id == agent_id:
                return a
        raise InventoryError(f"{self.path}: no agent with id {agent_id!r}")


def _mapping(value: Any, where: str) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InventoryError(f"{where} must be a mapping, got {type(value).__name__}")
    return value


def _groups(
    node: dict[str, Any],
    where: str,
    found: dict[str, tuple[dict[str, Any], dict[str, Any]]],
    inherited: dict[str, Any],
) -> None:
    """Walk ``children`` recursively, collecting each group's hosts and merged group vars."""
    for name, group in _mapping(node.get("children"), f"{where}.children").items():
        group = _mapping(group, f"{where}.children.{name}")
        gvars = {**inherited, **_mapping(group.get("vars"), f"{name}.vars")}
        hosts = _mapping(group.get("hosts"), f"{name}.hosts")
        found[name] = (hosts, gvars)
        _groups(group, f"{where}.children.{name}", found, gvars)


def load_inventory(path: str | Path) -> Fleet:
    """Parse ``path``; raises InventoryError with the file and field for anything wrong."""
    from bgt_core.safe_yaml import YamlError, load_file

    p = Path(path)
    try:
        doc = load_file(p)
    except YamlError as e:
        raise InventoryError(f"inventory: {e}") from None
    root = _mapping(_mapping(doc, str(p)).get("all"), f"{p}: all")
    if not root:
        raise InventoryError(f"{p}: expected a YAML inventory with a top-level 'all:' group")
    try:
        top = _mapping(root.get("vars"), "all.vars")
        groups: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
        _groups(root, "all", groups, top)
    except InventoryError as e:
        raise InventoryError(f"{p}: {e}") from None
    for need in ("collector", "agents"):
        if need not in groups or not groups[need][0]:
            raise InventoryError(f"{p}: group '{need}' is missing or has no hosts")
    chosts, cvars = groups["collector"]
    if len(chosts) != 1:
        raise InventoryError(
            f"{p}: group 'collector' must have exactly one host, has {len(chosts)}"
        )
    chost, chvars = next(iter(chosts.items()))
    cv = {**cvars, **_mapping(chvars, f"{p}: collector host {chost}")}
    site = str(top.get("bgt_site", "default"))
    try:
        wire.check_id(site, "bgt_site")
    except wire.WireError as e:
        raise InventoryError(f"{p}: {e}") from None
    port = cv.get("bgt_zenoh_port", top.get("bgt_zenoh_port", DEFAULT_PORT))
    if not isinstance(port, int) or not 0 < port < 65536:
        raise InventoryError(f"{p}: bgt_zenoh_port must be a TCP port number, got {port!r}")
    agents = []
    ahosts, avars = groups["agents"]
    for host, hvars in ahosts.items():
        v = {**avars, **_mapping(hvars, f"{p}: agents host {host}")}
        agent_id = v.get("agent_id", host)
        try:
            wire.check_id(agent_id, f"agents.{host}.agent_id")
        except wire.WireError as e:
            raise InventoryError(f"{p}: {e}") from None
        if agent_id in ADMIN_CNS:
            raise InventoryError(
                f"{p}: agents.{host}.agent_id {agent_id!r} is reserved for the collector"
            )
        adapters = v.get("adapters", [])
        if not isinstance(adapters, list) or not all(isinstance(a, str) for a in adapters):
            raise InventoryError(
                f"{p}: agents.{host}.adapters must be a list of adapter names or MACs"
            )
        agents.append(AgentHost(host, str(v.get("ansible_host", host)), agent_id, tuple(adapters)))
    ids = [a.agent_id for a in agents]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise InventoryError(f"{p}: agent ids must be unique, repeated: {', '.join(dupes)}")
    pki_dir = Path(str(top.get("bgt_pki_dir", "pki")))
    return Fleet(
        path=p,
        site=site,
        collector_host=str(chost),
        collector_address=str(cv.get("ansible_host", chost)),
        port=port,
        agents=tuple(agents),
        pki_dir=pki_dir if pki_dir.is_absolute() else p.parent / pki_dir,
    )
