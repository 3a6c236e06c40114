"""`annotator occupancy`: a floor plan -> an occupancy grid (.occ), free floor 0, occupied 1."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError


def occupancy(
    plan: Annotated[Path, typer.Argument(help="The floor plan image (.png).")],
    par: Annotated[
        Path, typer.Option("--par", help="The site's .par: the plan's pixel geometry and area.")
    ],
    out: Annotated[Path, typer.Option("--out", help="The .occ file to write.")],
    cell: Annotated[float, typer.Option(help="Cell size, metres.", min=0.01, max=10.0)] = 0.5,
    compare: Annotated[
        Path | None,
        typer.Option(
            "--compare",
            help="A published .occ of the same site and cell size: print the share of cells "
            "that agree.",
        ),
    ] = None,
) -> None:
    """Make an occupancy grid from a floor plan: a cell is occupied (1) when 30 % of the plan
    under it is not bare floor (near-white pixels) or a wall (dark line) crosses it, and
    outside the plan; free floor is 0, as in the published tetam grids. The grid covers the
    .par's area in the published layout (lower-left corners from its origin)."""
    with one_line_errors():
        import cv2

        from annotator.core.occupancy import agreement, occupancy_from_plan
        from bgt_core.formats.devices import read_par
        from bgt_core.formats.occ import read_occ, write_occ

        params = read_par(par)
        if not plan.is_file():
            raise ConfigError(f"{plan}: no such file")
        image = cv2.imread(str(plan), cv2.IMREAD_COLOR)
        if image is None:
            raise ConfigError(f"{plan}: not a readable image")
        theirs = read_occ(compare) if compare is not None else None
        if theirs is not None and abs(theirs.cell - cell) > 1e-9:
            raise ConfigError(f"--compare {compare}: its cells are {theirs.cell:g} m, not {cell:g}")
        grid = occupancy_from_plan(image, params, cell)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_occ(grid, out)
        occupied = sum(grid.cells.values())
        text = (
            f"{len(grid.cells)} cells of {cell:g} m, {occupied} occupied "
            f"({100 * occupied / len(grid.cells):.0f} %); wrote {out}"
        )
        if theirs is not None and compare is not None:
            share, n = agreement(grid, theirs)
            text += f"; {100 * share:.1f} % of {n} cells agree with {compare.name}"
        console.print(text, highlight=False, soft_wrap=True, markup=False)


def register(app: typer.Typer) -> None:
    app.command("occupancy", short_help="An occupancy grid (.occ) from a floor plan.")(occupancy)
