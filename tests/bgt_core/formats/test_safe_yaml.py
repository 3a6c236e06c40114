"""bgt_core.safe_yaml: aliases, depth, size and node count are refused before anything is
built, with one line naming the file; memory stays bounded (measured in a child process)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from bgt_core import safe_yaml
from bgt_core.safe_yaml import MAX_DEPTH, MAX_NODES, YamlError, dump, load_file, loads

# 342 bytes; yaml.safe_load would expand it to 9^9 = 387 million strings (tens of GiB).
BILLION_LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{n}: &{n} [{','.join(['*' + p] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)

# Peak resident memory allowed to a child that only imports yaml and loads one document; the
# child's own baseline is ~25 MiB, so this is generous on any machine.
PEAK_RSS_MIB = 300

CHILD = textwrap.dedent("""\
    import json, sys, time
    from bgt_core.safe_yaml import YamlError, load_file
    t = time.monotonic()
    try:
        doc = load_file(sys.argv[1])
        outcome = "loaded %d" % len(doc if isinstance(doc, (list, dict)) else [])
    except YamlError as e:
        outcome = "error: " + str(e)
    # VmHWM is this program's own peak: getrusage's ru_maxrss keeps the forking parent's peak
    # across exec, so a child of a pytest grown large would report the parent's size.
    with open("/proc/self/status") as f:
        hwm_kib = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
    print(json.dumps({"outcome": outcome, "seconds": time.monotonic() - t,
                      "peak_mib": hwm_kib / 1024}))
