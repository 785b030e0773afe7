"""``misrgraph products``: Projection Parameters and Reference Orbit Imagery."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    CONFIG_HELP,
    NOISE_HELP,
    adjust_config,
    check_output,
    console,
    handle_errors,
    print_coregistration,
    print_json,
    progress_bar,
)
from misrgraph.errors import InputError

__all__ = ["products"]


@handle_errors
def products(
    scenario_dir: Path = typer.Argument(
        ...,
        help="A scenario directory (misrgraph simulate), or an update state (misrgraph update: PP of its passes "
        "from the current estimate).",
    ),
    out: Path = typer.Option(..., "--out", help="Output directory for PP_<pass id>.h5 and products.json."),
    blocks: Optional[str] = typer.Option(
        None, "--blocks", help="SOM blocks A-B (inclusive, 1..180). Default: 10 around the pass's features."
    ),
    pass_file: Optional[Path] = typer.Option(None, "--pass", help="The pass. Default: the scenario's first."),
    camera_model: Optional[Path] = typer.Option(
        None,
        "--camera-model",
        help="Camera model: a file, a built-in name, or a CGM store (misrgraph cgm), whose version valid for "
        "each pass's orbit is used. Default: the scenario's camera_model.h5.",
    ),
    band: str = typer.Option("red", "--band", help="blue, green, red or nir."),
    roi: bool = typer.Option(
        False,
        "--roi",
        help="Also build the Reference Orbit Imagery from every pass with whole-swath strips (at least 4): "
        "ROI_P<path>.h5 on the 275 m SOM grid, the clearest pass per block, a per-pixel source map, "
        "co-registration measured on it.",
    ),
    geotiff: bool = typer.Option(
        False, "--geotiff", help="With --roi: one Cloud-Optimised GeoTIFF per camera in the path's misrsom CRS."
    ),
    quicklooks: bool = typer.Option(False, "--quicklooks", help="With --roi: one quick-look PNG per camera."),
    som_dem: Optional[Path] = typer.Option(
        None, "--som-dem", help="With --roi: heights on the path's 275 m SOM grid. Default: the scenario's dem_som.h5."
    ),
    coreg_points: int = typer.Option(
        64, "--coreg-points", help="With --roi: co-registration matches per image pair and block (0: not measured)."
    ),
    observations: str = typer.Option(
        "simulated",
        "--observations",
        help="simulated (the pass's own) or matched (those 'misrgraph match' measured) for the scenario's "
        "adjustment; a state adjusts its own set.",
    ),
    config: Optional[Path] = typer.Option(
        None, "--config", help=CONFIG_HELP.format(cls="AdjustConfig") + " For a scenario directory, not a state."
    ),
    noise_model: Optional[Path] = typer.Option(
        None, "--noise-model", help=NOISE_HELP + " For a scenario directory, not a state."
    ),
    file_format: str = typer.Option(
        "h5",
        "--format",
        help="h5 (misrgraph's HDF5 files) or misr (those, and MISR's HDF-EOS2 files in OUT/misr/: one PP file per "
        "camera and, with --roi, one L1B2-style ROI file per camera).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Projection Parameters of an adjusted pass on its path's 1.1 km SOM grid, with their 1 sigma.

    The pass is adjusted on the way; from an update state, every pass of the state from its current
    estimate. Scored against the simulator's truth when the pass has it. With --roi, the Reference
    Orbit Imagery of the path from all passes with imagery.
    """
    from misrgraph.runs.products import RoiOptions, run_products

    if not roi and (geotiff or quicklooks or som_dem):
        raise InputError("--geotiff/--quicklooks/--som-dem", "given without --roi", "--roi as well")
    cfg = adjust_config({}, config, noise_model)
    check_output(out / "products.json", "--out")
    opts = (
        RoiOptions(
            som_dem=str(som_dem) if som_dem else None,
            geotiff=geotiff,
            quicklooks=quicklooks,
            coregistration_points=coreg_points,
        )
        if roi
        else None
    )
    with progress_bar("products", disable=as_json) as progress:
        res = run_products(
            scenario_dir,
            out,
            blocks=blocks,
            pass_file=pass_file,
            camera_model=camera_model,
            band=band,
            cfg=cfg,
            progress=progress,
            roi=roi,
            roi_options=opts,
            observations=observations,
            file_format=file_format,
        )
    if as_json:
        print_json(res)
        return
    for one in res.get("passes", [res]):
        console.print(
            f"PP of pass {one['pass_id']}, path {res['path']}, blocks {res['blocks'][0]}-{res['blocks'][1]} "
            f"-> {one['files']['pp']}"
        )
        table = Table(title="geolocation of the PP (m)")
        for col in ("camera", "seen", "median 1 sigma", "RMS vs truth", "predicted RMS", "NEES"):
            table.add_column(col, justify="right")
        err = one.get("pp_error_m", {})
        for cam, frac in one["fraction_seen"].items():
            e = err.get(cam, {})
            sig = one["sigma_m_median"][cam]
            table.add_row(
                cam,
                f"{frac:.0%}",
                "-" if sig is None else f"{sig:.1f}",
                *([f"{e['rms']:.1f}", f"{e['predicted_rms']:.1f}", f"{e['nees']:.2f}"] if e else ["-"] * 3),
            )
        console.print(table)
    if res.get("roi"):
        print_coregistration(
            f"Reference Orbit Imagery -> {res['roi']['file']}: co-registration (px)",
            res["roi"]["cameras"],
            res["roi_coregistration_px"],
            res.get("roi_truth", {}),
            res.get("roi_predicted_px"),
        )
    misr = res.get("misr_files")
    if misr:
        n = sum(len(v) for v in misr["pp"].values()) + len(misr["roi"])
        console.print(f"{n} MISR HDF-EOS2 files -> {out / 'misr'}")
    console.print(f"{res['seconds']['total']:.0f} s")
