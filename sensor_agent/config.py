"""The agent's configuration: frozen records, the YAML loader (one-line errors naming the field)
and command-line overrides. Paths in a YAML file are relative to that file."""

from __future__ import annotations

import dataclasses
import math
import re
import socket
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bgt_core.keys import unknown_key
from bgt_core.motion import COVER_KEYS, PATH_KEYS, CoverEvent, MotionError, PathModel
from bgt_core.wire import WireError, check_id, normalize_mac
from bgt_core.zenoh_config import DEFAULT_ENDPOINT, TlsFiles, endpoint_problem
from sensor_agent.errors import ConfigError

BACKENDS = ("auto", "mgmt", "bleak", "replay", "simulated")
SCAN_MODES = ("active", "passive")
_UUID_RE = re.compile(r"^[0-9a-f]{32}$")
_ADAPTER_NAME_RE = re.compile(r"^hci[0-9]+$")


@dataclass(frozen=True, slots=True)
class AllowList:
    """Beacons to keep; both lists empty = keep everything. A reading passes if it matches either."""

    macs: frozenset[str] = frozenset()  # 12 lowercase hex digits
    ibeacon_uuids: frozenset[str] = frozenset()  # 32 lowercase hex digits

    @property
    def everything(self) -> bool:
        return not self.macs and not self.ibeacon_uuids


@dataclass(frozen=True, slots=True)
class ReplayConfig:
    paths: tuple[Path, ...] = ()
    speed: float = 1.0  # 0 = as fast as possible
    keep_time: bool = False


@dataclass(frozen=True, slots=True)
class SimulatedConfig:
    seed: int = 0
    sensors: tuple[str, ...] = ()  # MACs or aliases from the site's .dev; empty = all
    site: str = "tetam"  # a built-in site name, or a folder holding <name>.dev
    beacons: tuple[str, ...] = ()  # beacon MACs; empty = the site's beacons
    path: PathModel = field(default_factory=PathModel)
    t0: float | None = None  # Unix seconds at path time 0; None = when the agent starts
    events: tuple[CoverEvent, ...] = ()
    rate_hz: float = 10.0  # adverts per second per beacon
    tx_1m: float = -59.0  # RSSI at 1 m, dBm
    path_loss_exponent: float = 2.0
    sigma_db: float = 3.0
    drop_prob: float = 0.05  # chance any one advert is missed by any one sensor
    floor_dbm: float = -100.0  # weaker than this is never heard


@dataclass(frozen=True, slots=True)
class SpoolConfig:
    dir: Path | None = None
    max_mb: int = 256
    # Batches the collector refuses (a stream cap, a quota): drop them on its negative
    # acknowledgement, or keep re-sending them until it takes them (limits raised).
    on_refused: str = "drop"


@dataclass(frozen=True, slots=True)
class WatchdogConfig:
    silent_s: float = 60.0  # no advertisement for this long -> restart that adapter's scanner
    power_cycle_after: int = 2  # still silent after this many restarts -> power-cycle the adapter


