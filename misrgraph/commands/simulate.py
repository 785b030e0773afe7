"""``misrgraph simulate``: a scenario directory of simulated passes, GCPs, DEM and camera models."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer

from misrgraph.commands.common import (
    CONFIG_HELP,
    check_output,
    console,
    handle_errors,
    merge_config,
    print_json,
    progress_bar,
)

__all__ = ["simulate"]


@handle_errors
def simulate(
    scenario: str = typer.Option(
        "pass",
        "--scenario",
        help="pass (one adjustment pass), month (GCP passes for calibration) or path (repeat passes of one path "
        "seeing the same features).",
    ),
    passes: int = typer.Option(10, "--passes", help="Repeat passes of the path scenario (16 days apart)."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same files."),
    out: Path = typer.Option(
        ..., "--out", help="Output directory (created; replaced if it holds an earlier scenario)."
    ),
    path: int = typer.Option(37, "--path", help="WRS-2 path (1..233) of the pass, or the reference path of the month."),
    tie_points: int = typer.Option(1000, "--tie-points", help="Tie points per pass."),
    check_points: int = typer.Option(100, "--check-points", help="Independent check points per pass."),
    gcps: int = typer.Option(120, "--gcps", help="GCPs in the database."),
    days: int = typer.Option(30, "--days", help="Length of the month scenario (days)."),
    duration: float = typer.Option(2700.0, "--duration", help="Pass duration (s)."),
    gcp_blunder_rate: float = typer.Option(
        0.05, "--gcp-blunder-rate", help="Fraction of GCP observations that are blunders."
    ),
    tie_blunder_rate: float = typer.Option(
        0.0, "--tie-blunder-rate", help="Fraction of tie-point observations that are blunders."
    ),
    nav_sigma: float = typer.Option(50.0, "--nav-sigma-m", help="Ephemeris offset 1 sigma per axis (m)."),
    misalignment: float = typer.Option(60.0, "--misalignment-arcsec", help="Camera misalignment 1 sigma (arcsec)."),
    noise_free: bool = typer.Option(False, "--noise-free", help="No measurement noise and no blunders."),
    camera_truth: Optional[Path] = typer.Option(
        None,
        "--camera-truth",
        help="Use this true camera model (e.g. another scenario's camera_truth.h5) instead of drawing one.",
    ),
    chips: bool = typer.Option(False, "--chips", help="Store nine 64x64 image chips per GCP."),
    thermal: float = typer.Option(
        0.0,
        "--thermal-arcsec-per-c",
        help="1 sigma of each camera's delta and beta temperature slopes (arcsec per deg C; 0: none). The true camera "
        "is then a temperature table and each pass is simulated at its own camera temperature.",
    ),
    thermal_ppm: float = typer.Option(
        0.0, "--thermal-ppm-per-c", help="1 sigma of each camera's focal-length temperature slope (ppm per deg C)."
    ),
    bands: str = typer.Option("red", "--bands", help="Bands observed, comma-separated from blue, green, red, nir."),
    band_misalignment: float = typer.Option(
        0.0, "--band-misalignment-arcsec", help="1 sigma of each band's own delta, beta, epsilon offsets (arcsec)."
    ),
    truth: str = typer.Option(
        "independent",
        "--truth",
        help="independent: error sources the estimator does not share (attitude process with jitter, once-per-rev "
        "ephemeris, sub-posting terrain, correlated DEM and GCP errors, heavy-tailed matching noise); it checks "
        "the estimator. model: errors drawn from the estimator's own parameterisations; it checks the algebra.",
    ),
    imagery: bool = typer.Option(
        False,
        "--imagery",
        help="Also render the image windows matching reads (ray-cast, 14-bit) and the GCPs' reference chips into each "
        "pass file (about 0.3 s per GCP observation and band).",
    ),
    coast_ramp: float = typer.Option(
        8000.0,
        "--coast-ramp-m",
        help="Distance inland (m) over which the relief rises from 0 at the coast to its full height (0: a cliff).",
    ),
    cloud_fraction: float = typer.Option(
        0.0, "--cloud-fraction", help="With --imagery: fraction of the sky covered by clouds on a layer 3 km up."
    ),
    roi_blocks: Optional[str] = typer.Option(
        None,
        "--roi-blocks",
        help="With --imagery: also render every pass's whole image lines over SOM blocks A-B (red band, all cameras) "
        "and write dem_som.h5, for 'misrgraph products --roi'.",
    ),
    config: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP.format(cls="ScenarioConfig")),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Simulate a scenario directory: passes, GCP database, DEM, supplied and true camera models."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    fields: dict[str, Any] = dict(
        scenario=scenario,
        seed=seed,
        path=path,
        n_passes=passes,
        n_tie_points=tie_points,
        n_check_points=check_points,
        n_gcps=gcps,
        month_days=days,
        duration_s=duration,
        gcp_blunder_rate=gcp_blunder_rate,
        tie_blunder_rate=tie_blunder_rate,
        nav_sigma_m=nav_sigma,
        camera_misalignment_arcsec=misalignment,
        noise_free=noise_free,
        with_chips=chips,
        camera_truth=str(camera_truth) if camera_truth else "",
        thermal_arcsec_per_c=thermal,
        thermal_focal_ppm_per_c=thermal_ppm,
        bands=tuple(b.strip() for b in bands.split(",") if b.strip()),
        band_misalignment_arcsec=band_misalignment,
        truth=truth,
        imagery=imagery,
        cloud_fraction=cloud_fraction,
        coast_ramp_m=coast_ramp,
    )
    if roi_blocks:
        from misrgraph.runs.products import parse_blocks

        rb = parse_blocks(roi_blocks)
        fields["roi_blocks"] = (int(rb[0]), int(rb[-1]))
    merge_config(fields, config)
    cfg = ScenarioConfig.from_dict(fields)
    check_output(out, "--out")
    with progress_bar("simulating", disable=as_json) as progress:
        summary = run_simulate(cfg, out, progress=progress)
    if as_json:
        print_json({k: v for k, v in summary.items() if k != "pass_summaries"})
        return
    console.print(
        f"[bold]{cfg.scenario}[/] scenario (seed {cfg.seed}) written to {out}: {summary['passes']} passes, "
        f"{summary['observations']} observations, {summary['gcps_seen']} GCPs seen "
        f"({summary['gcps_seen_in_3_or_more_passes']} in 3 or more passes)"
    )
