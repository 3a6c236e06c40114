"""CAMPAIGN.yaml: what one published dataset is made of (the site, the runs, the stationary
fingerprint recordings, the grid sizes), checked once at load. docs/dataset.md has the schema.

Paths are relative to the campaign file or absolute. Every mapping takes only its own keys; a
misspelt one is one line naming the keys allowed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.errors import ConfigError
from annotator.fields import known_keys as _keys
from annotator.fields import mapping as _mapping
from annotator.fields import name as _name
from annotator.fields import number

CAMPAIGN_KEYS = (
    "name",
    "site",
    "runs",
    "fingerprints",
    "radiomap_cells",
    "occupancy_cells",
    "chunk_s",
    "description",
    "licence",
    "citation",
    "hardware",
)
SITE_KEYS = ("devices", "par", "plan", "markers")
RUN_KEYS = ("name", "experiment")
FINGERPRINT_KEYS = ("recordings",)
DEFAULT_LICENCE = "CC0-1.0"


@dataclass(frozen=True)
class Site:
    devices: Path  # .dev: the sensors and beacons
    par: Path  # .par: the plan's pixel geometry and the area's limits
    plan: Path  # the floor plan image
    markers: Path  # the surveyed marker map (.dat or YAML)

    @property
    def name(self) -> str:
        return self.devices.stem


@dataclass(frozen=True)
class RunSpec:
    name: str  # its folder name in the dataset
    experiment: Path


@dataclass(frozen=True)
class Campaign:
    path: Path
    name: str
    site: Site
    runs: tuple[RunSpec, ...]
    recordings: Path | None = None  # stationary fingerprints: a folder of <alias>_<x>_<y>_<z>.mbd
    radiomap_cells: tuple[float, ...] = (0.5, 1.0)
    occupancy_cells: tuple[float, ...] = (0.1, 0.2, 0.5, 1.0)
    chunk_s: float = 60.0  # seconds of video per detection task
    description: str = ""
    licence: str = DEFAULT_LICENCE
    citation: str = ""
    hardware: dict[str, str] = field(default_factory=dict)


def _file(base: Path, value: Any, where: str, *, folder: bool = False) -> Path:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{where}: expected a path, not {value!r:.40}")
    path = (base / value).resolve()
    if folder and not path.is_dir():
        raise ConfigError(f"{where}: no such folder {value}")
    if not folder and not path.is_file():
        raise ConfigError(f"{where}: no such file {value}")
    return path


def _cells(value: Any, where: str) -> tuple[float, ...]:
    if not isinstance(value, list) or not value:
        raise ConfigError(f"{where}: expected a list of cell sizes in metres, e.g. [0.5, 1.0]")
    out = [number(raw, where, 0.01, 10.0, "a cell size in 0.01..10 m") for raw in value]
    if len(set(out)) != len(out):
        raise ConfigError(f"{where}: a cell size is listed twice")
    return tuple(out)


def parse_campaign(obj: Any, path: Path) -> Campaign:
    source = str(path)
    base = path.parent
    d = _mapping(obj, source)
    _keys(d, CAMPAIGN_KEYS, source)
    for key in ("name", "site", "runs"):
        if key not in d:
            raise ConfigError(f"{source}: missing '{key}'")
    site_d = _mapping(d["site"], f"{source}: site")
    _keys(site_d, SITE_KEYS, source, "site")
    missing = [k for k in SITE_KEYS if k not in site_d]
    if missing:
        raise ConfigError(f"{source}: site: missing {', '.join(missing)}")
    site = Site(*(_file(base, site_d[k], f"{source}: site.{k}") for k in SITE_KEYS))
    if not isinstance(d["runs"], list) or not d["runs"]:
        raise ConfigError(f"{source}: runs: expected a list of {{name, experiment}}")
    runs = []
    for i, r in enumerate(d["runs"]):
        where = f"{source}: runs[{i}]"
        rd = _mapping(r, where)
        _keys(rd, RUN_KEYS, source, f"runs[{i}]")
        if "name" not in rd or "experiment" not in rd:
            raise ConfigError(f"{where}: needs name and experiment")
        runs.append(
            RunSpec(_name(rd["name"], f"{where}.name"), _file(base, rd["experiment"], where))
        )
    names = [r.name for r in runs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(f"{source}: runs: the name {twice[0]} is used twice")
    recordings = None
    if d.get("fingerprints") is not None:
        fd = _mapping(d["fingerprints"], f"{source}: fingerprints")
        _keys(fd, FINGERPRINT_KEYS, source, "fingerprints")
        if "recordings" in fd:
            recordings = _file(
                base, fd["recordings"], f"{source}: fingerprints.recordings", folder=True
            )
    hardware = {}
    if d.get("hardware") is not None:
        hardware = {
            str(k): str(v) for k, v in _mapping(d["hardware"], f"{source}: hardware").items()
        }
    text = {}
    for key in ("description", "licence", "citation"):
        v = d.get(key)
        if v is not None and not isinstance(v, str):
            raise ConfigError(f"{source}: {key} must be text")
        text[key] = v
    return Campaign(
        path=path,
        name=_name(d["name"], f"{source}: name"),
        site=site,
        runs=tuple(runs),
        recordings=recordings,
        radiomap_cells=(
            _cells(d["radiomap_cells"], f"{source}: radiomap_cells")
            if "radiomap_cells" in d
            else Campaign.radiomap_cells
        ),
        occupancy_cells=(
            _cells(d["occupancy_cells"], f"{source}: occupancy_cells")
            if "occupancy_cells" in d
            else Campaign.occupancy_cells
        ),
        chunk_s=(
            number(d["chunk_s"], f"{source}: chunk_s", 1.0, 86_400.0)
            if "chunk_s" in d
            else Campaign.chunk_s
        ),
        description=text["description"] or "",
        licence=text["licence"] or DEFAULT_LICENCE,
        citation=text["citation"] or "",
        hardware=hardware,
    )


def load_campaign(path: str | Path) -> Campaign:
    from bgt_core import safe_yaml

    path = Path(path).resolve()
    if not path.is_file():
        raise ConfigError(f"{path}: no such campaign file")
    try:
        obj = safe_yaml.load_file(path)
    except safe_yaml.YamlError as e:
        raise ConfigError(str(e)) from None
    return parse_campaign(obj, path)
