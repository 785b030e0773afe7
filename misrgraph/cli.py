"""The ``misrgraph`` command line: thin wrappers over the ``run_*`` functions.

Every command turns a :class:`~misrgraph.errors.MisrGraphError` into a one-line message on
stderr and exit status 2 (no traceback). ``--json`` prints machine-readable output on stdout.
"""

from __future__ import annotations

import functools
import json
import logging
import sys
from pathlib import Path
from typing import Any, Callable, Optional

import typer
from rich.console import Console
from rich.table import Table

from misrgraph.errors import MisrGraphError

__all__ = ["app", "main"]

app = typer.Typer(add_completion=False, no_args_is_help=True, help="In-flight geometric calibration of MISR as a GTSAM factor graph.")
console = Console()
err_console = Console(stderr=True)


def _fail(message: str, code: int = 2) -> None:
    err_console.print(f"misrgraph: error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


def handle_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator: MisrGraphError -> one-line message, exit 2."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except MisrGraphError as exc:
            _fail(str(exc))

    return wrapper


def _print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, sort_keys=False) + "\n")


@app.callback()
def _root(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details.")) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


SENS_HELP = """Ground displacement of each camera's pixel for a small attitude (and ephemeris) error.

Signs: along_m > 0 is in the flight direction, cross_m > 0 to the right of it (orbital +y).
+pitch tips the view forward, +roll tips it to the left, +yaw turns it counter-clockwise seen
from above. Ephemeris errors: +M m along (+x), cross (+y, right) and radial (up), attitude fixed
relative to the orbital frame. Nominal point: WGS84 ellipsoid, mid-pass of a Terra-like
descending pass (path 37) near the equator."""


@app.command(help=SENS_HELP)
@handle_errors
def sensitivity(
    arcsec: float = typer.Option(10.0, "--arcsec", help="Attitude perturbation (arcsec)."),
    pixel: float = typer.Option(0.0, "--pixel", help="Sample number, 0..1503."),
    band: str = typer.Option("red", "--band", help="blue, green, red or nir."),
    ephemeris_m: Optional[float] = typer.Option(None, "--ephemeris-m", help="Also perturb the position by this many metres along, cross and radial."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    from misrgraph.sensitivity import run_sensitivity

    res = run_sensitivity(arcsec=arcsec, pixel=pixel, band=band, ephemeris_m=ephemeris_m)
    if as_json:
        _print_json(res)
        return
    table = Table(title=f"Ground displacement (m) for +{arcsec:g} arcsec, pixel {pixel:g}, {band} band")
    table.add_column("camera")
    for ang in ("yaw", "pitch", "roll"):
        table.add_column(f"{ang}\nalong", justify="right")
        table.add_column(f"{ang}\ncross", justify="right")
    for cam, v in res["cameras"].items():
        table.add_row(cam, *[f"{v[a][d]:.1f}" for a in ("yaw", "pitch", "roll") for d in ("along_m", "cross_m")])
    console.print(table)
    if ephemeris_m is not None:
        eph = Table(title=f"Ground displacement (m) for +{ephemeris_m:g} m of position error")
        eph.add_column("camera")
        for ax in ("along", "cross", "radial"):
            eph.add_column(f"{ax}\nalong", justify="right")
            eph.add_column(f"{ax}\ncross", justify="right")
        for cam, v in res["cameras"].items():
            e = v["ephemeris"]
            eph.add_row(cam, *[f"{e[a][d]:.1f}" for a in ("along", "cross", "radial") for d in ("along_m", "cross_m")])
        console.print(eph)


@app.command()
@handle_errors
def demo(out: Path = typer.Option(Path("demo-output"), "--out", help="Directory for the demo's products.")) -> None:
    """Run every stage that exists on the built-in simulated scenario and print a summary table."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from misrgraph.demo import STAGES, run_demo

    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn(), console=err_console) as bar:
        task = bar.add_task("demo", total=len(STAGES))

        def step(name: str) -> None:
            bar.update(task, description=name, advance=1)

        records = run_demo(out, progress=step)
    table = Table(title="misrgraph demo")
    for col in ("stage", "status", "result", "time (s)"):
        table.add_column(col)
    for r in records:
        table.add_row(r["stage"], r["status"], r["summary"], f"{r['seconds']:.1f}" if r["status"] == "done" else "")
    console.print(table)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
