"""The annotator reads a collector run in its per-agent layout (rssi/<agent>/<sensor>.mbd) and
in the older flat one (rssi/<sensor>.mbd)."""

from __future__ import annotations

from pathlib import Path

import pytest

from annotator.errors import ConfigError
from annotator.io.rssi import load_rssi


def _run(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / "rssi" / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    (tmp_path / "run.yaml").write_text("id: r\nreadings: 3\n")
    return tmp_path


def test_per_agent_run_dir_loads_every_agents_files(tmp_path: Path) -> None:
    mac = "b827eb4521b4"
    run = _run(
        tmp_path,
        {
            f"pi-01/{mac}.mbd": f"1700000000.2,{mac},e78f135624ce,-50\n",
            f"pi-02/{mac}.mbd": f"1700000000.1,{mac},e78f135624ce,-60\n",
            "pi-02/b827eb4521b5.mbd": "1700000000.3,b827eb4521b5,e78f135624ce,-70\n",
        },
    )
    t = load_rssi(run)
    assert t.rssi.tolist() == [-60, -50, -70]  # time order across agents
    assert len(t.files) == 3
    assert t.run_info is not None
    assert (t.run_info.run_id, t.run_info.readings, t.run_info.stopped) == ("r", 3, False)


def test_flat_run_dir_still_loads(tmp_path: Path) -> None:
    run = _run(tmp_path, {"b827eb4521b4.mbd": "1700000000.2,b827eb4521b4,e78f135624ce,-50\n"})
    assert load_rssi(run).rssi.tolist() == [-50]


def test_a_garbled_run_yaml_is_one_line_naming_the_key(tmp_path: Path) -> None:
    mac = "b827eb4521b4"
    run = _run(tmp_path, {f"pi-01/{mac}.mbd": f"1700000000.2,{mac},e78f135624ce,-50\n"})
    (run / "run.yaml").write_text("id: r\nreadings: many\n")
    with pytest.raises(ConfigError) as err:
        load_rssi(run)
    msg = str(err.value)
    assert "run.yaml: readings must be a whole number" in msg
    assert "\n" not in msg
