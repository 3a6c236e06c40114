"""Builds the Zenoh session configuration both the agents and the collector open.

The only place that knows Zenoh's configuration keys; callers say what they mean
(router or client, where to listen, where to connect, TLS files) and get a ``zenoh.Config``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """PEM files for mutual TLS: the site CA, this node's certificate and key."""

    root_ca: str
    cert: str
    key: str


@dataclass(frozen=True, slots=True)
class SessionSpec:
    mode: str = "client"  # "router" for the collector, "client" for agents and CLI tools
    listen: Sequence[str] = ()
    connect: Sequence[str] = ()
    tls: TlsFiles | None = None
    extra: dict[str, object] = field(default_factory=dict)  # raw zenoh keys, for tests/ACLs


def build_config(spec: SessionSpec):  # -> zenoh.Config
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(spec.mode))
    # Multicast scouting would make sessions find strangers on the LAN; endpoints are explicit.
    conf.insert_json5("scouting/multicast/enabled", "false")
    # Advanced publishers/subscribers need sample timestamps.
    conf.insert_json5("timestamping/enabled", "true")
    if spec.mode == "router" or spec.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(spec.listen)))
    else:
        conf.insert_json5("listen/endpoints", "[]")
    if spec.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(spec.connect)))
    if spec.tls is not None:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(spec.tls.root_ca))
        conf.insert_json5("transport/link/tls/listen_private_key", json.dumps(spec.tls.key))
        conf.insert_json5("transport/link/tls/listen_certificate", json.dumps(spec.tls.cert))
        conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(spec.tls.key))
        conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(spec.tls.cert))
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
    for key, value in spec.extra.items():
        conf.insert_json5(key, json.dumps(value))
    return conf
