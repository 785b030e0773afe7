"""The command-line reference, generated from the CLI itself.

:func:`cli_markdown` walks the click command behind the ``misrgraph`` application (typer builds
it) and writes one section per command: its help text, its usage line and a table of its
arguments and options with their type, default and help. The documentation's build hook
(``docs/hooks.py``) puts it into ``docs/reference/cli.md``; ``misrgraph --help`` and this page
therefore never disagree.
"""

from __future__ import annotations

import enum
import types
import typing
from pathlib import Path
from typing import Any

import typer

from misrgraph.commands.cli import app

__all__ = ["command", "cli_markdown"]

#: ``misrgraph`` as a click group: every command and option as ``--help`` shows it
command = typer.main.get_command(app)


def _cell(text: Any) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ").strip()


def _default(param: Any) -> str:
    if getattr(param, "required", False):
        return "required"
    value = param.default
    if callable(value) or value is None or value == () or value == []:
        return ""
    if isinstance(value, enum.Enum):
        value = value.value
    if _is_flag(param):
        return "on" if value else "off"
    return f"`{value}`"


def _name(param: Any) -> str:
    if param.param_type_name == "argument":
        return f"`{param.name.upper()}`"
    names = [*param.opts, *getattr(param, "secondary_opts", [])]
    return ", ".join(f"`{n}`" for n in names)


_TYPE_NAMES = {Path: "path", float: "number", int: "integer", str: "text", bool: "flag"}


def _annotation(param: Any) -> Any:
    """The parameter's Python type (typer's own descriptor), without ``Optional``."""
    ann = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    args = [a for a in typing.get_args(ann) if a is not type(None)]
    if ann is not None and typing.get_origin(ann) in (typing.Union, types.UnionType) and len(args) == 1:
        return args[0]
    return ann


def _is_flag(param: Any) -> bool:
    return _annotation(param) is bool or bool(getattr(param, "is_flag", False))


def _type(param: Any) -> str:
    ann = _annotation(param)
    if ann is None:  # a click without typer's descriptors
        return "flag" if _is_flag(param) else (getattr(getattr(param, "type", None), "name", "") or "").lower()
    if typing.get_origin(ann) is list:
        inner = typing.get_args(ann)
        return (_TYPE_NAMES.get(inner[0], getattr(inner[0], "__name__", "value")) if inner else "value") + " ..."
    return _TYPE_NAMES.get(ann, getattr(ann, "__name__", str(ann)))


def _section(cmd: Any, path: list[str], level: int, out: list[str]) -> None:
    import inspect

    out.append(f"{'#' * level} `{' '.join(path)}`\n")
    help_text = inspect.cleandoc(cmd.help or "")
    if help_text:
        out.append(help_text + "\n")
    params = [p for p in cmd.params if p.name not in ("help",) and not getattr(p, "hidden", False)]
    sub = getattr(cmd, "commands", None)
    usage = " ".join(path) + (" [OPTIONS]" if any(p.param_type_name == "option" for p in params) else "")
    usage += "".join(
        f" {p.name.upper()}" + ("..." if p.nargs == -1 else "") for p in params if p.param_type_name == "argument"
    )
    if sub:
        usage += " COMMAND [ARGS]..."
    out.append(f"```text\n{usage}\n```\n")
    if params:
        out.append("| argument or option | type | default | what it does |")
        out.append("|---|---|---|---|")
        for p in params:
            out.append(f"| {_name(p)} | {_cell(_type(p))} | {_default(p)} | {_cell(getattr(p, 'help', '') or '')} |")
        out.append("")
    for name in sub or {}:
        _section(sub[name], [*path, name], min(level + 1, 4), out)


def cli_markdown(level: int = 2) -> str:
    """Markdown of every command of ``misrgraph``: help, usage and a table of its parameters."""
    out: list[str] = []
    for name, cmd in command.commands.items():
        _section(cmd, ["misrgraph", name], level, out)
    return "\n".join(out) + "\n"