""")


def load_in_child(path: Path) -> dict:
    res = subprocess.run(
        [sys.executable, "-c", CHILD, str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return json.loads(res.stdout)


def test_billion_laughs_fails_fast_with_bounded_memory(tmp_path: Path):
    p = tmp_path / "calibration.yaml"
    p.write_text(BILLION_LAUGHS)
    r = load_in_child(p)
    assert r["outcome"] == f"error: {p}:1: anchors (&a) are not allowed; write the value out"
    assert r["peak_mib"] < PEAK_RSS_MIB
    assert r["seconds"] < 10  # it is refused at the first anchor; the bound is for a busy machine


def test_the_largest_accepted_document_stays_within_the_memory_bound(tmp_path: Path):
    """MAX_NODES - 1 tiny values: loaded, and the peak still under the bound."""
    p = tmp_path / "big.yaml"
    p.write_text("[" + ",".join(["1"] * (MAX_NODES - 1)) + "]\n")
    r = load_in_child(p)
    assert r["outcome"] == f"loaded {MAX_NODES - 1}"
    assert r["peak_mib"] < PEAK_RSS_MIB


def test_a_file_of_too_many_values_is_refused_before_it_is_built(tmp_path: Path):
    p = tmp_path / "many.yaml"
    p.write_text("[" + ",".join(["1"] * (3 * MAX_NODES)) + "]\n")  # 1.5 MB, well under MAX_BYTES
    r = load_in_child(p)
    assert r["outcome"] == f"error: {p}:1: more than {MAX_NODES} values in one document"
    assert r["peak_mib"] < PEAK_RSS_MIB


def test_aliases_and_anchors_are_refused_naming_file_and_line():
    with pytest.raises(YamlError, match=r"^f\.yaml:2: anchors \(&x\)"):
        loads("a: 1\nb: &x [1]\n", "f.yaml")
    with pytest.raises(YamlError, match=r"^f\.yaml:1: aliases \(\*x\)"):
        loads("b: *x\n", "f.yaml")  # an alias to nothing is still refused as an alias
    with pytest.raises(YamlError, match="anchors"):
        loads("base: &b {k: 1}\nother:\n  <<: *b\n", "f.yaml")  # merge keys need aliases


def test_nesting_is_limited():
    ok = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    assert loads(ok, "f.yaml") == eval(ok)  # noqa: S307 - a literal of brackets
    with pytest.raises(YamlError, match=rf"^f\.yaml:1: nested deeper than {MAX_DEPTH} levels"):
        loads("[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1), "f.yaml")
    deep_block = (
        "".join("  " * i + f"k{i}:\n" for i in range(MAX_DEPTH + 1))
        + "  " * (MAX_DEPTH + 1)
        + "v\n"
    )
    with pytest.raises(YamlError, match="nested deeper"):
        loads(deep_block, "f.yaml")
    # 100,000 levels: refused at level 65, no RecursionError
    with pytest.raises(YamlError, match="nested deeper"):
        loads("[" * 100_000, "f.yaml")


def test_size_is_limited_before_reading(tmp_path: Path):
    p = tmp_path / "huge.yaml"
    with p.open("wb") as f:
        f.truncate(safe_yaml.MAX_BYTES + 1)  # sparse: no need to write 8 MiB
    with pytest.raises(
        YamlError, match=rf"huge\.yaml: {safe_yaml.MAX_BYTES + 1} bytes; a YAML file may be at most"
    ):
        load_file(p)
    small = tmp_path / "small.yaml"
    small.write_text("a: [1, 2]\n")
    with pytest.raises(YamlError, match="at most 5"):
        load_file(small, max_bytes=5)


def test_not_utf8_names_line_and_byte_offset(tmp_path: Path):
    p = tmp_path / "c.yaml"
    p.write_bytes(b"a: 1\nb: caf\xe9\n")
    with pytest.raises(YamlError, match=r"c\.yaml:2: not UTF-8 text \(byte 0xe9 at offset 11\)"):
        load_file(p)


def test_missing_file_and_bad_values_are_one_line(tmp_path: Path):
    with pytest.raises(YamlError, match=r"nope\.yaml: cannot read \(No such file"):
        load_file(tmp_path / "nope.yaml")
    for text, problem in [
        ("x: " + "9" * 5000, "a value cannot be read"),
        ("x: 2024-13-45", "a value cannot be read"),
        ("x: !!python/object/apply:os.system [echo]", "not valid YAML"),
        ("a: [1, 2", "not valid YAML"),
        ("---\na: 1\n---\nb: 2\n", "not valid YAML"),
    ]:
        with pytest.raises(YamlError) as info:
            loads(text, "v.yaml")
        msg = str(info.value)
        assert msg.startswith("v.yaml")
        assert problem in msg
        assert "\n" not in msg


def test_plain_documents_load_as_with_safe_load():
    import yaml

    text = "a: 1\nb: [1.5, .nan, ~, yes]\nc: {d: 2001-12-14}\n\ufeffe: 'x'\n".replace("\ufeff", "")
    assert repr(loads(text)) == repr(yaml.safe_load(text))
    assert loads("") is None
    assert loads("\ufeffa: 1") == {"a": 1}


def test_dump_writes_shared_objects_out_so_they_load_again():
    shared = [1, 2]
    data = {"x": shared, "y": shared, "z": {"w": shared}}
    text = dump(data, sort_keys=False)
    assert "&" not in text
    assert "*" not in text
    assert loads(text) == data


def test_a_loader_must_be_the_safe_one():
    import yaml

    with pytest.raises(TypeError):
        loads("a: 1", loader=yaml.UnsafeLoader)


def _yaml_readers():
    from annotator.errors import ConfigError as AnnotatorConfigError
    from annotator.io.experiment import load_calibration, load_experiment, load_rig
    from annotator.io.waypoints import load_waypoints
    from bgt_core.formats.markers import MarkerMapError, read_marker_map
    from collector.config import ConfigError as CollectorConfigError
    from collector.config import load_config as collector_config
    from deploy.inventory import InventoryError, load_inventory
    from sensor_agent.config import ConfigError as AgentConfigError
    from sensor_agent.config import load_config as agent_config

    return [
        ("agent.yaml", agent_config, AgentConfigError),
        ("collector.yaml", collector_config, CollectorConfigError),
        ("inventory.yml", load_inventory, InventoryError),
        ("experiment.yaml", load_experiment, AnnotatorConfigError),
        ("rig.yaml", load_rig, AnnotatorConfigError),
        ("calibration.yaml", load_calibration, AnnotatorConfigError),
        ("path.yaml", load_waypoints, AnnotatorConfigError),
        ("markers.yaml", read_marker_map, MarkerMapError),
    ]


@pytest.mark.parametrize(
    "index",
    range(8),
    ids=["agent", "collector", "inventory", "experiment", "rig", "calibration", "path", "markers"],
)
def test_every_yaml_reader_of_the_suite_refuses_aliases(tmp_path: Path, index: int):
    name, reader, error = _yaml_readers()[index]
    p = tmp_path / name
    p.write_text(BILLION_LAUGHS)
    with pytest.raises(error) as info:
        reader(p)
    assert "anchors (&a) are not allowed" in str(info.value)
    assert name in str(info.value)


def test_run_yaml_with_aliases_is_skipped_by_the_collector_and_refused_by_the_annotator(
    tmp_path: Path,
):
    from annotator.errors import ConfigError
    from annotator.io.rssi import load_rssi
    from collector.store import list_runs

    run = tmp_path / "data" / "r1"
    (run / "rssi").mkdir(parents=True)
    (run / "rssi" / "aabbccddeeff.mbd").write_text("1700000000.5,aabbccddeeff,112233445566,-60\n")
    (run / "run.yaml").write_text(BILLION_LAUGHS)
    assert list_runs(tmp_path / "data") == []  # skipped with a warning, not a crash
    with pytest.raises(ConfigError, match=r"run\.yaml:1: anchors"):
        load_rssi(run)
