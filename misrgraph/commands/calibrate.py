"""``misrgraph calibrate``: camera calibration over a month of GCP passes."""

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
)

__all__ = ["calibrate"]


@handle_errors
def calibrate(
    scenario_dir: Path = typer.Argument(..., help="Scenario directory (misrgraph simulate --scenario month)."),
    camera_model: Optional[Path] = typer.Option(
        None,
        "--camera-model",
        help="Supplied model: an HDF5 file, 'preflight' (Table 1) or 'nominal'. Default: SCENARIO_DIR/camera_model.h5.",
    ),
    gcp_file: Optional[Path] = typer.Option(None, "--gcps", help="GCP database. Default: SCENARIO_DIR/gcp.h5."),
    out: Optional[Path] = typer.Option(
        None, "--out", help="Write the recalibrated camera model (HDF5, with covariance)."
    ),
    params: str = typer.Option(
        "delta,beta,epsilon,alpha2,alpha3",
        "--params",
        help="Comma list from: delta, beta, epsilon, f, alpha0..alpha5, omega.",
    ),
    focal_prior_px: float = typer.Option(
        0.05,
        "--focal-prior-px",
        help="Prior of f and alpha_i (when in --params): the focal plane known to this many pixels at the swath edge; "
        "0: the wide post-launch prior.",
    ),
    per_band: bool = typer.Option(False, "--per-band", help="Separate corrections per camera and band."),
    temperature_bins: int = typer.Option(
        1,
        "--temperature-bins",
        help="Split the passes into N bins of equal count by camera temperature, estimate the corrections per bin, "
        "write a temperature table and report each parameter's slope per deg C (1: one set).",
    ),
    max_passes: Optional[int] = typer.Option(None, "--max-passes", help="Use only the first N passes."),
    plots: Optional[Path] = typer.Option(None, "--plots", help="Write PNG plots into this directory."),
    max_iterations: int = typer.Option(100, "--max-iterations", help="Levenberg-Marquardt iterations per solve."),
    accept_unconverged: bool = typer.Option(
        False,
        "--accept-unconverged",
        help="Keep the result of a solve that did not converge (flagged) instead of failing with exit 1.",
    ),
    observations: str = typer.Option(
        "simulated",
        "--observations",
        help="simulated (each pass's observations) or matched (those 'misrgraph match' measured in a month simulated "
        "with --imagery).",
    ),
    variance_components: int = typer.Option(
        0,
        "--variance-components",
        help="Rounds of variance-component estimation: each camera's observation sigmas rescaled by its sigma0 and the "
        "month re-solved; 0: keep the stated sigmas.",
    ),
    jitter_arcsec: float = typer.Option(
        0.0,
        "--jitter-arcsec",
        help="1 sigma (arcsec, per angle) of the attitude jitter whose unresolved part is added to every GCP "
        "observation's sigma, as adjust does. 0: the matcher's sigma alone.",
    ),
    config: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP.format(cls="CalibrateConfig")),
    noise_model: Optional[Path] = typer.Option(
        None, "--noise-model", help=NOISE_HELP + " The calibration takes its attitude and ephemeris levels."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Camera calibration by space resection over GCP passes (per-pass navigation errors as nuisance)."""
    from factors.collinearity import CAMERA_PARAMS
    from misrgraph.estimate.calibrate import CalibrateConfig
    from misrgraph.runs.calibrate import run_calibrate

    names = [p.strip() for p in params.split(",") if p.strip()]
    omega = "omega" in names
    names = [p for p in names if p != "omega"]
    bad = [p for p in names if p not in CAMERA_PARAMS]
    if bad or not names:
        fail(f"--params: got {bad[0] if bad else params!r}; expected a comma list of {', '.join(CAMERA_PARAMS)}, omega")
    fields: dict[str, Any] = dict(
        params=tuple(names),
        per_band=per_band,
        estimate_omega=omega,
        focal_prior_px=focal_prior_px,
        temperature_bins=temperature_bins,
        max_iterations=max_iterations,
        accept_unconverged=accept_unconverged,
        variance_component_rounds=variance_components,
        attitude_jitter_arcsec=jitter_arcsec,
    )
    merge_config(fields, config)
    noise = load_noise(noise_model)
    if noise is not None:
        fields["noise"] = noise
    cfg = CalibrateConfig.from_dict(fields)
    check_output(out, "--out")
    with err_console.status("calibrating...") as st:
        s = run_calibrate(
            scenario_dir,
            camera_model,
            gcp_file,
            out,
            cfg,
            max_passes,
            progress=lambda m: st.update(m),
            observations=observations,
        )
    if plots is not None:
        from misrgraph.viz.plots import plot_calibration

        plot_calibration(s, plots)
    if as_json:
        print_json({k: v for k, v in s.items() if k != "rejected"})
        return
    t = Table(
        title=f"camera calibration: {s['passes']} passes, {s['iterations']} iterations, "
        f"{s['rejected_observations']['count']} observations rejected"
    )
    t.add_column("camera")
    t.add_column("corrections (arcsec for angles) +- sigma")
    t.add_column("pointing error (px)", justify="right")
    t.add_column("sigma (px)", justify="right")
    for cam, v in s["cameras"].items():
        par = ", ".join(
            f"{k} {v_['value'] / 4.8481e-6:.1f}+-{v_['sigma'] / 4.8481e-6:.1f}"
            if k.split(".")[-1] in ("delta", "beta", "epsilon")
            else f"{k} {v_['value']:.3g}+-{v_['sigma']:.2g}"
            for k, v_ in v["params"].items()
        )
        t.add_row(cam, par, f"{v.get('pointing_error_px', float('nan')):.3f}", f"{v['sigma_px']:.3f}")
    console.print(t)
    if "max_pointing_error_px" in s:
        console.print(
            f"max pointing error {s['max_pointing_error_px']:.3f} px (requirement 0.125); NEES/dim {s['nees']:.2f}"
        )
    for pd in s["poorly_determined"]:
        console.print(
            f"[yellow]poorly determined:[/] {pd['parameter']} (posterior sigma {pd['ratio']:.0%} of its prior)"
        )
    if "thermal" in s:
        th = s["thermal"]
        tt = Table(
            title="thermal slopes per deg C (angles in arcsec) over bins at "
            + ", ".join(f"{x:.1f}" for x in th["bins_c"])
            + " C"
        )
        tt.add_column("camera")
        tt.add_column("slope +- sigma (true)")
        for cam, ps in th["slopes"].items():
            tt.add_row(
                cam,
                ", ".join(
                    f"{p} {e.get('slope_arcsec_per_c', e['slope_per_c']):.3g}"
                    f"+-{e.get('sigma_arcsec_per_c', e['sigma_per_c']):.2g}"
                    + (
                        f" ({e['true_slope_per_c'] / (4.8481e-6 if 'slope_arcsec_per_c' in e else 1):.3g})"
                        if "true_slope_per_c" in e
                        else ""
                    )
                    for p, e in ps.items()
                ),
            )
        console.print(tt)
        if "nees" in th:
            console.print(f"thermal slopes NEES/dim {th['nees']:.2f} over {th['nees_dim']}")