@dataclass(frozen=True, slots=True)
class AgentConfig:
    agent_id: str
    site: str = "default"
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    backend: str = "auto"  # auto: the management socket if it can be used, else bleak
    batch_ms: int = 100
    adapters: tuple[str, ...] = ()  # names (hci0) or MACs; empty = every adapter
    scan_mode: str = "active"
    allow: AllowList = field(default_factory=AllowList)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    simulated: SimulatedConfig = field(default_factory=SimulatedConfig)
    spool: SpoolConfig = field(default_factory=SpoolConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    tls: TlsFiles | None = None
    status_interval_s: float = 5.0
    ack_timeout_s: float = 30.0  # replay end: how long to wait for the collector's acks

    def to_dict(self) -> dict[str, Any]:
        """The resolved configuration as plain YAML-able data (for `sensor-agent check`)."""
        sim = self.simulated
        return {
            "agent_id": self.agent_id,
            "site": self.site,
            "connect": list(self.connect),
            "backend": self.backend,
            "batch_ms": self.batch_ms,
            "adapters": list(self.adapters),
            "scan_mode": self.scan_mode,
            "allow": {
                "macs": sorted(self.allow.macs),
                "ibeacon_uuids": sorted(self.allow.ibeacon_uuids),
            },
            "replay": {
                "paths": [str(p) for p in self.replay.paths],
                "speed": self.replay.speed,
                "keep_time": self.replay.keep_time,
            },
            "simulated": {
                "seed": sim.seed,
                "sensors": list(sim.sensors),
                "site": sim.site,
                "beacons": list(sim.beacons),
                "path": sim.path.to_dict(),
                "t0": sim.t0,
                "events": [e.to_dict() for e in sim.events],
                "rate_hz": sim.rate_hz,
                "tx_1m": sim.tx_1m,
                "path_loss_exponent": sim.path_loss_exponent,
                "sigma_db": sim.sigma_db,
                "drop_prob": sim.drop_prob,
                "floor_dbm": sim.floor_dbm,
            },
            "spool": {
                "dir": None if self.spool.dir is None else str(self.spool.dir),
                "max_mb": self.spool.max_mb,
                "on_refused": self.spool.on_refused,
            },
            "watchdog": {
                "silent_s": self.watchdog.silent_s,
                "power_cycle_after": self.watchdog.power_cycle_after,
            },
            "tls": None
            if self.tls is None
            else {"root_ca": self.tls.root_ca, "cert": self.tls.cert, "key": self.tls.key},
            "status_interval_s": self.status_interval_s,
            "ack_timeout_s": self.ack_timeout_s,
        }


def default_agent_id() -> str:
    """The host name, trimmed to the characters an agent id may hold."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:64]
    return name or "agent"


# ---------------------------------------------------------------------------------------------
# Field checkers: each raises ConfigError("<source>: <field> must be ..., got <value>")


class _Fields:
    def __init__(self, source: str, base_dir: Path) -> None:
        self.source = source
        self.base_dir = base_dir

    def fail(self, name: str, what: str, value: Any) -> ConfigError:
        return ConfigError(f"{self.source}: {name} must be {what}, got {value!r}")

    def mapping(self, d: Any, name: str, allowed: Sequence[str]) -> Mapping[str, Any]:
        if d is None:
            return {}
        if not isinstance(d, Mapping):
            raise self.fail(name or "the top level", "a mapping", d)
        message = unknown_key(d, allowed, self.source, name)
        if message is not None:
            raise ConfigError(message)
        return d

    def pos_int(self, v: Any, name: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise self.fail(name, "a positive integer", v)
        return v

    def integer(self, v: Any, name: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(name, "an integer", v)
        return v

    def number(
        self,
        v: Any,
        name: str,
        lo: float | None = None,
        lo_open: bool = False,
        hi: float | None = None,
    ) -> float:
        ok = not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
        if ok and lo is not None:
            ok = v > lo if lo_open else v >= lo
        if ok and hi is not None:
            ok = v <= hi
        if not ok:
            if lo is None and hi is None:
                what = "a number"
            elif hi is None:
                what = f"a number {'>' if lo_open else '>='} {lo:g}"
            else:
                what = f"a number in [{lo:g}, {hi:g}]"
            raise self.fail(name, what, v)
        return float(v)

    def boolean(self, v: Any, name: str) -> bool:
        if not isinstance(v, bool):
            raise self.fail(name, "true or false", v)
        return v

    def string(self, v: Any, name: str) -> str:
        if not isinstance(v, str) or not v:
            raise self.fail(name, "a non-empty string", v)
        return v

    def str_list(self, v: Any, name: str) -> tuple[str, ...]:
        if v is None:
            return ()
        if isinstance(v, str) or not isinstance(v, Sequence):
            raise self.fail(name, "a list of strings", v)
        for i, s in enumerate(v):
            if not isinstance(s, str) or not s:
                raise self.fail(f"{name}[{i}]", "a non-empty string", s)
        return tuple(v)

    def choice(self, v: Any, name: str, choices: Sequence[str]) -> str:
        if v not in choices:
            raise self.fail(name, " | ".join(choices), v)
        return str(v)

    def ident(self, v: Any, name: str) -> str:
        try:
            return check_id(v, name)
        except WireError:
            raise self.fail(name, "1-64 characters of [A-Za-z0-9_.-]", v) from None

    def mac(self, v: Any, name: str) -> str:
        try:
            return normalize_mac(v)
        except WireError:
            raise self.fail(name, "a MAC address", v) from None

    def path(self, v: Any, name: str) -> Path:
        p = Path(self.string(v, name)).expanduser()
        return p if p.is_absolute() else self.base_dir / p


def check_endpoint(value: str, name: str = "connect", source: str = "command line") -> str:
    problem = endpoint_problem(value)
    if problem is not None:
        raise ConfigError(f"{source}: {name} {problem}")
    return value


def _adapter(f: _Fields, v: Any, name: str) -> str:
    s = f.string(v, name)
    if _ADAPTER_NAME_RE.match(s):
        return s
    return f.mac(s, name)


_TOP_KEYS = (
    "agent_id",
    "site",
    "connect",
    "backend",
    "batch_ms",
    "adapters",
    "scan_mode",
    "allow",
    "replay",
    "simulated",
    "spool",
    "watchdog",
    "tls",
    "status_interval_s",
    "ack_timeout_s",
)
_SIM_KEYS = (
    "seed",
    "sensors",
    "site",
    "beacons",
    "path",
    "t0",
    "events",
    "rate_hz",
    "tx_1m",
    "path_loss_exponent",
    "sigma_db",
    "drop_prob",
    "floor_dbm",
)


def parse_config(
    data: Any, source: str = "agent.yaml", base_dir: Path | None = None
) -> AgentConfig:
    """Validate a parsed YAML document; ``base_dir`` anchors relative paths (default: cwd)."""
    f = _Fields(source, base_dir if base_dir is not None else Path.cwd())
    d = f.mapping(data, "", _TOP_KEYS)
    out: dict[str, Any] = {}
    out["agent_id"] = f.ident(d["agent_id"], "agent_id") if "agent_id" in d else default_agent_id()
    if "site" in d:
        out["site"] = f.ident(d["site"], "site")
    if "connect" in d:
        eps = f.str_list(d["connect"], "connect")
        out["connect"] = tuple(
            check_endpoint(e, f"connect[{i}]", source) for i, e in enumerate(eps)
        )
    if "backend" in d:
        out["backend"] = f.choice(d["backend"], "backend", BACKENDS)
    if "batch_ms" in d:
        out["batch_ms"] = f.pos_int(d["batch_ms"], "batch_ms")
    if "adapters" in d:
        names = f.str_list(d["adapters"], "adapters")
        out["adapters"] = tuple(_adapter(f, a, f"adapters[{i}]") for i, a in enumerate(names))
    if "scan_mode" in d:
        out["scan_mode"] = f.choice(d["scan_mode"], "scan_mode", SCAN_MODES)
    if "allow" in d:
        out["allow"] = _allow(f, d["allow"])
    if "replay" in d:
        out["replay"] = _replay(f, d["replay"])
    if "simulated" in d:
        out["simulated"] = _simulated(f, d["simulated"])
    if "spool" in d:
        out["spool"] = _spool(f, d["spool"])
    if "watchdog" in d:
        out["watchdog"] = _watchdog(f, d["watchdog"])
    if d.get("tls") is not None:
        out["tls"] = _tls(f, d["tls"])
    if "status_interval_s" in d:
        out["status_interval_s"] = f.number(
            d["status_interval_s"], "status_interval_s", lo=0.0, lo_open=True
        )
    if "ack_timeout_s" in d:
        out["ack_timeout_s"] = f.number(d["ack_timeout_s"], "ack_timeout_s", lo=0.0)
    return AgentConfig(**out)


def _allow(f: _Fields, raw: Any) -> AllowList:
    a = f.mapping(raw, "allow", ("macs", "ibeacon_uuids"))
    macs = f.str_list(a.get("macs"), "allow.macs")
    uuids = f.str_list(a.get("ibeacon_uuids"), "allow.ibeacon_uuids")
    norm_uuids = []
    for i, u in enumerate(uuids):
        flat = u.replace("-", "").lower()
        if not _UUID_RE.match(flat):
            raise f.fail(f"allow.ibeacon_uuids[{i}]", "a 128-bit UUID", u)
        norm_uuids.append(flat)
    return AllowList(
        frozenset(f.mac(m, f"allow.macs[{i}]") for i, m in enumerate(macs)), frozenset(norm_uuids)
    )


def _replay(f: _Fields, raw: Any) -> ReplayConfig:
    r = f.mapping(raw, "replay", ("paths", "speed", "keep_time"))
    return ReplayConfig(
        tuple(
            f.path(p, f"replay.paths[{i}]")
            for i, p in enumerate(f.str_list(r.get("paths"), "replay.paths"))
        ),
        f.number(r.get("speed", 1.0), "replay.speed", lo=0.0),
        f.boolean(r.get("keep_time", False), "replay.keep_time"),
    )


def _spool(f: _Fields, raw: Any) -> SpoolConfig:
    s = f.mapping(raw, "spool", ("dir", "max_mb", "on_refused"))
    sdir = s.get("dir")
    return SpoolConfig(
        None if sdir is None else f.path(sdir, "spool.dir"),
        f.pos_int(s.get("max_mb", 256), "spool.max_mb"),
        f.choice(s.get("on_refused", "drop"), "spool.on_refused", ("drop", "keep")),
    )


def _watchdog(f: _Fields, raw: Any) -> WatchdogConfig:
    w = f.mapping(raw, "watchdog", ("silent_s", "power_cycle_after"))
    pca = w.get("power_cycle_after", 2)
    if isinstance(pca, bool) or not isinstance(pca, int) or pca < 0:
        raise f.fail("watchdog.power_cycle_after", "an integer >= 0", pca)
    return WatchdogConfig(
        f.number(w.get("silent_s", 60.0), "watchdog.silent_s", lo=0.0, lo_open=True), pca
    )


def _tls(f: _Fields, raw: Any) -> TlsFiles:
    t = f.mapping(raw, "tls", ("root_ca", "cert", "key"))
    for k in ("root_ca", "cert", "key"):
        if k not in t:
            raise ConfigError(f"{f.source}: tls.{k} is missing (tls needs root_ca, cert and key)")
    return TlsFiles(*(str(f.path(t[k], f"tls.{k}")) for k in ("root_ca", "cert", "key")))


def _simulated(f: _Fields, raw: Any) -> SimulatedConfig:
    s = f.mapping(raw, "simulated", _SIM_KEYS)
    kw: dict[str, Any] = {}
    if "seed" in s:
        kw["seed"] = f.integer(s["seed"], "simulated.seed")
    if "sensors" in s:
        kw["sensors"] = f.str_list(s["sensors"], "simulated.sensors")
    if "site" in s:
        site = f.string(s["site"], "simulated.site")
        # a bare name is a built-in site; anything path-like is relative to the config file
        kw["site"] = (
            str(f.path(site, "simulated.site")) if ("/" in site or site.endswith(".dev")) else site
        )
    if "beacons" in s:
        kw["beacons"] = tuple(
            f.mac(m, f"simulated.beacons[{i}]")
            for i, m in enumerate(f.str_list(s["beacons"], "simulated.beacons"))
        )
    if s.get("path") is not None:
        kw["path"] = _sim_path(f, s["path"])
    if s.get("t0") is not None:
        kw["t0"] = f.number(s["t0"], "simulated.t0", lo=0.0)
    if s.get("events") is not None:
        kw["events"] = _sim_events(f, s["events"])
    if "rate_hz" in s:
        kw["rate_hz"] = f.number(s["rate_hz"], "simulated.rate_hz", lo=0.0, lo_open=True)
    for k in ("tx_1m", "floor_dbm"):
        if k in s:
            kw[k] = f.number(s[k], f"simulated.{k}")
    if "path_loss_exponent" in s:
        kw["path_loss_exponent"] = f.number(
            s["path_loss_exponent"], "simulated.path_loss_exponent", lo=0.0, lo_open=True
        )
    if "sigma_db" in s:
        kw["sigma_db"] = f.number(s["sigma_db"], "simulated.sigma_db", lo=0.0)
    if "drop_prob" in s:
        kw["drop_prob"] = f.number(s["drop_prob"], "simulated.drop_prob", lo=0.0, hi=1.0)
    return SimulatedConfig(**kw)


def _sim_path(f: _Fields, p: Any) -> PathModel:
    if not isinstance(p, Mapping):
        raise f.fail("simulated.path", "a mapping (waypoints, speed_mps, dwell_s)", p)
    f.mapping(p, "simulated.path", PATH_KEYS)
    try:
        return PathModel.from_dict(p)
    except MotionError as e:
        raise ConfigError(f"{f.source}: simulated.path: {e}") from None


def _sim_events(f: _Fields, ev: Any) -> tuple[CoverEvent, ...]:
    if isinstance(ev, str) or not isinstance(ev, Sequence):
        raise f.fail("simulated.events", "a list of cover events", ev)
    events = []
    for i, item in enumerate(ev):
        if not isinstance(item, Mapping):
            raise f.fail(f"simulated.events[{i}]", "a mapping", item)
        f.mapping(item, f"simulated.events[{i}]", COVER_KEYS)
        try:
            events.append(CoverEvent.from_dict(item))
        except MotionError as err:
            raise ConfigError(f"{f.source}: simulated.events[{i}]: {err}") from None
    return tuple(events)


def load_config(path: str | Path | None) -> AgentConfig:
    """Read and validate a YAML file; ``None`` gives the defaults."""
    if path is None:
        return parse_config({}, "defaults")
    from bgt_core.safe_yaml import YamlError, decode_utf8, loads, read_bytes_limited

    path = Path(path)
    try:
        data = loads(decode_utf8(read_bytes_limited(path), path.name), path.name)
    except YamlError as e:
        raise ConfigError(str(e)) from None
    return parse_config({} if data is None else data, path.name, path.resolve().parent)


def with_overrides(
    cfg: AgentConfig,
    *,
    agent_id: str | None = None,
    site: str | None = None,
    connect: Sequence[str] = (),
    backend: str | None = None,
    adapters: Sequence[str] = (),
    replay: Sequence[str | Path] = (),
    replay_speed: float | None = None,
    replay_keep_time: bool | None = None,
    scan_mode: str | None = None,
    ack_timeout_s: float | None = None,
) -> AgentConfig:
    """Apply command-line flags on top of a loaded config; empty/None flags keep the file's value.

    Giving replay files without a backend selects the replay backend.
    """
    f = _Fields("command line", Path.cwd())
    kw: dict[str, Any] = {}
    if agent_id is not None:
        kw["agent_id"] = f.ident(agent_id, "--agent-id")
    if site is not None:
        kw["site"] = f.ident(site, "--site")
    if connect:
        kw["connect"] = tuple(check_endpoint(e, "--connect") for e in connect)
    if backend is not None:
        kw["backend"] = f.choice(backend, "--backend", BACKENDS)
    elif replay:
        kw["backend"] = "replay"
    if adapters:
        kw["adapters"] = tuple(_adapter(f, a, "--adapter") for a in adapters)
    if scan_mode is not None:
        kw["scan_mode"] = f.choice(scan_mode, "--scan-mode", SCAN_MODES)
    if ack_timeout_s is not None:
        kw["ack_timeout_s"] = f.number(ack_timeout_s, "--ack-timeout", lo=0.0)
    rp = cfg.replay
    if replay:
        rp = dataclasses.replace(rp, paths=tuple(f.path(str(p), "--replay") for p in replay))
    if replay_speed is not None:
        rp = dataclasses.replace(rp, speed=f.number(replay_speed, "--replay-speed", lo=0.0))
    if replay_keep_time is not None:
        rp = dataclasses.replace(rp, keep_time=replay_keep_time)
    kw["replay"] = rp
    out = dataclasses.replace(cfg, **kw)
    if out.backend == "replay" and not out.replay.paths:
        raise ConfigError("the replay backend needs files: give --replay PATH or replay.paths")
    return out
