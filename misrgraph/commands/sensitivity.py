"""``misrgraph sensitivity``: the forward model's ground displacement for a small attitude or ephemeris error."""

from __future__ import annotations

from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    console,
    handle_errors,
    print_json,
)

__all__ = ["sensitivity"]

SENS_HELP = """Ground displacement of each camera's pixel for a small attitude (and ephemeris) error.

Signs: along_m > 0 is in the flight direction, cross_m > 0 to the right of it (orbital +y).
+pitch tips the view forward, +roll tips it to the left, +yaw turns it counter-clockwise seen
from above. Ephemeris errors: +M m along (+x), cross (+y, right) and radial (up), attitude fixed
relative to the orbital frame. Nominal point: WGS84 ellipsoid, mid-pass of a Terra-like
descending pass (path 37) near the equator."""


@handle_errors
def sensitivity(
    arcsec: float = typer.Option(10.0, "--arcsec", help="Attitude perturbation (arcsec)."),
    pixel: float = typer.Option(0.0, "--pixel", help="Sample number, 0..1503."),
    band: str = typer.Option("red", "--band", help="blue, green, red or nir."),
    ephemeris_m: Optional[float] = typer.Option(
        None, "--ephemeris-m", help="Also perturb the position by this many metres along, cross and radial."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    from misrgraph.evaluate.sensitivity import run_sensitivity

    res = run_sensitivity(arcsec=arcsec, pixel=pixel, band=band, ephemeris_m=ephemeris_m)
    if as_json:
        print_json(res)
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
