"""Collector settings: the collector.yaml schema, its validation, and the Zenoh session it implies.

Paths in the file are relative to the file; CLI flags override file values (see ``with_overrides``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from bgt_core.keys import unknown_key
from bgt_core.wire import WireError, check_id
from bgt_core.zenoh_config import (
    DEFAULT_ENDPOINT,
    SessionSpec,
    TlsFiles,
    endpoint_problem,
    insecure_endpoints,
)
from collector.errors import ConfigError

KEYS = (
    "site",
    "data_dir",
    "listen",
    "tls",
    "insecure",
    "acl",
    "fsync_interval_s",
    "clock_interval_s",
    "limits",
)


@dataclass(frozen=True, slots=True)
class Limits:
    """What one agent (misconfigured, buggy or hostile) can make the collector hold.

    streams_per_agent / streams_total: (agent, sensor) streams accepted; batches of further
    streams are refused (not written, not acknowledged), counted and reported. open_files: .mbd
    files open at once (least recently used closed first; also kept under half the descriptor
    limit). queue_mb: received batches waiting for the writer, in MiB of decoded rows.
    agent_readings_per_s: what one agent may write, on average over 10 s; agent_mb_per_run: how
    much of one run's files one agent may fill. Batches past either are refused with a negative
    acknowledgement (the agent drops them, see protocol.md) and counted by agent.
    """

    streams_per_agent: int = 64
    streams_total: int = 1024
    open_files: int = 256
    queue_mb: float = 64.0
    agent_readings_per_s: float = 20_000.0
    agent_mb_per_run: float = 4096.0

    RANGES = {
        "streams_per_agent": (1, 100_000),
        "streams_total": (1, 1_000_000),
        "open_files": (1, 65_536),
        "queue_mb": (1, 65_536),
        "agent_readings_per_s": (1, 10_000_000),
        "agent_mb_per_run": (1, 10_000_000),
    }
    FLOATS = frozenset({"queue_mb", "agent_readings_per_s", "agent_mb_per_run"})


@dataclass(frozen=True, slots=True)
class CollectorConfig:
    site: str = "default"
    data_dir: Path = Path("data")
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    tls: TlsFiles | None = None
    insecure: bool = False
    acl: Path | None = None  # zenoh access-control JSON5 file
    fsync_interval_s: float = 1.0
    clock_interval_s: float = 120.0  # agent clock checks during a run (also at start and stop)
    limits: Limits = Limits()

    def session_spec(self, acl_text: str | None = None) -> SessionSpec:
        return SessionSpec(mode="router", listen=self.listen, tls=self.tls, acl=acl_text)

    def with_overrides(
        self,
        *,
        data_dir: Path | None = None,
        listen: list[str] | None = None,
        site: str | None = None,
        insecure: bool = False,
    ) -> CollectorConfig:
        """Apply CLI flags (None/False = keep the file's value) and re-check the result."""
        cfg = self
        if insecure:
            cfg = replace(cfg, insecure=True)
        if data_dir is not None:
            cfg = replace(cfg, data_dir=Path(data_dir))
        if listen:
            cfg = replace(cfg, listen=tuple(listen))
        if site is not None:
            cfg = replace(cfg, site=site)
        cfg.validate("options")
        return cfg

    def describe(self) -> dict[str, Any]:
        """The resolved settings as plain data (what `collector serve --check` prints)."""
        return {
            "site": self.site,
            "data_dir": str(self.data_dir),
            "listen": list(self.listen),
            "tls": None
            if self.tls is None
            else {"root_ca": self.tls.root_ca, "cert": self.tls.cert, "key": self.tls.key},
            "insecure": self.insecure,
            "acl": None if self.acl is None else str(self.acl),
            "fsync_interval_s": self.fsync_interval_s,
            "clock_interval_s": self.clock_interval_s,
            "limits": {k: getattr(self.limits, k) for k in Limits.RANGES},
        }

    def validate(self, where: str) -> None:
        """Checks that involve several fields; raises ConfigError naming `where`."""
        try:
            check_id(self.site, "site")
        except WireError as e:
            raise ConfigError(f"{where}: {e}") from None
        for ep in self.listen:
            _check_endpoint(ep, where, "listen")
            if ep.startswith("tls/") and self.tls is None:
                raise ConfigError(
                    f"{where}: listen endpoint {ep} needs tls: {{root_ca, cert, key}}"
                )
        exposed = insecure_endpoints(self.listen)
        if exposed and not self.insecure:
            raise ConfigError(
                f"{where}: listen endpoint {exposed[0]} is unencrypted beyond this machine; "
                "use tls/... with tls files, or allow it with insecure: true / --insecure"
            )


def _check_endpoint(ep: Any, where: str, field: str) -> None:
    problem = endpoint_problem(ep)
    if problem is not None:
        raise ConfigError(f"{where}: {field} entry {problem}")


def load_config(path: str | Path) -> CollectorConfig:
    """Read and validate a collector.yaml; every problem is one ConfigError line naming the field."""
    from bgt_core.safe_yaml import YamlError, decode_utf8, loads, read_bytes_limited

    path = Path(path)
    name = path.name
    try:
        raw = loads(decode_utf8(read_bytes_limited(path), name), name)
    except YamlError as e:
        raise ConfigError(str(e)) from None
    return parse_config(raw or {}, base=path.parent, name=name)


def parse_config(raw: Any, *, base: Path, name: str = "collector.yaml") -> CollectorConfig:
    if not isinstance(raw, dict):
        raise ConfigError(f"{name}: expected a mapping of settings at the top level")
    message = unknown_key(raw, KEYS, name)
    if message is not None:
        raise ConfigError(message)
    cfg = CollectorConfig()
    kw: dict[str, Any] = {}
    if "site" in raw:
        kw["site"] = _str(raw["site"], name, "site")
    if "data_dir" in raw:
        kw["data_dir"] = base / _str(raw["data_dir"], name, "data_dir")
    else:
        kw["data_dir"] = base / cfg.data_dir
    if "listen" in raw:
        kw["listen"] = _listen(raw["listen"], name)
    if raw.get("tls") is not None:
        kw["tls"] = _tls(raw["tls"], base, name)
    if "insecure" in raw:
        if not isinstance(raw["insecure"], bool):
            raise ConfigError(f"{name}: insecure must be true or false, got {raw['insecure']!r}")
        kw["insecure"] = raw["insecure"]
    if raw.get("acl") is not None:
        acl = base / _str(raw["acl"], name, "acl")
        if not acl.is_file():
            raise ConfigError(f"{name}: acl file not found: {acl}")
        kw["acl"] = acl
    if "fsync_interval_s" in raw:
        kw["fsync_interval_s"] = _seconds(raw, "fsync_interval_s", name, 0, 3600)
    if "clock_interval_s" in raw:
        kw["clock_interval_s"] = _seconds(raw, "clock_interval_s", name, 1, 86400)
    if raw.get("limits") is not None:
        kw["limits"] = _limits(raw["limits"], name)
    cfg = replace(cfg, **kw)
    cfg.validate(name)
    return cfg


def _listen(listen: Any, name: str) -> tuple[str, ...]:
    """``listen``: one endpoint or a non-empty list of them."""
    given = listen
    if isinstance(listen, str):
        listen = [listen]
    if not isinstance(listen, list) or not listen:
        raise ConfigError(f"{name}: listen must be a non-empty list of endpoints, got {given!r}")
    for ep in listen:
        _check_endpoint(ep, name, "listen")
    return tuple(listen)


TLS_KEYS = ("root_ca", "cert", "key")


def _tls(tls: Any, base: Path, name: str) -> TlsFiles:
    """``tls``: the CA, certificate and key files, relative to ``base``; each must exist."""
    if isinstance(tls, dict) and (message := unknown_key(tls, TLS_KEYS, name, "tls")):
        raise ConfigError(message)
    if not isinstance(tls, dict) or set(tls) != set(TLS_KEYS):
        raise ConfigError(f"{name}: tls must be null or a mapping with root_ca, cert and key")
    files = {k: base / _str(v, name, f"tls.{k}") for k, v in tls.items()}
    for k, p in files.items():
        if not p.is_file():
            raise ConfigError(f"{name}: tls.{k} file not found: {p}")
    return TlsFiles(str(files["root_ca"]), str(files["cert"]), str(files["key"]))


def _seconds(raw: dict[str, Any], key: str, name: str, lo: int, hi: int) -> float:
    """``raw[key]``: a number of seconds in ``[lo, hi]`` (not a bool)."""
    v = raw[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi:
        raise ConfigError(f"{name}: {key} must be a number of seconds in [{lo}, {hi}], got {v!r}")
    return float(v)


def _limits(raw: Any, name: str) -> Limits:
    if not isinstance(raw, dict):
        raise ConfigError(f"{name}: limits must be a mapping ({', '.join(Limits.RANGES)})")
    message = unknown_key(raw, Limits.RANGES, name, "limits")
    if message is not None:
        raise ConfigError(message)
    kw: dict[str, Any] = {}
    for k, v in raw.items():
        lo, hi = Limits.RANGES[k]
        whole = k not in Limits.FLOATS
        ok = (
            not isinstance(v, bool)
            and isinstance(v, int if whole else int | float)
            and lo <= v <= hi
        )
        if not ok:
            raise ConfigError(
                f"{name}: limits.{k} must be {'an integer' if whole else 'a number'} "
                f"in [{lo}, {hi}], got {v!r}"
            )
        kw[k] = v if whole else float(v)
    return replace(Limits(), **kw)


def _str(v: Any, name: str, field: str) -> str:
    if not isinstance(v, str) or not v:
        raise ConfigError(f"{name}: {field} must be a non-empty string, got {v!r}")
    return v


def check_files(cfg: CollectorConfig) -> None:
    """What `serve --check` adds to parsing: the TLS files are PEM of the right kind, the ACL file
    is accepted by zenoh, and the whole Zenoh configuration builds. One ConfigError line otherwise."""
    from bgt_core.zenoh_config import AclFileError, build_config, load_acl, zenoh_reason

    acl_text = None
    if cfg.acl is not None:
        try:
            acl_text = load_acl(cfg.acl)
        except AclFileError as e:
            raise ConfigError(zenoh_reason(e)) from None
    if cfg.tls is not None:
        from cryptography import x509
        from cryptography.hazmat.primitives.serialization import load_pem_private_key

        checks = (
            ("tls.root_ca", cfg.tls.root_ca, x509.load_pem_x509_certificate),
            ("tls.cert", cfg.tls.cert, x509.load_pem_x509_certificate),
            ("tls.key", cfg.tls.key, lambda b: load_pem_private_key(b, password=None)),
        )
        for field, path, load in checks:
            try:
                load(Path(path).read_bytes())
            except OSError as e:
                raise ConfigError(f"{field}: cannot read {path}: {e.strerror}") from None
            except (ValueError, TypeError) as e:
                raise ConfigError(
                    f"{field}: {path} is not a usable PEM file: "
                    f"{str(e).splitlines()[0] if str(e) else type(e).__name__}"
                ) from None
    try:
        build_config(cfg.session_spec(acl_text))
    except Exception as e:  # noqa: BLE001 - zenoh reports config problems as ZError or ValueError
        raise ConfigError(f"zenoh rejects the configuration: {zenoh_reason(e)}") from None


def descriptor_budget(open_files: int) -> int:
    """Files the writer may hold open: the configured number, at most half the soft RLIMIT_NOFILE
    (Zenoh's sockets and the rest of the process need the other half)."""
    try:
        import resource

        soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (ImportError, OSError, ValueError):
        return open_files
    if soft == resource.RLIM_INFINITY:
        return open_files
    return max(4, min(open_files, soft // 2))
