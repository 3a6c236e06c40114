"""Builds the Zenoh session configuration both the agents and the collector open.

The only place that knows Zenoh's configuration keys; callers say what they mean
(router or client, where to listen, where to connect, TLS files) and get a ``zenoh.Config``.
"""

from __future__ import annotations

import ipaddress
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

# A Zenoh locator: PROTOCOL/ADDRESS, optionally ?config and #metadata. Every protocol but the
# Unix-socket ones needs HOST:PORT (an IPv6 host in brackets).
_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z][a-z0-9+-]*)/(?P<addr>[^\s?#]+)(\?[^\s#]*)?(#\S*)?$")
_HOST_PORT_RE = re.compile(r"^(?P<host>\[[0-9A-Fa-f:.]+\]|[^\s:\[\]/]+):(?P<port>[0-9]{1,5})$")


def endpoint_problem(value: object) -> str | None:
    """Why ``value`` is not a Zenoh endpoint the suite accepts (agent ``connect``, collector
    ``listen``, every ``--connect``/``--listen``), or None: the one endpoint rule."""
    if not isinstance(value, str):
        return f"must be a string like tcp/192.168.1.10:7447, got {type(value).__name__}"
    m = _ENDPOINT_RE.match(value)
    if m is None:
        return f"must look like tcp/HOST:PORT (e.g. tcp/192.168.1.10:7447), got {value[:80]!r}"
    if m["proto"].startswith("unixsock"):
        return None
    hp = _HOST_PORT_RE.match(m["addr"])
    if hp is None:
        return f"needs HOST:PORT after {m['proto']}/, got {value[:80]!r}"
    if not 0 < int(hp["port"]) <= 65535:
        return f"port {hp['port']} is outside 1..65535 in {value[:80]!r}"
    return None


# Largest message a session accepts: a maximum batch (wire.MAX_PAYLOAD_BYTES, 4 MiB) plus room
# for its key and Zenoh's headers. Larger messages are refused while they arrive, before Zenoh
# reassembles them (its default would let 1 GiB through).
MAX_MESSAGE_BYTES = 4 * 1024 * 1024 + 64 * 1024
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


def zenoh_reason(err: BaseException) -> str:
    """Zenoh's error text on one line, without the Rust source locations it appends
    ('... at /path/x.rs:61.') and the brackets around its error chain; '' if it has none."""
    text = _RUST_LOCATION.sub("", " ".join(str(err).split()))
    return text.replace("[", "").replace("]", "").strip()


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
    acl: str | None = None  # JSON5 text of zenoh's `access_control` section (see load_acl)
    max_message_bytes: int = MAX_MESSAGE_BYTES


def build_config(spec: SessionSpec) -> zenoh.Config:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(spec.mode))
    # Multicast scouting would make sessions find strangers on the LAN; endpoints are explicit.
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/link/rx/max_message_size", str(int(spec.max_message_bytes)))
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
    if spec.acl is not None:
        conf.insert_json5("access_control", spec.acl)
    for key, value in spec.extra.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


class AclFileError(ValueError):
    """An ACL file that is missing or that zenoh rejects."""


def load_acl(path: str | Path) -> str:
    """Read a zenoh ACL file (JSON5, the `access_control` section as ``deploy/`` generates it).

    Zenoh itself validates it here, so a typo fails at startup with the file's name rather
    than later inside ``zenoh.open``.
    """
    import zenoh

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as e:
        raise AclFileError(f"{p}: cannot read ACL file: {e.strerror or e}") from e
    try:
        zenoh.Config().insert_json5("access_control", text)
    except zenoh.ZError as e:
        reason = zenoh_reason(e) or "invalid"
        raise AclFileError(f"{p}: not a valid zenoh access_control section: {reason}") from e
    return text


def insecure_endpoints(endpoints: Sequence[str]) -> list[str]:
    """The endpoints that would carry traffic unencrypted beyond this machine.

    Plain ``tcp``/``udp`` links on any address that is not loopback (a wildcard such as
    ``0.0.0.0`` or a hostname counts as exposed); the collector refuses to listen on these
    without an explicit ``--insecure``.
    """
    out = []
    for ep in endpoints:
        proto, _, rest = ep.partition("/")
        if proto not in ("tcp", "udp"):
            continue  # tls/quic are encrypted; unixsock-stream never leaves the host
        host = rest.split("#", 1)[0].rsplit(":", 1)[0].strip("[]")
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = host == "localhost"
        if not loopback:
            out.append(ep)
    return out
