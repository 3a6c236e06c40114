"""`annotator markers print`: a PDF of printable ArUco markers, one per page, at true size."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from annotator.commands._common import console, one_line_errors
from annotator.errors import ConfigError

markers_app = typer.Typer(help="Marker sheets for the room.", no_args_is_help=True)


@markers_app.command("print")
def print_markers(
    out: Annotated[Path, typer.Option("--out", help="PDF file to write.")],
    ids: Annotated[
        str, typer.Option(help="Marker ids: ranges and lists, e.g. 0-29 or 0,4,8-11.")
    ] = "0-29",
    length: Annotated[float, typer.Option(help="Side of the black square, metres.")] = 0.298,
    dictionary: Annotated[str, typer.Option(help="ArUco dictionary.")] = "DICT_6X6_50",
    paper: Annotated[
        str, typer.Option(help="Paper size: auto (smallest that fits), A4, A3, A2, A1 or A0.")
    ] = "auto",
) -> None:
    """Write one marker per page, the black square exactly LENGTH wide when printed at 100 %,
    with its id and a 10 cm scale bar to check the printer's scaling."""
    with one_line_errors():
        from matplotlib.backends.backend_pdf import PdfPages

        from annotator.plots.marker_sheets import choose_paper, marker_page, parse_ids

        if not 0 < length <= 2:
            raise ConfigError(f"--length {length}: expected metres, e.g. 0.298")
        id_list = parse_ids(ids)
        sheet = choose_paper(length, paper)
        pages = [
            marker_page(i, length, dictionary, sheet)[0] for i in id_list
        ]  # validates every id first
        out.parent.mkdir(parents=True, exist_ok=True)
        with PdfPages(
            out, metadata={"Title": f"ArUco {dictionary} markers, {length * 1000:.1f} mm"}
        ) as pdf:
            for fig in pages:
                pdf.savefig(fig)
        console.print(
            f"wrote {len(id_list)} {sheet} pages to {out}",
            highlight=False,
            soft_wrap=True,
            markup=False,
        )


def register(app: typer.Typer) -> None:
    app.add_typer(markers_app, name="markers")
