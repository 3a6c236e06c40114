"""`annotator dataset build`: a campaign to a published dataset folder.

Runs are annotated as Dask tasks (`annotator.dataset.runs`), on a ``LocalCluster`` of one
single-threaded worker process per core by default or on an existing scheduler; everything after
that (fingerprints, radio maps, occupancy, the layout, the datasheet, the manifest) is computed
here in a fixed order. The dataset is written into ``OUT.partial`` and moved into place at the
end, so an interrupted build leaves the previous dataset whole.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.dataset.campaign import Campaign
from annotator.dataset.runs import RunDone, annotate_runs
from annotator.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class BuildResult:
    out: Path
    runs: list[RunDone]
    annotated: int  # runs annotated this build (the others came from the cache)
    seconds: float
    tables: dict[str, int] = field(default_factory=dict)
    occupancy_agreement: dict[float, float] = field(default_factory=dict)
    files: int = 0


def default_cache(campaign: Campaign) -> Path:
    return campaign.path.parent / ".bgt-cache" / campaign.name


def _client(workers: int | None, scheduler: str | None) -> tuple[Any, Any]:
    try:
        from distributed import Client, LocalCluster
    except ModuleNotFoundError:
        raise ConfigError(
            "annotator dataset build needs Dask (the dataset extra): pip install '.[dataset]'"
        ) from None
    if scheduler is not None:
        return Client(scheduler, timeout="20s"), None
    n = workers or os.cpu_count() or 1
    cluster = LocalCluster(
        n_workers=n,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",  # never the fixed 8787 a real cluster may hold
        silence_logs=logging.ERROR,
    )
    return Client(cluster), cluster


def published_occupancy(campaign: Campaign, cell: float) -> Path | None:
    """The site's own grid at ``cell``, when one lies beside its .par or in ../occ/."""
    name = f"{campaign.site.name}_{float(cell)!r}.occ"
    for folder in (campaign.site.par.parent, campaign.site.par.parent.parent / "occ"):
        if (folder / name).is_file():
            return folder / name
    return None


def build_dataset(
    campaign: Campaign,
    out: Path,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    cache: Path | None = None,
    on_progress: Callable[[dict[str, Any]], None] | None = None,
    on_run: Callable[[RunDone], None] | None = None,
    on_stage: Callable[[str], None] | None = None,
) -> BuildResult:
    import json

    import cv2

    from annotator.core.occupancy import agreement
    from annotator.dataset.datasheet import datasheet
    from annotator.dataset.layout import (
        copy,
        site_files,
        write_manifest,
        write_occupancy,
        write_parquet_tables,
        write_tracks,
    )
    from bgt_core.formats.devices import read_dev, read_par
    from bgt_core.formats.occ import read_occ

    def stage(text: str) -> None:
        if on_stage is not None:
            on_stage(text)

    t0 = time.perf_counter()
    out = out.resolve()
    if out == campaign.path.parent or out in campaign.path.parents:
        raise ConfigError(f"--out {out}: would replace the campaign's own folder")
    cache = cache or default_cache(campaign)
    devices = read_dev(campaign.site.devices)
    params = read_par(campaign.site.par)
    plan = cv2.imread(str(campaign.site.plan), cv2.IMREAD_COLOR)
    if plan is None:
        raise ConfigError(f"{campaign.site.plan}: not a readable image")

    client, cluster = _client(workers, scheduler)
    try:
        runs = annotate_runs(
            campaign.runs, cache, client, on_progress, on_run, chunk_s=campaign.chunk_s
        )
    finally:
        client.close()
        if cluster is not None:
            cluster.close()

    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    site = campaign.site.name
    stage("site files and tracks")
    site_files(partial, campaign)
    reports = {run.name: write_tracks(partial, run, devices) for run in runs}
    refined = runs[0].results / "refined" / "marker_positions.dat"
    copy(
        refined if refined.is_file() else campaign.site.markers,
        partial / "vid" / "marker_positions.dat",
    )

    stage("occupancy grids")
    grids = write_occupancy(partial, plan, params, site, campaign.occupancy_cells)
    agree = {}
    for cell, occ in grids.items():
        theirs = published_occupancy(campaign, cell)
        if theirs is not None:
            agree[cell] = agreement(occ, read_occ(theirs))[0]

    hst = None
    if campaign.recordings is not None:
        stage("fingerprints and radio maps")
        hst = _fingerprints_and_maps(campaign, partial, devices, params, grids)

    stage("tables, datasheet, manifest")
    tables = write_parquet_tables(partial, runs, hst)
    (partial / "README.md").write_text(
        datasheet(campaign, runs, reports, tables, agree), encoding="utf-8"
    )
    (partial / "campaign.json").write_text(
        json.dumps(
            {
                "name": campaign.name,
                "runs": {r.name: {"inputs_sha256": r.digest} for r in runs},
                "radiomap_cells": list(campaign.radiomap_cells),
                "occupancy_cells": list(campaign.occupancy_cells),
            },
            indent=1,
            sort_keys=True,
        ),
        encoding="utf-8",
    )
    manifest = write_manifest(partial)
    files = len(manifest.read_text("utf-8").splitlines())
    old = out.with_name(out.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if out.exists():
        out.rename(old)
    partial.rename(out)
    shutil.rmtree(old, ignore_errors=True)
    return BuildResult(
        out,
        runs,
        sum(not r.cached for r in runs),
        time.perf_counter() - t0,
        tables,
        agree,
        files,
    )


def _fingerprints_and_maps(
    campaign: Campaign, out: Path, devices: Any, params: Any, grids: dict[float, Any]
) -> Any:
    from annotator.core.fingerprints import rssi_edges
    from annotator.dataset.layout import copy
    from annotator.io.radio_data import (
        Site,
        make_grid,
        radio_maps,
        stationary_fingerprints,
        write_radio_maps,
    )
    from bgt_core.formats.hst import write_hst

    assert campaign.recordings is not None
    recordings = sorted(campaign.recordings.glob("*.mbd"))
    for f in recordings:
        copy(f, out / "fpt" / f.name)
    result = stationary_fingerprints(recordings, rssi_edges(), devices)
    hst_path = out / "hst" / "set_1" / f"{campaign.site.name}_multi_rssi.hst"
    hst_path.parent.mkdir(parents=True, exist_ok=True)
    write_hst(result.histograms, hst_path)
    site = Site(campaign.site.name, params, campaign.site.plan)
    for cell in campaign.radiomap_cells:
        grid = make_grid(result.histograms, cell, grids.get(cell), site)
        maps = radio_maps(result.histograms, grid)
        write_radio_maps(
            maps, result.histograms, grid, out / "grd", campaign.site.name, plots=False
        )
    return result.histograms
