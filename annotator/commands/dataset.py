"""`annotator dataset build`: a campaign's runs annotated (in parallel on Dask) and written, with
fingerprints, radio maps, occupancy grids and a datasheet, in the published layout."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from annotator.commands._common import console, one_line_errors, stage_columns
from annotator.errors import ConfigError

dataset_app = typer.Typer(
    help="Build a publishable dataset from a campaign (docs/dataset.md).", no_args_is_help=True
)


@dataset_app.command("build")
def build(
    campaign: Annotated[Path, typer.Argument(help="CAMPAIGN.yaml (docs/dataset.md).")],
    out: Annotated[Path, typer.Option("--out", help="The dataset folder (replaced when done).")],
    workers: Annotated[
        int | None,
        typer.Option(
            "--workers",
            help="Worker processes of the local Dask cluster (default: one per core).",
            min=1,
            max=256,
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler",
            help="An existing Dask scheduler, e.g. tcp://host:8786 (its workers need the suite "
            "and the campaign's files at the same paths).",
        ),
    ] = None,
    cache: Annotated[
        Path | None,
        typer.Option(
            "--cache",
            help="Where each run's results are kept by the hash of its inputs (default "
            ".bgt-cache/<name> beside the campaign file).",
        ),
    ] = None,
) -> None:
    """Annotate every run of the campaign (runs whose inputs are unchanged since the last build
    come from the cache), make the fingerprint histograms, radio maps and occupancy grids, and
    write the published layout with parquet tables, a datasheet (README.md) and SHA256SUMS."""
    with one_line_errors():
        from importlib.util import find_spec

        from rich.progress import Progress

        from annotator.dataset.build import build_dataset
        from annotator.dataset.campaign import load_campaign
        from annotator.dataset.runs import RunDone

        if find_spec("distributed") is None:
            raise ConfigError(
                "annotator dataset build needs Dask (the dataset extra): pip install '.[dataset]'"
            )
        if workers is not None and scheduler is not None:
            raise ConfigError("--workers and --scheduler: give one (workers belong to a cluster)")
        spec = load_campaign(campaign)
        with Progress(*stage_columns(28), console=console) as bar:
            overall = bar.add_task("runs", total=len(spec.runs))
            per_run: dict[str, Any] = {}

            def run_bar(name: str) -> Any:
                if name not in per_run:
                    per_run[name] = bar.add_task(name, total=1)
                return per_run[name]

            def on_progress(event: dict[str, Any]) -> None:
                name = str(event.get("run", "?"))
                stage = str(event.get("stage", ""))
                bar.update(
                    run_bar(name),
                    description=f"{name} {stage}"[:28],
                    completed=int(event.get("done", 0)),
                    total=max(int(event.get("total", 1)), 1),
                )

            def on_run(done: RunDone) -> None:
                task = run_bar(done.name)
                bar.update(task, description=f"{done.name} {'cached' if done.cached else 'done'}")
                bar.update(task, completed=bar.tasks[task].total)
                bar.advance(overall)

            stage_task = None

            def on_stage(text: str) -> None:
                nonlocal stage_task
                if stage_task is None:
                    stage_task = bar.add_task(text[:28], total=None)
                bar.update(stage_task, description=text[:28])

            result = build_dataset(
                spec,
                out,
                workers=workers,
                scheduler=scheduler,
                cache=cache,
                on_progress=on_progress,
                on_run=on_run,
                on_stage=on_stage,
            )
        agree = ", ".join(f"{c:g} m {100 * a:.1f} %" for c, a in result.occupancy_agreement.items())
        console.print(
            f"{len(result.runs)} runs ({result.annotated} annotated, "
            f"{len(result.runs) - result.annotated} from the cache), {result.files} files in "
            f"{result.out}, {result.seconds:.0f} s"
            + (f"; occupancy agrees with the site's grids: {agree}" if agree else ""),
            highlight=False,
            soft_wrap=True,
            markup=False,
        )


def register(app: typer.Typer) -> None:
    app.add_typer(dataset_app, name="dataset")
