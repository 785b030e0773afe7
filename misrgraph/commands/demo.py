"""``misrgraph demo``: the whole workflow on simulated data."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import check_output, console, handle_errors, progress_bar

__all__ = ["demo"]


@handle_errors
def demo(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Directory for the demo's products."),
    small: bool = typer.Option(False, "--small", help="Reduced sizes (about a minute)."),
    save: Optional[Path] = typer.Option(
        None, "--save", help="Also write the stages' results, with their provenance, as JSON to this file."
    ),
) -> None:
    """The whole workflow on simulated data: calibrate, adjust, match, update, record; prints a summary."""
    from misrgraph.bench.provenance import finish
    from misrgraph.runs.demo import STAGES, run_demo

    check_output(out / "demo.json", "--out")
    check_output(save, "--save")
    with progress_bar("demo", counts=True) as update:
        done = {"n": 0}

        def step(name: str) -> None:
            update(name, done["n"], len(STAGES))
            done["n"] += 1

        records = run_demo(out, progress=step, small=small)
        update("done", len(STAGES), len(STAGES))
    finish({"small": small, "stages": records}, save)
    table = Table(title=f"misrgraph demo (products in {out})")
    for col in ("stage", "result against the simulator's truth", "time (s)"):
        table.add_column(col)
    for r in records:
        table.add_row(r["stage"], r["summary"], f"{r['seconds']:.1f}")
    console.print(table)
    console.print(f"total {sum(r['seconds'] for r in records):.0f} s")
