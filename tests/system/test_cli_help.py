"""Every command's --help prints every character its help texts were written with (issue 30):
rich markup must not eat ``[default: ...]`` or ``[[x, y], ...]``, and flags show no ``<bool>``
value as if they took one."""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from annotator.cli import app as annotator_app
from collector.cli import app as collector_app
from deploy.cli import app as deploy_app
from sensor_agent.cli import app as agent_app

APPS = {
    "annotator": annotator_app,
    "collector": collector_app,
    "sensor-agent": agent_app,
    "deploy": deploy_app,
}


# Typer carries its own copy of click: commands and groups are told apart by what they have.
Command = Any


def _is_group(cmd: Command) -> bool:
    return hasattr(cmd, "list_commands")


def _commands(group: Command, path: tuple[str, ...]) -> Iterator[tuple[tuple[str, ...], Command]]:
    yield path, group
    ctx = group.context_class(group)
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        assert cmd is not None
        if _is_group(cmd):
            yield from _commands(cmd, (*path, name))
        else:
            yield (*path, name), cmd


def every_command() -> list[tuple[str, tuple[str, ...], Command]]:
    out = []
    for cli, app in APPS.items():
        root = typer.main.get_command(app)
        assert _is_group(root)
        out += [(cli, path, cmd) for path, cmd in _commands(root, ())]
    return out


def _squash(text: str) -> str:
    """Text without white space or the help panels' borders (the help is wrapped to the width)."""
    return re.sub(r"[\s│╭╮╰╯─]+", "", text)


def _unescape(text: str) -> str:
    return text.replace("\\[", "[")


COMMANDS = every_command()


def test_the_clis_have_commands_with_bracketed_help() -> None:
    """The check below has something to check: known bracketed texts are among the helps."""
    helps = [
        _unescape(p.help or "") for _, _, c in COMMANDS for p in c.params if hasattr(p, "help")
    ]
    assert any("[[x, y], ...]" in h for h in helps)
    assert any("[default: evaluation.json next to TRAJECTORY]" in h for h in helps)
    assert len(COMMANDS) > 30


@pytest.mark.parametrize(
    ("cli", "path", "command"), COMMANDS, ids=[" ".join((c, *p)) for c, p, _ in COMMANDS]
)
def test_help_prints_every_character(cli: str, path: tuple[str, ...], command: Command) -> None:
    result = CliRunner().invoke(APPS[cli], [*path, "--help"], env={"COLUMNS": "100"})
    assert result.exit_code == 0, result.output
    shown = _squash(result.output)
    texts = [_unescape(command.help or "")] if not _is_group(command) else []
    texts += [_unescape(p.help) for p in command.params if getattr(p, "help", None)]
    for text in texts:
        for bracketed in re.findall(r"\[[^\]]*\]+", text):
            assert _squash(bracketed) in shown, (
                f"{bracketed!r} lost from {' '.join((cli, *path))} --help"
            )
    assert "<bool>" not in result.output
