"""`annotator dataset build` end to end on a real Dask LocalCluster: a campaign of two short
simulated runs and the bundled stationary fingerprints becomes the published layout; a second
build with nothing changed annotates nothing; 1 and 2 workers give identical files."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pandas as pd
import pytest

from annotator_cli import invoke
from bgt_core.formats.grd import read_grd
from bgt_core.formats.hst import read_hst
from bgt_core.formats.mbd import iter_rows
from bgt_core.formats.occ import read_occ
from bgt_core.sites import site_dir

pytest.importorskip("distributed")
pytestmark = pytest.mark.slow

DATA = Path(__file__).resolve().parents[2] / "data" / "dataset"
SITE = site_dir("tetam")


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("campaign")
    for name, seed, path in (("walk_a", "0", "loop"), ("walk_b", "1", "rectangle")):
        invoke(
            "simulate", "--out", str(base / "runs" / name), "--duration", "6", "--seed", seed,
            "--path", path, "--rssi-rate", "4", "--jobs", "2",
        )  # fmt: skip
    # the published site files, as a user keeps them beside the campaign
    for sub, name in (("cnf", "tetam.dev"), ("cnf", "tetam.par"), ("map", "tetam.png")):
        (base / sub).mkdir(exist_ok=True)
        src = SITE / name if name != "tetam.dev" else DATA / "cnf" / name
        (base / sub / name).write_bytes(src.read_bytes())
    (base / "occ").mkdir()
    for cell in ("0.5", "1.0"):
        (base / "occ" / f"tetam_{cell}.occ").write_bytes(
            (DATA / "occ" / f"tetam_{cell}.occ").read_bytes()
        )
    path = base / "campaign.yaml"
    path.write_text(
        "name: tetam-test\n"
        "description: Two short simulated walks through the tetam room.\n"
        "site: {devices: cnf/tetam.dev, par: cnf/tetam.par, plan: map/tetam.png, "
        f"markers: {SITE / 'marker_positions.dat'}}}\n"
        "runs:\n"
        "  - {name: walk_a, experiment: runs/walk_a/experiment.yaml}\n"
        "  - {name: walk_b, experiment: runs/walk_b/experiment.yaml}\n"
        f"fingerprints: {{recordings: {DATA / 'fpt'}}}\n"
        "radiomap_cells: [1.0]\n"
        "occupancy_cells: [0.5, 1.0]\n"
        "hardware: {cameras: 'two simulated 960x540 30 fps', sensors: '12 simulated'}\n"
    )
    return path


def digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def built(campaign: Path) -> tuple[Path, Path, str]:
    """The campaign built once with one worker: (dataset, cache, what the command printed)."""
    out = campaign.parent / "dataset"
    cache = campaign.parent / "cache"
    text = invoke("dataset", "build", str(campaign), "--out", str(out), "--workers", "1",
                  "--cache", str(cache))  # fmt: skip
    return out, cache, text


def test_build_writes_the_published_layout_and_caches_runs(
    campaign: Path, built: tuple[Path, Path, str]
) -> None:
    out, cache, text = built
    tmp_path = campaign.parent
    assert "2 runs (2 annotated, 0 from the cache)" in text
    # the layout
    for rel in ("cnf/tetam.dev", "cnf/tetam.par", "map/tetam.png", "vid/marker_positions.dat",
                "trk/walk_a_all_sensors.mbd", "trk/walk_b_all_sensors.mbd", "trk/walk_a.png",
                "runs/walk_a/report.json", "hst/set_1/tetam_multi_rssi.hst",
                "occ/tetam_0.5.occ", "occ/tetam_1.0.occ", "parquet/readings.parquet",
                "parquet/trajectories.parquet", "parquet/fingerprints.parquet", "README.md",
                "SHA256SUMS"):  # fmt: skip
        assert (out / rel).is_file(), rel
    # per-sensor track files named by alias at 0.00_0.00_0.00, rows as the published ones
    sensors = sorted((out / "trk" / "walk_a").glob("*_0.00_0.00_0.00.mbd"))
    assert len(sensors) >= 12
    assert any(p.name == "sensor10_0.00_0.00_0.00.mbd" for p in sensors)
    rows = list(iter_rows(sensors[0]))
    assert rows
    published = next(iter_rows(DATA / "trk" / "straight_01" / sensors[0].name))
    assert len(rows[0].rest) == len(published.rest)  # x, y, z and the rotation matrix
    # fingerprints, radio maps and occupancy parse with the project's readers
    hst = read_hst(out / "hst" / "set_1" / "tetam_multi_rssi.hst")
    assert len(hst.fingerprints) == 1  # the bundled recordings hold one position
    grds = sorted((out / "grd").glob("tetam_*_1.0.grd"))
    assert len(grds) == len(hst.devices.dongles)
    assert read_grd(grds[0]).cell == 1.0
    occ = read_occ(out / "occ" / "tetam_0.5.occ")
    assert set(occ.cells.values()) == {0, 1}
    # the parquet tables hold every labelled reading with its run and sigma
    readings = pd.read_parquet(out / "parquet" / "readings.parquet")
    assert set(readings["run"]) == {"walk_a", "walk_b"}
    assert {"x", "y", "z", "pos_sigma"} <= set(readings.columns)
    reports = {
        r: json.loads((out / "runs" / r / "report.json").read_text()) for r in ("walk_a", "walk_b")
    }
    assert sum(r["counts"]["labelled"] for r in reports.values()) == len(readings)
    assert reports["walk_a"]["experiment"] == "walk_a"  # no path of the building machine
    assert str(tmp_path) not in (out / "README.md").read_text()
    # the datasheet: the runs with their figures, the occupancy agreement, licence
    sheet = (out / "README.md").read_text()
    assert "| [walk_a](runs/walk_a/report.json)" in sheet
    assert "cameras: two simulated" in sheet
    assert "% of cells agree with the site's published grid" in sheet
    assert "CC0-1.0" in sheet
    # the manifest covers every file
    listed = dict(line.split("  ")[::-1] for line in (out / "SHA256SUMS").read_text().splitlines())
    assert listed == {k: v for k, v in digests(out).items() if k != "SHA256SUMS"}

    # nothing changed: no annotation, the same files
    before = digests(out)
    text = invoke("dataset", "build", str(campaign), "--out", str(out), "--workers", "1",
                  "--cache", str(cache))  # fmt: skip
    assert "2 runs (0 annotated, 2 from the cache)" in text
    assert digests(out) == before


def test_one_and_two_workers_give_identical_files(
    campaign: Path, built: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """One worker of the build's own LocalCluster, and an existing two-worker cluster reached by
    --scheduler (as a lab's would be): the same files."""
    from distributed import LocalCluster

    two = tmp_path / "dataset-2"
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    ) as cluster:
        invoke("dataset", "build", str(campaign), "--out", str(two),
               "--scheduler", cluster.scheduler_address, "--cache", str(tmp_path / "cache-2"))  # fmt: skip
    assert digests(built[0]) == digests(two)


