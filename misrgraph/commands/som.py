"""``misrgraph som``: a path's SOM grid and blocks, and orbit <-> path <-> time."""

from __future__ import annotations

from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    console,
    handle_errors,
    print_json,
)

__all__ = ["app", "som_convert", "som_orbit"]

app = typer.Typer(help="MISR space: a path's SOM grid and blocks, and orbit <-> path <-> time.", no_args_is_help=True)


@app.command("convert")
@handle_errors
def som_convert(
    path: int = typer.Option(..., "--path", help="MISR/WRS-2 path, 1..233."),
    resolution: int = typer.Option(
        1100, "--resolution", help="Grid resolution (m): 275 or 1100 (also 2200, 4400, 8800, 17600)."
    ),
    block: Optional[int] = typer.Option(None, "--block", help="Block, 1..180 (with --line and --sample)."),
    line: Optional[float] = typer.Option(
        None, "--line", help="Fractional line in the block (-0.5 is the edge of the first pixel)."
    ),
    sample: Optional[float] = typer.Option(None, "--sample", help="Fractional sample in the block."),
    lat: Optional[float] = typer.Option(None, "--lat", help="Geodetic WGS84 latitude (deg), with --lon."),
    lon: Optional[float] = typer.Option(None, "--lon", help="Longitude (deg), with --lat."),
    som_x: Optional[float] = typer.Option(None, "--som-x", help="SOM x (m, along the path), with --som-y."),
    som_y: Optional[float] = typer.Option(None, "--som-y", help="SOM y (m, across the path), with --som-x."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Print one point as block/line/sample, lat/lon and SOM x/y, given any one of them."""
    from misrgraph.runs.som import run_som_convert

    res = run_som_convert(
        path, resolution, block=block, line=line, sample=sample, lat=lat, lon=lon, som_x=som_x, som_y=som_y
    )
    if as_json:
        print_json(res)
        return
    table = Table(title=f"path {res['path']}, {res['resolution_m']} m", show_header=False)
    for k in ("block", "line", "sample", "lat", "lon", "som_x", "som_y"):
        v = res[k]
        table.add_row(k, "off the grid" if v is None else (f"{v:.6f}" if isinstance(v, float) else str(v)))
    console.print(table)


@app.command("orbit")
@handle_errors
def som_orbit(
    orbit: Optional[int] = typer.Option(None, "--orbit", help="MISR orbit number (>= 995)."),
    time: Optional[str] = typer.Option(None, "--time", help="UTC time, ISO-8601 (e.g. 2005-08-08T10:30:00Z)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Orbit number, path and UTC start/end of an orbit, or of the orbit flying at a time."""
    from misrgraph.runs.som import run_som_orbit

    res = run_som_orbit(orbit=orbit, time=time)
    if as_json:
        print_json(res)
        return
    console.print(f"orbit {res['orbit']}  path {res['path']}  {res['start']} .. {res['end']}")
