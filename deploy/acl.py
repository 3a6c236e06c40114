"""Owns the collector's Zenoh access-control policy, generated from the list of agents.

The collector is the only router; every agent and CLI is a client that reaches it over mutual
TLS, so the router's ACL sees each client's certificate CN and filters what crosses its link.
Default deny; each agent may only write and answer under its own id, and only the
collector/operator identities may use the collector's control queryables.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from bgt_core import wire

# Message kinds of zenoh 1.x's ACL (checked against the installed zenoh by tests/deploy).
ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]
# What the router may pass *to* an agent on any site key: declarations (without them a
# client publisher believes nobody subscribes and drops its samples) and queries (so a
# wildcard query such as "status of every agent" reaches each agent's own queryable; the
# agent can only answer under its own keys because replies are checked on the way in).
_TO_AGENTS = [
    "declare_subscriber",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "query",
]


def _rule_id(prefix: str, name: str) -> str:
    # Rule ids must be unique; '.' and '-' are fine in them, spaces are not used.
    return f"{prefix}-{name}"


def _with_adv(prefixes: list[str]) -> list[str]:
    # '@adv' is a verbatim chunk: '**' never matches it, so the advanced publisher's cache,
    # heartbeat and liveliness keys (<key>/@adv/pub/...) need their own entries.
    return [k for p in prefixes for k in (f"{p}/**", f"{p}/**/@adv/**")]


def agent_key_exprs(site: str, agent_id: str) -> list[str]:
    """Everything agent ``agent_id`` owns: its data (with the advanced publisher's ``@adv``
    keys), liveliness token, status and clock queryables, and the acks addressed to it."""
    wire.check_id(agent_id, "agent id")
    return _with_adv(
        [
            f"ble/{site}/rssi/{agent_id}",
            wire.agent_token_key(site, agent_id),
            wire.agent_status_key(site, agent_id),
            wire.agent_clock_key(site, agent_id),
            wire.ack_key(site, agent_id),
        ]
    )


def build_acl(site: str, agent_ids: Sequence[str], admin_cns: Sequence[str]) -> dict[str, Any]:
    """The ``access_control`` section for the collector's Zenoh config.

    ``admin_cns`` are the certificate CNs with full rights on ``ble/<site>/**`` (the collector
    itself and the operator CLI); they may start/stop runs and query every agent.
    """
    wire.check_id(site, "site")
    clash = set(agent_ids) & set(admin_cns)
    if clash:
        raise ValueError(f"agent ids clash with admin certificate names: {sorted(clash)}")
    if len(set(agent_ids)) != len(agent_ids):
        raise ValueError("agent ids must be unique")
    rules: list[dict[str, Any]] = [
        {
            "id": "site-all",
            "messages": ALL_MESSAGES,
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": _with_adv([f"ble/{site}"]),
        },
        {
            "id": "site-to-agents",
            "messages": _TO_AGENTS,
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": _with_adv([f"ble/{site}"]),
        },
    ]
    subjects: list[dict[str, Any]] = [{"id": "admins", "cert_common_names": list(admin_cns)}]
    policies: list[dict[str, Any]] = [
        {"id": "admins", "rules": ["site-all"], "subjects": ["admins"]}
    ]
    for agent in agent_ids:
        rid = _rule_id("own", agent)
        rules.append(
            {
                "id": rid,
                "messages": ALL_MESSAGES,
                "flows": ["ingress", "egress"],
                "permission": "allow",
                "key_exprs": agent_key_exprs(site, agent),
            }
        )
        sid = _rule_id("agent", agent)
        subjects.append({"id": sid, "cert_common_names": [agent]})
        policies.append({"id": sid, "rules": [rid, "site-to-agents"], "subjects": [sid]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
