"""The CLI reference is generated from the CLI, and every option's help says what it does without
the project's history."""

from __future__ import annotations

import re

import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.commands.reference import cli_markdown, command

runner = CliRunner()


def _commands(group, path):
    for name, cmd in group.commands.items():
        yield [*path, name], cmd
        if hasattr(cmd, "commands"):
            yield from _commands(cmd, [*path, name])


COMMANDS = list(_commands(command, []))
DATE = re.compile(r"\b(19|20)\d\d-\d\d-\d\d\b")


def test_every_command_and_option_is_in_the_reference():
    md = cli_markdown()
    assert len(COMMANDS) > 30
    for path, cmd in COMMANDS:
        head = f"`misrgraph {' '.join(path)}`"
        assert head in md, head
        section = md.split(head, 1)[1].split("\n#", 1)[0]
        for p in cmd.params:
            if p.name == "help":
                continue
            name = f"`{p.opts[0]}`" if p.param_type_name == "option" else f"`{p.name.upper()}`"
            assert name in section, (path, name)


@pytest.mark.parametrize("path", [["adjust"], ["simulate"], ["bench", "nees"], ["som", "convert"]])
def test_the_reference_lists_what_help_shows(path):
    """Independent of the generator: every option that ``--help`` prints is in its section."""
    res = runner.invoke(app, [*path, "--help"], terminal_width=200)
    assert res.exit_code == 0
    # the options' own rows (rich's table: a border, then the option), not options named in a text
    shown = set(re.findall(r"^\W\s+(--[a-z][a-z0-9-]+)", res.stdout, re.M)) - {"--help"}
    section = cli_markdown().split(f"`misrgraph {' '.join(path)}`", 1)[1].split("\n#", 1)[0]
    assert shown and all(f"`{o}`" in section for o in shown), shown


def test_help_texts_say_what_and_carry_no_history():
    for path, cmd in COMMANDS:
        assert (cmd.help or "").strip(), path
        assert not DATE.search(cmd.help or ""), path
        for p in cmd.params:
            if p.param_type_name != "option" or p.name == "help":
                continue
            text = p.help or ""
            assert text.strip(), (path, p.opts)
            assert not DATE.search(text), (path, p.opts, text)
            assert not re.search(r"\b(until|since) (19|20)\d\d|\bit was\b|\bused to\b", text), (path, p.opts, text)
