"""Agent config: YAML loading, defaults, one-line errors naming the field, flag overrides."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from sensor_agent.config import AgentConfig, load_config, parse_config, with_overrides
from sensor_agent.errors import ConfigError

FULL = """\
agent_id: pi-01
site: default
connect: [tcp/127.0.0.1:7447]
backend: bleak
batch_ms: 100
adapters: [hci0, "AA:BB:CC:DD:EE:01"]
scan_mode: passive
allow: {macs: ["E7:8F:13:56:24:CE"], ibeacon_uuids: ["E2C56DB5-DFFB-48D2-B060-D0F5A71096E0"]}
replay: {paths: [rec/a.mbd], speed: 2.5, keep_time: true}
simulated: {seed: 7, sensors: [sensor10, "000000000101"], site: tetam,
            path: {waypoints: [[1, 1, 1.5], [5, 1, 1.5]], speed_mps: 0.5, dwell_s: 2},
            t0: 1700000000.5, events: [{start_s: 10, duration_s: 3, attenuation_db: 25, drop_prob: 0.9}]}
spool: {dir: spool, max_mb: 64}
tls: {root_ca: pki/ca.pem, cert: pki/pi-01.pem, key: pki/pi-01.key}
status_interval_s: 5
"""


def write(tmp_path: Path, text: str, name: str = "agent.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_full_file_parses_with_paths_relative_to_it(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, FULL))
    base = tmp_path.resolve()
    assert cfg.agent_id == "pi-01"
    assert cfg.adapters == ("hci0", "aabbccddee01")
    assert cfg.scan_mode == "passive"
    assert cfg.allow.macs == frozenset({"e78f135624ce"})
    assert cfg.allow.ibeacon_uuids == frozenset({"e2c56db5dffb48d2b060d0f5a71096e0"})
    assert cfg.replay.paths == (base / "rec" / "a.mbd",)
    assert (cfg.replay.speed, cfg.replay.keep_time) == (2.5, True)
    assert cfg.simulated.seed == 7
    assert cfg.simulated.sensors == ("sensor10", "000000000101")
    assert cfg.simulated.path.waypoints == ((1.0, 1.0, 1.5), (5.0, 1.0, 1.5))
    assert cfg.simulated.path.dwell_s == 2
    assert cfg.simulated.t0 == 1700000000.5
    assert cfg.simulated.events[0].attenuation_db == 25
    assert cfg.spool.dir == base / "spool"
    assert cfg.spool.max_mb == 64
    assert cfg.tls is not None
    assert cfg.tls.cert == str(base / "pki" / "pi-01.pem")


def test_empty_file_gives_defaults(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, ""))
    assert (cfg.site, cfg.connect, cfg.backend, cfg.batch_ms) == (
        "default",
        ("tcp/127.0.0.1:7447",),
        "auto",
        100,
    )
    assert cfg.allow.everything
    assert cfg.tls is None
    assert cfg.spool.dir is None
    assert cfg.ack_timeout_s == 30


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("batch_ms: x", "agent.yaml: batch_ms must be a positive integer, got 'x'"),
        ("batch_ms: 0", "agent.yaml: batch_ms must be a positive integer, got 0"),
        ("agent_id: 'pi 01'", "agent.yaml: agent_id must be 1-64 characters"),
        (
            "backend: usb",
            "agent.yaml: backend must be auto | mgmt | bleak | replay | simulated, got 'usb'",
        ),
        ("scan_mode: loud", "agent.yaml: scan_mode must be active | passive"),
        ("connect: tcp/1.2.3.4:7447", "agent.yaml: connect must be a list of strings"),
        ("connect: [localhost]", "agent.yaml: connect[0] must look like tcp/HOST:PORT"),
        ("adapters: [hci0, nonsense]", "agent.yaml: adapters[1] must be a MAC address"),
        ("allow: {macs: [zz]}", "agent.yaml: allow.macs[0] must be a MAC address"),
        (
            "allow: {ibeacon_uuids: [1234]}",
            "agent.yaml: allow.ibeacon_uuids[0] must be a non-empty string",
        ),
        ("allow: {colours: []}", "agent.yaml: unknown key 'allow.colours'"),
        ("replay: {speed: -1}", "agent.yaml: replay.speed must be a number >= 0, got -1"),
        ("replay: {keep_time: 'yes'}", "agent.yaml: replay.keep_time must be true or false"),
        ("simulated: {seed: 1.5}", "agent.yaml: simulated.seed must be an integer, got 1.5"),
        ("simulated: {drop_prob: 2}", "agent.yaml: simulated.drop_prob must be a number in [0, 1]"),
        (
            "simulated: {path: {waypoints: [[1, 2]]}}",
            "agent.yaml: simulated.path: waypoint 0 must be [x, y, z]",
        ),
        (
            "simulated: {events: [{start_s: 1}]}",
            "agent.yaml: simulated.events[0]: cover event: missing 'duration_s'",
        ),
        ("spool: {max_mb: -5}", "agent.yaml: spool.max_mb must be a positive integer, got -5"),
        ("tls: {root_ca: ca.pem}", "agent.yaml: tls.cert is missing"),
        ("status_interval_s: 0", "agent.yaml: status_interval_s must be a number > 0, got 0"),
        ("colour: blue", "agent.yaml: unknown key 'colour'"),
        ("- just\n- a list", "agent.yaml: the top level must be a mapping"),
        ("batch_ms: [", "agent.yaml:2: not valid YAML"),
    ],
)
def test_bad_values_name_the_field(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, text))
    assert str(e.value).startswith(message)
    assert "\n" not in str(e.value)


def test_missing_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read"):
        load_config(tmp_path / "nope.yaml")


def test_flags_override_the_file(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, FULL))
    out = with_overrides(
        cfg,
        agent_id="pi-09",
        site="lab",
        connect=["tcp/10.0.0.1:7447"],
        adapters=["hci1"],
        replay=["x.mbd"],
        replay_speed=0.0,
    )
    assert (out.agent_id, out.site, out.connect, out.adapters) == (
        "pi-09",
        "lab",
        ("tcp/10.0.0.1:7447",),
        ("hci1",),
    )
    # replay files without --backend pick the replay backend; keep_time stays from the file
    assert out.backend == "replay"
    assert out.replay.paths == (Path.cwd() / "x.mbd",)
    assert (out.replay.speed, out.replay.keep_time) == (0.0, True)
    assert with_overrides(cfg) == cfg


def test_bad_flags_are_one_line() -> None:
    cfg = parse_config({})
    with pytest.raises(ConfigError, match="command line: --connect must look like tcp/HOST:PORT"):
        with_overrides(cfg, connect=["7447"])
    with pytest.raises(ConfigError, match="replay backend needs files"):
        with_overrides(cfg, backend="replay")
    with pytest.raises(ConfigError, match="--replay-speed must be a number >= 0"):
        with_overrides(cfg, replay=["a.mbd"], replay_speed=-2.0)


def test_to_dict_round_trips(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, FULL))
    again = parse_config(yaml.safe_load(yaml.safe_dump(cfg.to_dict())), "again", tmp_path)
    assert again == cfg
    assert isinstance(again, AgentConfig)


def test_check_command_prints_resolved_config(tmp_path: Path) -> None:
    p = write(tmp_path, "agent_id: pi-03\nbatch_ms: 50\n")
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "from sensor_agent.cli import main; main()",
            "check",
            "--config",
            str(p),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    printed = yaml.safe_load(r.stdout)
    assert printed["agent_id"] == "pi-03"
    assert printed["batch_ms"] == 50
    assert printed["connect"] == ["tcp/127.0.0.1:7447"]

    bad = write(tmp_path, "batch_ms: x\n", "bad.yaml")
    r = subprocess.run(
        [
            sys.executable,
            "-c",
            "from sensor_agent.cli import main; main()",
            "check",
            "--config",
            str(bad),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1
    assert r.stderr.strip() == "bad.yaml: batch_ms must be a positive integer, got 'x'"


def test_simulated_site_path_is_relative_to_the_file(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, "simulated: {site: sites/lab.dev}"))
    assert cfg.simulated.site == str(tmp_path.resolve() / "sites" / "lab.dev")
    assert load_config(write(tmp_path, "simulated: {site: tetam}")).simulated.site == "tetam"
