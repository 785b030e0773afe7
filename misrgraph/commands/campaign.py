"""``misrgraph campaign``: calibration, adjustments and products of many paths on Dask."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    CONFIG_HELP,
    NOISE_HELP,
    check_output,
    console,
    err_console,
    fail,
    handle_errors,
    load_noise,
    merge_config,
    print_json,
    progress_bar,
)

__all__ = ["campaign"]

CAMPAIGN_HELP = """The calibration campaign as one command, on Dask.

Calibrate the cameras on a GCP month, adjust the chosen repeat passes of each path with the
calibrated model, build each path's incremental state and Projection Parameters, and write a report
(OUT/report/campaign.md) and OUT/summary.json.

Inputs are simulated into OUT/inputs unless --inputs names scenario directories (month/ and
path_PPP/). Tasks run on a LocalCluster of --workers processes (default: one per core), on the
cluster at --scheduler (its workers must see OUT at the same path), or with --workers 0 in this
process without Dask. Rerun the same command to resume: every output is named by a digest of its
inputs and written atomically, so nothing done is redone and nothing is counted twice. Exit status
1 when any task failed (each failure is reported with its reason; none stops the others)."""


@handle_errors
def campaign(
    out: Path = typer.Option(..., "--out", help="Campaign directory (created; rerun into it to resume)."),
    months: float = typer.Option(
        6.0, "--months", help="Months of data after the epoch (a path repeats every 16 days)."
    ),
    fraction: float = typer.Option(0.3, "--fraction", help="Fraction of each path's repeat passes adjusted."),
    paths: Optional[str] = typer.Option(
        None, "--paths", help="Paths, comma-separated or ranges (37,38 or 30-33). Default: all 233."
    ),
    passes_per_path: int = typer.Option(
        4, "--passes-per-path", help="At least this many passes per path (if the period has them)."
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="LocalCluster worker processes (default: one per core; 0: this process, no Dask)."
    ),
    scheduler: Optional[str] = typer.Option(
        None, "--scheduler", help="Address of a running Dask scheduler, tcp://HOST:PORT."
    ),
    inputs: Optional[Path] = typer.Option(
        None, "--inputs", help="Existing scenarios: a directory with month/ and path_PPP/. Default: simulate them."
    ),
    size: str = typer.Option(
        "standard", "--size", help="Simulated scenario size: standard (45-minute passes, 600 tie points) or reduced."
    ),
    truth: str = typer.Option(
        "independent", "--truth", help="Simulator truth: independent or model (see simulate --help)."
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated inputs."),
    pp_blocks: int = typer.Option(0, "--pp-blocks", help="SOM blocks of each path's PP (0: 10 standard, 2 reduced)."),
    no_products: bool = typer.Option(False, "--no-products", help="Skip the per-path state and products."),
    roi: bool = typer.Option(
        False,
        "--roi",
        help="Build each path's Reference Orbit Imagery from its state (inputs with whole-swath strips and a SOM DEM; "
        "simulated inputs get them).",
    ),
    roi_blocks: int = typer.Option(
        1, "--roi-blocks", help="Blocks of strips a simulated path gets with --roi, from the one under mid-pass."
    ),
    observations: str = typer.Option(
        "simulated",
        "--observations",
        help="simulated (each pass's own) or matched (measured in the imagery by 'misrgraph match': simulated inputs "
        "are then rendered and matched, brought ones must have been) for the calibration, the adjustments and "
        "the path states.",
    ),
    recalibrate: float = typer.Option(
        0.0,
        "--recalibrate",
        help="Months between calibration windows (0: one calibration). Each window is calibrated, the "
        "calibrations are watched for a change, and each pass is adjusted with the camera-model version "
        "valid for its orbit (OUT/cgm/).",
    ),
    noise_fit_passes: int = typer.Option(
        0,
        "--noise-fit-passes",
        help="Learn the noise levels on this many of the first passes (noise fit) and adjust every other "
        "pass and path with them (0: the --noise-model or pre-flight levels throughout).",
    ),
    monitor_alpha: float = typer.Option(
        0.05, "--monitor-alpha", help="False-alarm probability of the monitor over a campaign (with --recalibrate)."
    ),
    config: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP.format(cls="CampaignConfig")),
    noise_model: Optional[Path] = typer.Option(None, "--noise-model", help=NOISE_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    from misrgraph.campaign.plan import CampaignConfig, parse_paths
    from misrgraph.campaign.run import run_campaign

    if workers is not None and scheduler is not None:
        fail("--workers and --scheduler: give one (--workers starts a local cluster, --scheduler uses yours)")
    fields: dict[str, Any] = dict(
        months=months,
        fraction=fraction,
        paths=parse_paths(paths) if paths else (),
        passes_per_path=passes_per_path,
        size=size,
        truth=truth,
        seed=seed,
        pp_blocks=pp_blocks,
        products=not no_products,
        roi=roi,
        roi_blocks=roi_blocks,
        observations=observations,
        recalibrate_months=recalibrate,
        noise_fit_passes=noise_fit_passes,
        monitor_alpha=monitor_alpha,
    )
    merge_config(fields, config)
    noise = load_noise(noise_model)
    if noise is not None:
        fields["noise"] = noise
    cfg = CampaignConfig.from_dict(fields)
    if inputs is not None and cfg.recalibrate_months:
        fail("--inputs: a campaign over years (--recalibrate) simulates its windows; give one or the other")
    check_output(out / "summary.json", "--out")
    with progress_bar("campaign: starting", disable=as_json, counts=True) as update:

        def progress(done: int, total: int, message: str) -> None:
            if message.startswith("Dask dashboard"):
                err_console.print(message)  # the bar's console: printed above the live bar
            update(message, done, total)

        res = run_campaign(out, cfg, inputs=inputs, workers=workers, scheduler=scheduler, progress=progress)
    if as_json:
        print_json(res)
    else:
        p = res["passes"]
        console.print(
            f"{p['done']}/{p['planned']} passes adjusted ({p['failed']} failed) in {res['seconds']:.0f} s "
            f"on {res['cluster'].get('kind')}; report: {res['report']}"
        )
        cal = res["calibration"]
        if cal.get("status") == "done" and cal.get("max_pointing_error_px") is not None:
            console.print(f"calibration: largest pointing error {cal['max_pointing_error_px']:.3f} px -> {cal['file']}")
        table = Table(title="per path")
        for col in (
            "path",
            "passes",
            "check-point RMS (m)",
            "co-registration max (px)",
            "PP error RMS (m)",
            "ROI co-registration (px)",
        ):
            table.add_column(col, justify="right")
        fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
        for path_, v in res["paths"].items():
            table.add_row(
                path_,
                f"{v['passes']['done']}/{v['passes']['planned']}",
                fmt(v["checkpoint_rms_m"], ".1f"),
                fmt(v["coregistration_px_max"], ".3f"),
                fmt((v.get("products") or {}).get("pp_error_rms_m"), ".1f"),
                fmt(((v.get("products") or {}).get("roi") or {}).get("coregistration_px_max"), ".2f"),
            )
        console.print(table)
        for f in res["failed"]:
            err_console.print(f"failed: {f['stage']} {f['name']}: {f['reason']}", markup=False)
    if res["failed"]:
        raise typer.Exit(1)
