"""``misrgraph import``: real GCP lists, DEM rasters and MISR AGPs and L1B2 files into misrgraph's files."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from misrgraph.commands.common import (
    check_output,
    console,
    handle_errors,
    print_json,
)

__all__ = ["app", "import_gcps", "import_dem", "import_agp", "import_l1b2"]

app = typer.Typer(
    help="Real inputs into misrgraph's files: GCP lists (CSV, GeoJSON), DEM rasters (any GDAL raster), "
    "MISR AGPs and L1B2 files.",
    no_args_is_help=True,
)


@app.command("gcps")
@handle_errors
def import_gcps(
    source: Path = typer.Argument(..., help="GCP list: .csv (header row) or .geojson (Point features)."),
    out: Path = typer.Option(..., "--out", help="GCP database to write (HDF5), e.g. SCENARIO_DIR/gcp.h5."),
    sigma_m: Optional[float] = typer.Option(
        None, "--sigma-m", help="1-sigma (m, every ENU axis) where the list has no sigma column."
    ),
    geoid: Optional[Path] = typer.Option(
        None, "--geoid", help="Geoid grid raster (e.g. us_nga_egm96_15.tif) for heights above the geoid."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Import a GCP list with its sigmas (columns: lat, lon, height [m ellipsoidal] or height_msl,
    sigma_m or sigma_h_m + sigma_v_m or sigma_e_m + sigma_n_m + sigma_u_m, optional id, region)."""
    from misrgraph.runs.imports import run_import_gcps

    res = run_import_gcps(source, out, sigma_m, geoid)
    if as_json:
        print_json(res)
        return
    console.print(
        f"{res['gcps']} GCPs -> {res['out']} (sigma {res['sigma_m']['min']:.3g}..{res['sigma_m']['max']:.3g} m)"
    )


@app.command("dem")
@handle_errors
def import_dem(
    sources: list[Path] = typer.Argument(..., help="DEM rasters (GeoTIFF, DTED, ... any CRS), heights in metres."),
    out: Path = typer.Option(..., "--out", help="DEM file to write (HDF5), e.g. SCENARIO_DIR/dem.h5."),
    posting_arcsec: float = typer.Option(3.0, "--posting-arcsec", help="Posting of the geographic grid (arc seconds)."),
    tile_postings: int = typer.Option(1201, "--tile-postings", help="Postings per tile side (>= 32)."),
    quality: int = typer.Option(1, "--quality", help="Accuracy class: 1 (30 m), 2 (60 m), 3 (120 m) 1-sigma."),
    geoid: Optional[Path] = typer.Option(
        None, "--geoid", help="Geoid grid raster; heights above it become ellipsoidal."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Import DEM rasters as square geographic tiles (bilinear onto the posting grid)."""
    from misrgraph.runs.imports import run_import_dem

    res = run_import_dem(sources, out, posting_arcsec, tile_postings, quality, geoid)
    if as_json:
        print_json(res)
        return
    console.print(
        f"{res['tiles']} tiles of {res['tile_postings']} postings -> {res['out']} "
        f"(heights {res['height_m']['min']:.0f}..{res['height_m']['max']:.0f} m, {res['height_reference']})"
    )


@app.command("agp")
@handle_errors
def import_agp(
    source: Path = typer.Argument(
        ..., help="MISR AGP file (HDF-EOS2, grid Standard), e.g. MISR_AM1_AGP_P037_F01_24.hdf."
    ),
    out: Path = typer.Option(..., "--out", help="DEM file to write (HDF5), e.g. SCENARIO_DIR/agp_dem.h5."),
    blocks: Optional[str] = typer.Option(
        None, "--blocks", help="Blocks A-B to import. Default: the file's Start_block..End block."
    ),
    posting_arcsec: float = typer.Option(
        30.0, "--posting-arcsec", help="Posting of the geographic grid (arc seconds)."
    ),
    tile_postings: int = typer.Option(64, "--tile-postings", help="Postings per tile side (>= 32)."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Import a MISR AGP's heights (AveSceneElev, m above the WGS84 ellipsoid) as a DEM, each
    posting's 1-sigma from StdDevSceneElev."""
    from misrgraph.runs.imports import run_import_agp

    res = run_import_agp(source, out, blocks, posting_arcsec, tile_postings)
    if as_json:
        print_json(res)
        return
    console.print(
        f"path {res['path']} blocks {res['blocks'][0]}-{res['blocks'][1]}: {res['tiles']} tiles of "
        f"{res['tile_postings']} postings -> {res['out']} (heights {res['height_m']['min']:.0f}.."
        f"{res['height_m']['max']:.0f} m, sigma {res['sigma_m']['min']:.3g}..{res['sigma_m']['max']:.3g} m)"
    )


@app.command("l1b2")
@handle_errors
def import_l1b2(
    sources: list[Path] = typer.Argument(..., help="MISR L1B2 files (HDF-EOS2), one per camera, of one path."),
    out: Path = typer.Option(
        ..., "--out", help="Reference Orbit Imagery file to write (HDF5), e.g. runs/mine/l1b2_roi.h5."
    ),
    band: str = typer.Option("red", "--band", help="blue, green, red or nir (275 m in the files: red, or An's bands)."),
    blocks: Optional[str] = typer.Option(None, "--blocks", help="Blocks A-B. Default: every block the files share."),
    compare: Optional[Path] = typer.Option(
        None,
        "--compare",
        help="misrgraph's ROI file of the path (products --roi): measure the imported imagery's misregistration "
        "against it per camera and block (275 m pixels, by least-squares matching).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Import MISR L1B2 radiances (Radiance/RDQI unpacked: fill, RDQI 2-3 and terrain-obscured
    pixels empty) as a Reference Orbit Imagery file, to compare with misrgraph's own ROI."""
    from misrgraph.runs.imports import run_import_l1b2

    check_output(out, "--out")
    res = run_import_l1b2(sources, out, band, blocks, compare)
    if as_json:
        print_json(res)
        return
    console.print(
        f"path {res['path']} {res['band']} blocks {res['blocks'][0]}-{res['blocks'][1]}, cameras "
        f"{', '.join(res['cameras'])} -> {res['out']}"
    )
    for cam, per in res.get("comparison", {}).items():
        for b, v in per.items():
            what = (
                "fewer than 3 matches"
                if v is None
                else f"misregistration {v['excess_px']:.2f} px beyond matching noise, mean offset "
                f"{v['mean_px']:.2f} px ({v['matches']} matches)"
            )
            console.print(f"  {cam} block {b}: {what}")
