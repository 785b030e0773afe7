"""``misrgraph cgm``: camera-model versions by orbit range (add, list, show, diff)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from misrgraph.commands.common import console, handle_errors, print_json

__all__ = ["app", "cgm_add", "cgm_list", "cgm_show", "cgm_diff"]

app = typer.Typer(
    help="Camera-model versions by orbit range: a store that adjust, update and products read through "
    "--camera-model, picking the version valid for each pass's orbit.",
    no_args_is_help=True,
)

_STORE = typer.Argument(..., help="CGM store directory (cgm.json and versions/).")


def _fmt(x: Optional[float], spec: str = ".3f") -> str:
    return "-" if x is None else format(x, spec)


def _print_versions(versions: list[dict[str, Any]]) -> None:
    t = Table(title="camera-model versions")
    for col in ("version", "orbits", "created (UTC)", "reason", "source"):
        t.add_column(col)
    for v in versions:
        last = "" if v["last_orbit"] is None else str(v["last_orbit"])
        t.add_row(v["id"], f"{v['first_orbit']}-{last}", v["created_utc"], v["reason"], Path(v["source"]).name)
    console.print(t)


@app.command("add")
@handle_errors
def cgm_add(
    store: Path = typer.Argument(..., help="CGM store directory; created when missing."),
    camera_model: Path = typer.Argument(..., help="Camera-model file to store ('calibrate --out')."),
    from_orbit: int = typer.Option(..., "--from-orbit", help="First orbit the version is valid for."),
    to_orbit: Optional[int] = typer.Option(
        None,
        "--to-orbit",
        help="Last orbit it is valid for (inclusive). Default: open-ended, which closes an open-ended "
        "earlier version at the orbit before --from-orbit.",
    ),
    reason: str = typer.Option("", "--reason", help="What triggered the version (e.g. a monitor alarm)."),
    as_json: bool = typer.Option(False, "--json", help="Print the store's versions as JSON."),
) -> None:
    """Store a camera model as a new version valid for a range of orbits."""
    from misrgraph.runs.cgm import run_cgm_add

    res = run_cgm_add(store, camera_model, from_orbit, to_orbit, reason)
    if as_json:
        print_json(res)
        return
    console.print(f"added {res['added']['id']} to {store}", highlight=False)
    _print_versions(res["versions"])


@app.command("list")
@handle_errors
def cgm_list(
    store: Path = _STORE,
    as_json: bool = typer.Option(False, "--json", help="Print the versions as JSON."),
) -> None:
    """List a store's versions with their orbit ranges and what triggered them."""
    from misrgraph.runs.cgm import run_cgm_list

    res = run_cgm_list(store)
    if as_json:
        print_json(res)
        return
    _print_versions(res["versions"])


@app.command("show")
@handle_errors
def cgm_show(
    store: Path = _STORE,
    version: Optional[str] = typer.Argument(None, help="Version id (v001, ...). Or give --orbit."),
    orbit: Optional[int] = typer.Option(None, "--orbit", help="Show the version valid for this orbit."),
    as_json: bool = typer.Option(False, "--json", help="Print the version as JSON."),
) -> None:
    """One version's pointing angles per camera (arcsec) with their 1-sigma, and its pointing
    1-sigma in pixels (from the calibration's covariance, when the file has one)."""
    from misrgraph.runs.cgm import run_cgm_show

    res = run_cgm_show(store, version, orbit)
    if as_json:
        print_json(res)
        return
    last = "" if res["last_orbit"] is None else res["last_orbit"]
    console.print(f"{res['id']}: orbits {res['first_orbit']}-{last}; {res['reason'] or 'no reason given'}")
    t = Table(title="pointing angles (arcsec, +- 1 sigma)")
    for col in ("camera", "delta", "beta", "epsilon", "pointing sigma (px)"):
        t.add_column(col, justify="right")
    for cam, v in res["cameras"].items():
        cells = [f"{v[p]['arcsec']:.2f} +- {_fmt(v[p]['sigma_arcsec'], '.2f')}" for p in ("delta", "beta", "epsilon")]
        t.add_row(cam, *cells, _fmt(v["sigma_px"]))
    console.print(t)


@app.command("diff")
@handle_errors
def cgm_diff(
    store: Path = _STORE,
    a: str = typer.Argument(..., help="The earlier version id."),
    b: str = typer.Argument(..., help="The later version id."),
    as_json: bool = typer.Option(False, "--json", help="Print the differences as JSON."),
) -> None:
    """What changed between two versions, per camera: the angles (arcsec) and the pointing (px),
    each with its 1-sigma and z from the two calibrations' covariances."""
    from misrgraph.runs.cgm import run_cgm_diff

    res = run_cgm_diff(store, a, b)
    if as_json:
        print_json(res)
        return
    t = Table(title=f"{a} -> {b}: change (arcsec; pointing px), z = change / sigma")
    for col in ("camera", "delta", "beta", "epsilon", "pointing (px)", "z"):
        t.add_column(col, justify="right")
    for cam, v in res["cameras"].items():
        cells = [f"{v[p]['arcsec']:+.2f} (z {_fmt(v[p]['z'], '.1f')})" for p in ("delta", "beta", "epsilon")]
        t.add_row(cam, *cells, f"{v['pointing_px']:.3f}", _fmt(v["z"], ".1f"))
    console.print(t)
    w = res["largest"]
    console.print(f"largest change: {w['camera']}, {w['pointing_px']:.3f} px (z {_fmt(w['z'], '.1f')})")
