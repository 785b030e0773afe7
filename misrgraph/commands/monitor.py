"""``misrgraph monitor``: a series of calibrations tested for a change of the camera model."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import console, handle_errors, print_json

__all__ = ["monitor"]


@handle_errors
def monitor(
    table: Path = typer.Argument(
        ..., help="CSV with a header row: utc (time of each calibration), calibration (its 'calibrate --json' file)."
    ),
    train_until: Optional[str] = typer.Option(
        None,
        "--train-until",
        help="UTC time: the process levels are learned from the calibrations before it. Default: the first half.",
    ),
    alpha: float = typer.Option(
        0.05, "--alpha", help="False-alarm probability of the whole table (shared by every camera and parameter)."
    ),
    seasonal: bool = typer.Option(True, "--seasonal/--no-seasonal", help="Model an annual term."),
    view: str = typer.Option(
        "conditional",
        "--view",
        help="conditional: each camera given the other cameras at each calibration (their shared "
        "error taken out, from the summaries' correlations); marginal: each camera's own series.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Test every camera's delta, beta and epsilon over a series of calibrations for a step or a
    drift the learned process does not explain: the first alarm of each says a new camera model is
    needed, with the camera, the parameter, the date and the evidence."""
    from misrgraph.runs.monitor import run_monitor

    res = run_monitor(table, train_until, alpha, seasonal, view)
    if as_json:
        print_json(res)
        return
    console.print(
        f"{res['calibrations']} calibrations {res['from']} .. {res['to']}; levels learned on the first "
        f"{res['trained_on']}; false-alarm probability {res['alpha']:g}; {res['view']} view"
    )
    if not res["alarms"]:
        console.print("no change found: the camera model holds")
        return
    t = Table(title="new camera model needed")
    for col in ("camera", "parameter", "utc", "test", "direction", "evidence", "level before (arcsec)"):
        t.add_column(col, justify="right")
    for a in res["alarms"]:
        t.add_row(
            a["camera"],
            a["parameter"],
            a["utc"],
            a["kind"],
            "up" if a["direction"] > 0 else "down",
            f"{a['statistic']:.1f} > {a['threshold']:.1f}",
            f"{a['level_before_arcsec']:.2f} +- {a['level_sigma_before_arcsec']:.2f}",
        )
    console.print(t)