def test_a_worker_lost_mid_run_is_retried_and_corrupts_nothing(
    campaign: Path, built: tuple[Path, Path, str], tmp_path: Path
) -> None:
    """The finish task's worker process dies once (after leaving half an output folder);
    Dask's nanny restarts it, the task runs again, and the run's results are whole and equal
    to the undisturbed build's."""
    from distributed import Client, LocalCluster

    from annotator.dataset.campaign import load_campaign
    from annotator.dataset.runs import annotate_runs
    from dask_faults import finish_dying_once

    spec = load_campaign(campaign)
    runs = spec.runs[:1]
    with (
        LocalCluster(
            n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0"
        ) as cluster,
        Client(cluster) as client,
    ):
        hit = annotate_runs(runs, tmp_path / "hit", client, finish=finish_dying_once)
    calm = annotate_runs(runs, built[1], None)  # the undisturbed build's, from its cache
    assert calm[0].cached
    assert (hit[0].results.parent / f".died-{runs[0].name}").is_file()  # it did die once
    assert not hit[0].cached
    assert (hit[0].results / "report.json").is_file()
    assert digests(hit[0].results / "annotated") == digests(calm[0].results / "annotated")
    # a second build finds the run whole in the cache, and clears the dead attempt's leftovers
    again = annotate_runs(runs, tmp_path / "hit", None)  # no task: no client
    assert again[0].cached
    assert not list(hit[0].results.parent.glob("*.part-*"))
