"""`annotator` command line: a thin typer app; each command lives in annotator/commands/."""

from __future__ import annotations

import importlib
import logging

import typer

from bgt_core.cli_help import flow_command_help

app = typer.Typer(
    name="annotator",
    help="Offline annotation: camera-tracked ground truth for BLE RSSI captures.",
    no_args_is_help=True,
    pretty_exceptions_show_locals=False,
)

# Each module defines `register(app)`; the order here is the order in --help.
COMMAND_MODULES = (
    "run",
    "track",
    "evaluate",
    "import-log",
    "simulate",
    "calibrate",
    "markers",
    "fingerprints",
    "radiomap",
    "occupancy",
    "dataset",
    "score",
    "localize",
    "tum",
    "demo",
)

for _name in COMMAND_MODULES:
    try:
        _mod = importlib.import_module(f"annotator.commands.{_name.replace('-', '_')}")
    except ModuleNotFoundError as _e:  # a command still being written; the others work
        if _e.name != f"annotator.commands.{_name.replace('-', '_')}":
            raise
        continue
    _mod.register(app)
flow_command_help(app)


@app.callback()
def _root(
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages."),
) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


def main() -> None:
    app()


if __name__ == "__main__":
    main()
