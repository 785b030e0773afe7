"""``misrgraph demo``: the whole workflow on simulated data."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from misrgraph.commands.common import (
    console,
    err_console,
    handle_errors,
)

__all__ = ["demo"]

@handle_errors
def demo(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Directory for the demo's products."),
    small: bool = typer.Option(False, "--small", help="Reduced sizes (about a minute)."),
) -> None:
    """The whole workflow on simulated data: calibrate, adjust, update, record; prints a summary."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.runs.demo import STAGES, run_demo

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=err_console) as bar:
        task = bar.add_task("demo", total=len(STAGES))
        done = {"n": 0}

        def step(name: str) -> None:
            bar.update(task, description=name, completed=done["n"])
            done["n"] += 1

        records = run_demo(out, progress=step, small=small)
        bar.update(task, completed=len(STAGES), description="done")
    table = Table(title=f"misrgraph demo (products in {out})")
    for col in ("stage", "result against the simulator's truth", "time (s)"):
        table.add_column(col)
    for r in records:
        table.add_row(r["stage"], r["summary"], f"{r['seconds']:.1f}")
    console.print(table)
    console.print(f"total {sum(r['seconds'] for r in records):.0f} s")

