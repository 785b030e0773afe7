"""``misrgraph info``: validate a misrgraph file and print what it holds."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from misrgraph.commands.common import (
    console,
    handle_errors,
    print_json,
)

__all__ = ["info"]


@handle_errors
def info(
    file: Path = typer.Argument(..., help="A misrgraph HDF5 file."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Validate a misrgraph HDF5 file and print what it holds."""
    from misrgraph.io.info import run_info

    res = run_info(file)
    if as_json:
        print_json(res)
        return
    table = Table(title=str(file), show_header=False)
    for k, v in res.items():
        table.add_row(k, json.dumps(v) if isinstance(v, (dict, list)) else str(v))
    console.print(table)
