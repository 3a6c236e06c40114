"""`annotator` commands run in the test's process (typer's CliRunner), for end-to-end tests."""

from __future__ import annotations

from typer.testing import CliRunner

from annotator.cli import app

_runner = CliRunner()


def invoke(*args: str) -> str:
    """Run ``annotator ARGS``; its output, after asserting it succeeded (the output is the
    failure's message)."""
    res = _runner.invoke(app, list(args))
    assert res.exit_code == 0, res.output
    return res.output
