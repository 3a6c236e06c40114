"""A misspelt key at any level of any config the suite reads is one error line that names the
file, the key and the allowed keys, with the close match when there is one (issue 30).

Before, `refien:` at the top of experiment.yaml was silently ignored and `sycn:` was reported as
"sync.mode is manual but sync.video_start is missing"."""

from __future__ import annotations

from pathlib import Path

import pytest

from annotator.errors import ConfigError as AnnotatorConfigError
from annotator.io.experiment import load_experiment
from collector.config import parse_config as parse_collector
from collector.errors import ConfigError as CollectorConfigError
from sensor_agent.config import parse_config as parse_agent
from sensor_agent.errors import ConfigError as AgentConfigError
from tests.annotator.io.test_input_fuzz import make_experiment

T0 = 1_700_000_000.0
JIG = (
    "  jig: {from: 0.0, to: 1.0, position: [1, 2, 1.5], "
    "R_world_bundle: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], sigam_m: 0.001}\n"
)

# (what is replaced in the good experiment.yaml / rig.yaml, by what; the key named; the hint)
EXPERIMENT_TYPOS = [
    ("experiment.yaml", "sync:\n", "sycn:\n", "'sycn'", "did you mean 'sync'?"),
    (
        "experiment.yaml",
        "rig: rig.yaml\n",
        "rig: rig.yaml\nrefien: {mode: all}\n",
        "'refien'",
        "did you mean 'refine'?",
    ),
    ("experiment.yaml", "rssi: rssi\n", "rssi: rssi\ncolour: red\n", "'colour'", None),
    (
        "experiment.yaml",
        "length: 0.298",
        "length: 0.298, lenght: 0.3",
        "'markers.lenght'",
        "did you mean 'length'?",
    ),
    (
        "experiment.yaml",
        "  mode: manual\n",
        "  mdoe: manual\n  mode: manual\n",
        "'sync.mdoe'",
        "did you mean 'mode'?",
    ),
    (
        "experiment.yaml",
        "rig: rig.yaml\n",
        "rig: rig.yaml\nrefine: {mode: all, survey_sigma: 1}\n",
        "'refine.survey_sigma'",
        "did you mean 'survey_sigma_m'?",
    ),
    (
        "experiment.yaml",
        "rig: rig.yaml\n",
        "rig: rig.yaml\nrefine:\n" + JIG,
        "'refine.jig.sigam_m'",
        "did you mean 'sigma_m'?",
    ),
    (
        "rig.yaml",
        "cameras:\n",
        "camera_list: []\ncameras:\n",
        "'camera_list'",
        "did you mean 'cameras'?",
    ),
    (
        "rig.yaml",
        "    calibration: front.yaml\n",
        "    calibration: front.yaml\n    t_bundle_cam: [0, 0, 0]\n",
        "'cameras.front.t_bundle_cam'",
        "did you mean 't_bundle_camera'?",
    ),
    (
        "rig.yaml",
        "cameras:\n",
        "antennas: {reciever: [0, 0, 0.1]}\ncameras:\n",
        "'antennas.reciever'",
        "did you mean 'receiver'?",
    ),
    (
        "experiment.yaml",
        "rig: rig.yaml\n",
        "rig: rig.yaml\nreciever: aabbccddeeff\n",
        "'reciever'",
        "did you mean 'receiver'?",
    ),
]


@pytest.mark.parametrize(("file", "old", "new", "key", "hint"), EXPERIMENT_TYPOS)
def test_experiment_typo_at_every_level(
    tmp_path: Path, file: str, old: str, new: str, key: str, hint: str | None
) -> None:
    exp = make_experiment(tmp_path / "exp")
    load_experiment(exp)  # the unmodified experiment loads
    target = exp.parent / file
    text = target.read_text()
    assert old in text
    target.write_text(text.replace(old, new, 1))
    with pytest.raises(AnnotatorConfigError) as err:
        load_experiment(exp)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(str(target) + ": unknown key " + key), message
    assert "allowed: " in message
    if hint is None:
        assert "did you mean" not in message
    else:
        assert hint in message


AGENT = {"agent_id": "pi-1", "backend": "simulated", "simulated": {"site": "tetam"}}

AGENT_TYPOS = [
    ({"agent_idd": "pi-1"}, "'agent_idd'", "did you mean 'agent_id'?"),
    ({"simulated": {"site": "tetam", "rate": 5}}, "'simulated.rate'", "did you mean 'rate_hz'?"),
    ({"simulated": {"site": "tetam", "colour": 5}}, "'simulated.colour'", None),
    ({"simulated": {"site": "tetam", "seeds": 5}}, "'simulated.seeds'", "did you mean 'seed'?"),
    ({"spool": {"dir": "spool", "max_mbb": 5}}, "'spool.max_mbb'", "did you mean 'max_mb'?"),
    ({"watchdog": {"restart": 1}}, "'watchdog.restart'", None),
    (
        {"simulated": {"site": "tetam", "path": {"waypoints": [[0, 0, 1], [1, 0, 1]], "sped": 1}}},
        "'simulated.path.sped'",
        "did you mean 'speed_mps'?",
    ),
    (
        {"simulated": {"site": "tetam", "events": [{"start_s": 1, "duration": 2}]}},
        "'simulated.events[0].duration'",
        "did you mean 'duration_s'?",
    ),
]


@pytest.mark.parametrize(("change", "key", "hint"), AGENT_TYPOS)
def test_agent_typo_at_every_level(
    tmp_path: Path, change: dict[str, object], key: str, hint: str | None
) -> None:
    parse_agent(AGENT, "agent.yaml", tmp_path)
    with pytest.raises(AgentConfigError) as err:
        parse_agent({**AGENT, **change}, "agent.yaml", tmp_path)
    message = str(err.value)
    assert message.startswith("agent.yaml: "), message
    assert f"unknown key {key}" in message
    if hint is None:
        assert "did you mean" not in message
    else:
        assert hint in message


COLLECTOR_TYPOS = [
    ({"data_dri": "data"}, "'data_dir'", "'data_dri'"),
    ({"limits": {"streams_totl": 5}}, "'streams_total'", "'limits.streams_totl'"),
    ({"tls": {"root_ca": "ca", "cert": "c", "kye": "k"}}, "'key'", "'tls.kye'"),
]


@pytest.mark.parametrize(("raw", "close", "key"), COLLECTOR_TYPOS)
def test_collector_typo_at_every_level(
    tmp_path: Path, raw: dict[str, object], close: str, key: str
) -> None:
    parse_collector({"data_dir": "data"}, base=tmp_path)
    with pytest.raises(CollectorConfigError) as err:
        parse_collector(raw, base=tmp_path)
    message = str(err.value)
    assert message.startswith(f"collector.yaml: unknown key {key} (did you mean {close}?"), message


def test_markers_length_sigma(tmp_path: Path) -> None:
    """markers.length_sigma: the printed size's relative 1-sigma (default 1 %), in 0..0.2."""
    exp = make_experiment(tmp_path / "exp")
    assert load_experiment(exp).markers.length_sigma == 0.01
    text = exp.read_text()
    exp.write_text(text.replace("length: 0.298", "length: 0.298, length_sigma: 0.002"))
    assert load_experiment(exp).markers.length_sigma == 0.002
    exp.write_text(text.replace("length: 0.298", "length: 0.298, length_sigma: 0.5"))
    with pytest.raises(AnnotatorConfigError, match="markers.length_sigma: must be a relative"):
        load_experiment(exp)
