from __future__ import annotations

from bgt_core.cli_help import flow


def test_flow_joins_the_lines_of_each_paragraph_and_keeps_list_items() -> None:
    text = """First line
        goes on here.

        Steps:
        1. one thing
           that wraps;
        2. another.
        - a bullet
    """
    assert flow(text) == (
        "First line goes on here.\n\nSteps:\n1. one thing that wraps;\n2. another.\n- a bullet"
    )


def test_every_cli_command_help_is_flowed() -> None:
    from annotator.cli import app as annotator_app
    from collector.cli import app as collector_app
    from sensor_agent.cli import app as agent_app

    for app in (annotator_app, collector_app, agent_app):
        for info in app.registered_commands:
            assert info.help, info.callback
            for para in info.help.split("\n\n"):
                lines = para.splitlines()
                assert all(line[:1] in "-*123456789 " for line in lines[1:]), (info.help, para)
