"""``misrgraph adjust`` and ``misrgraph tie-height``: the bundle adjustment of one pass."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    CONFIG_HELP,
    NOISE_HELP,
    adjust_config,
    check_output,
    console,
    err_console,
    fail,
    handle_errors,
    mode_or_sigma,
    parse_comma_list,
    print_json,
)
from misrgraph.model.errormodels import ATTITUDE_DAMPING

__all__ = ["adjust", "tie_height"]


@handle_errors
def adjust(
    scenario_dir: Path = typer.Argument(..., help="Scenario directory (misrgraph simulate), or one with real inputs."),
    camera_model: Optional[Path] = typer.Option(
        None,
        "--camera-model",
        help="Camera model: an HDF5 file (e.g. written by calibrate), 'preflight' (Table 1), 'nominal', or a "
        "CGM store (misrgraph cgm), whose version valid for the pass's orbit is used. "
        "Default: SCENARIO_DIR/camera_model.h5.",
    ),
    pass_file: Optional[Path] = typer.Option(
        None, "--pass", help="Pass file (needed when SCENARIO_DIR/passes holds several)."
    ),
    gcp_file: Optional[Path] = typer.Option(None, "--gcps", help="GCP database. Default: SCENARIO_DIR/gcp.h5."),
    dem_file: Optional[Path] = typer.Option(None, "--dem", help="DEM tiles. Default: SCENARIO_DIR/dem.h5."),
    out: Optional[Path] = typer.Option(
        None, "--out", help="Write RESULT.h5 (error models, landmarks, covariances, residuals)."
    ),
    plots: Optional[Path] = typer.Option(None, "--plots", help="Write PNG plots into this directory (needs --out)."),
    pitch_spacing: float = typer.Option(
        60.0,
        "--pitch-knots-s",
        help="Pitch knot spacing (s); a --noise-model file's attitude.knot_spacing_s replaces it.",
    ),
    rollyaw_spacing: float = typer.Option(
        60.0,
        "--roll-yaw-knots-s",
        help="Roll and yaw knot spacing (s); a --noise-model file's attitude.knot_spacing_s replaces it.",
    ),
    threshold1: int = typer.Option(
        1, "--threshold1", help="Eq. 28: minimum observations per knot support (--knot-prior independent)."
    ),
    threshold2: int = typer.Option(
        1, "--threshold2", help="Eq. 29: minimum cameras per knot support (--knot-prior independent)."
    ),
    knot_rule: str = typer.Option(
        "support",
        "--knot-rule",
        help="Where eqs. 28-29 count: 'support' (each knot's support) or 'interval' ([t_i, t_i+1), as the paper "
        "writes).",
    ),
    knot_prior: str = typer.Option(
        "process",
        "--knot-prior",
        help="'process': consecutive knots tied by the attitude error process, every knot kept; "
        "'process+jitter': the process plus the jitter's share of the knots, one joint prior per angle; "
        "'independent': the paper's independent knot priors with eqs. 28-29's knot removal.",
    ),
    knot_damping: float = typer.Option(
        ATTITUDE_DAMPING,
        "--knot-damping",
        help="Damping ratio of the process knot prior (1: Matern-3/2; see docs, explanation/conventions).",
    ),
    no_dem: bool = typer.Option(False, "--no-dem", help="Leave out the DEM height factors."),
    dem_sigma_scale: float = typer.Option(
        1.0,
        "--dem-sigma-scale",
        help="The DEM height factors' 1 sigma is the DEM's stated 1 sigma times this, with the local surface fit's "
        "residual added in quadrature.",
    ),
    dem_smoothing: float = typer.Option(
        1.0,
        "--dem-smoothing",
        help="1 sigma (DEM postings, 0-2) of the Gaussian low-pass of the DEM the height factors read; 0: the raw DEM.",
    ),
    robust: str = typer.Option(
        "cauchy", "--robust", help="Loss of the first (blunder-finding) solve: cauchy, huber or none."
    ),
    max_iterations: int = typer.Option(100, "--max-iterations", help="Levenberg-Marquardt iterations per solve."),
    snooping_rounds: int = typer.Option(
        4,
        "--snooping-rounds",
        help="Rounds of iterated data snooping (Baarda, alpha 0.001) after the least-squares solve; 0: off.",
    ),
    drop_rejected: bool = typer.Option(
        False,
        "--drop-rejected-tie-points",
        help="Drop a tie point whole when any of its observations is rejected (robust screen or snooping).",
    ),
    variance_components: int = typer.Option(
        3,
        "--variance-components",
        help="Rounds of variance-component estimation: the sigmas of each class (tie points per camera, GCP "
        "measurements) are learned from the pass when its redundancy is at least 30; 0: keep the stated sigmas.",
    ),
    jitter_arcsec: float = typer.Option(
        1.0,
        "--jitter-arcsec",
        help="1 sigma (arcsec, per angle) of the attitude jitter. The part the knots cannot follow is noise in every "
        "image observation and in every geolocation sigma. 0: none.",
    ),
    no_jitter_weights: bool = typer.Option(
        False,
        "--no-jitter-in-weights",
        help="Weight the image observations by the matcher's sigma alone (the unresolved jitter still enters the "
        "geolocation sigmas).",
    ),
    jitter_periods: str = typer.Option(
        "8,120", "--jitter-periods-s", help="The jitter's periods (s), MIN,MAX, equal power per log-period."
    ),
    once_per_rev: float = typer.Option(
        0.0,
        "--ephemeris-once-per-rev-m",
        help="1 sigma amplitude (m, per orbital axis) of a once-per-revolution ephemeris error; the ephemeris segments "
        "then get one joint prior. 0: none.",
    ),
    eph_segments: int = typer.Option(
        1, "--ephemeris-segments", help="Eq. 19 segments over the pass (1, or 2 with --ephemeris-once-per-rev-m)."
    ),
    accept_unconverged: bool = typer.Option(
        False,
        "--accept-unconverged",
        help="Keep the result of a solve that did not converge (flagged in the summary and RESULT.h5) instead of "
        "failing with exit 1.",
    ),
    observations: str = typer.Option(
        "simulated",
        "--observations",
        help="simulated (the pass's observations) or matched (those 'misrgraph match' measured in the imagery).",
    ),
    tie_height: str = typer.Option(
        "auto",
        "--tie-height-sigma-m",
        help="1 sigma (m) of the height error a matched tie point's rays share: 'auto' estimates it for matched tie "
        "points and leaves it out for simulated ones; 'estimate' always estimates it; a number fixes it (0: off).",
    ),
    tie_offset: str = typer.Option(
        "auto",
        "--tie-offset-sigma-px",
        help="1 sigma (px) of the offset a matched tie point's conjugates share: 'auto' takes what 'misrgraph match' "
        "measured and leaves it out for simulated tie points; a number fixes it (0: off).",
    ),
    config: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP.format(cls="AdjustConfig")),
    noise_model: Optional[Path] = typer.Option(None, "--noise-model", help=NOISE_HELP),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Simultaneous bundle adjustment of one pass: ephemeris and attitude error models with covariances."""
    from misrgraph.runs.adjust import run_adjust

    periods = parse_comma_list("--jitter-periods-s", jitter_periods, float, "8,120")
    tie_height_setting = mode_or_sigma("--tie-height-sigma-m", tie_height, ("auto", "estimate"), "m")
    tie_offset_setting = mode_or_sigma("--tie-offset-sigma-px", tie_offset, ("auto",), "px")
    fields: dict[str, Any] = dict(
        knot_spacing_s=(rollyaw_spacing, pitch_spacing, rollyaw_spacing),
        threshold1=threshold1,
        threshold2=threshold2,
        knot_rule=knot_rule,
        knot_prior=knot_prior,
        knot_prior_damping=knot_damping,
        use_dem=not no_dem,
        dem_sigma_scale=dem_sigma_scale,
        dem_smoothing_postings=dem_smoothing,
        robust=robust,
        max_iterations=max_iterations,
        snooping_rounds=snooping_rounds,
        variance_component_rounds=variance_components,
        drop_rejected_tie_points=drop_rejected,
        accept_unconverged=accept_unconverged,
        attitude_jitter_arcsec=jitter_arcsec,
        attitude_jitter_periods_s=periods,
        jitter_in_weights=not no_jitter_weights,
        ephemeris_once_per_rev_m=once_per_rev,
        ephemeris_segments=eph_segments,
        tie_height_sigma_m=tie_height_setting,
        tie_offset_sigma_px=tie_offset_setting,
    )
    cfg = adjust_config(fields, config, noise_model)
    if plots is not None and out is None:
        fail("--plots: needs --out RESULT.h5 (the plots are drawn from it)")
    check_output(out, "--out")
    with err_console.status("adjusting...") as st:
        summary = run_adjust(
            scenario_dir,
            camera_model,
            pass_file,
            gcp_file,
            dem_file,
            out,
            cfg,
            progress=lambda s: st.update(s),
            observations=observations,
        )
    if plots is not None:
        from misrgraph.viz.plots import plot_adjustment

        plot_adjustment(out, plots)
    if as_json:
        print_json(summary)
        return
    _print_adjust_summary(summary)


@handle_errors
def tie_height(
    results: list[Path] = typer.Argument(
        ..., help="RESULT.h5 files of 'adjust --observations matched --out', one per pass."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Pool the matched tie points' shared height error over passes.

    On a short pass one estimate is as uncertain as the variance itself; the pooled 1 sigma is the
    value to fix with 'adjust --tie-height-sigma-m'.
    """
    from misrgraph.runs.adjust import run_tie_height_pool

    res = run_tie_height_pool(results)
    if as_json:
        print_json(res)
        return
    console.print(
        f"tie points' shared height error, pooled over {res['passes']} passes ({res['dem_factors']} DEM factors): "
        f"[bold]{res['sigma_m']:.1f} m[/bold] (variance {res['unclipped_variance_m2']:.0f} "
        f"± {res['standard_error_m2']:.0f} m², 1 sigma from the passes' scatter)",
        soft_wrap=True,
    )
    for path, why in res["skipped"].items():
        console.print(f"  skipped {path}: {why}", soft_wrap=True, markup=False, highlight=False)
    console.print(
        f"fix it with: misrgraph adjust ... --observations matched --tie-height-sigma-m {res['sigma_m']:.1f}",
        soft_wrap=True,
        highlight=False,
    )


def _print_learned_sigma(vc: dict | None) -> None:
    """The observation sigmas the variance components learned, one row per class."""
    if not vc or not vc.get("classes"):
        return
    t = Table(title=f"observation sigmas (variance components, {vc['rounds']} rounds)")
    for col in ("class", "stated (px)", "used (px)", "scale", "+-1 sigma", "redundancy", "status"):
        t.add_column(col, justify="right")
    for name, v in vc["classes"].items():
        t.add_row(
            name,
            f"{v['stated_sigma_px']:.3f}",
            f"{v['sigma_px']:.3f}",
            f"{v['scale']:.3f}",
            f"{v['scale_sd']:.3f}",
            f"{v['redundancy']:.0f}",
            v["status"],
        )
    console.print(t)


def _print_adjust_summary(s: dict) -> None:
    console.print(
        f"pass {s['pass_id']}: {s['observations']} observations, {s['landmarks']} landmarks, "
        f"{s['iterations']} iterations ({s['solver_status'].replace('_', ' ')}), cost {s['final_cost']:.1f}, "
        f"{s['seconds']:.1f} s"
    )
    console.print("knots kept/removed: " + ", ".join(f"{a} {v['kept']}/{v['removed']}" for a, v in s["knots"].items()))
    rej = s["rejected_observations"]
    console.print(
        f"rejected observations: {rej['count']}" + (f" (all in {rej['full_list']})" if rej["full_list"] else "")
    )
    for d in s.get("diagnostics", []):
        console.print(f"[yellow]note:[/] {d}")
    _print_learned_sigma(s.get("reliability", {}).get("observation_sigma"))
    dem = s.get("reliability", {}).get("dem_sigma") or {}
    if dem.get("status") not in (None, "none"):
        console.print(
            f"DEM heights: scale on the DEM's stated sigma {dem['sigma_scale']:.3f} ({dem['status']}; "
            f"sigma0 {dem['sigma0']:.3f}, redundancy {dem['redundancy']:.0f}, "
            f"stated sigma {100 * dem['stated_share']:.0f} % of the factors' variance)"
        )
    th = s.get("tie_height", {})
    if th.get("source") == "estimated":
        console.print(
            f"tie points' shared height error (template relief, from {th['dem_factors']} DEM residuals): "
            f"{th['sigma_m']:.1f} m (variance {th['unclipped_variance_m2']:.0f} +- {th['standard_error_m2']:.0f} m^2), "
            "added to their covariance along An's ray"
        )
    elif th.get("source") == "fixed":
        console.print(
            f"tie points' shared height error: {th['sigma_m']:.1f} m (fixed), added to their covariance along An's ray"
        )
    to = s.get("tie_offset", {})
    if to.get("source") in ("matched", "fixed"):
        console.print(
            f"offset shared by a tie point's conjugates: {to['sigma_px']:.3f} px "
            f"({'measured by the matcher' if to['source'] == 'matched' else 'fixed'}), its effect added to "
            f"{to.get('tie_points', 0)} tie points' covariance"
        )
    if "checkpoint_geolocation_m" in s:
        t = Table(title="check points: ground error (m) with supplied -> corrected navigation")
        for col in ("camera", "before mean", "before std", "after mean", "after std", "ratio", "co-reg vs An (px)"):
            t.add_column(col, justify="right")
        for cam, v in s["checkpoint_geolocation_m"].items():
            t.add_row(
                cam,
                f"{v['before']['mean']:.1f}",
                f"{v['before']['std']:.1f}",
                f"{v['after']['mean']:.1f}",
                f"{v['after']['std']:.1f}",
                f"{v['ratio_before_over_after']:.1f}",
                f"{s['coregistration_px'].get(cam, float('nan')):.3f}",
            )
        console.print(t)
        att, obs = s["attitude_rms_arcsec"], s["attitude_rms_arcsec_observed"]
        console.print(
            "attitude RMS error (arcsec) where observed / whole pass: "
            + ", ".join(f"{k} {obs[k]:.2f}/{v:.2f}" for k, v in att.items())
            + f" ({100 * s['observed_fraction_of_pass']:.0f} % of the pass observed); "
            f"ephemeris RMS error {s['ephemeris_rms_m']:.1f} m"
        )
        n = s["nees"]
        parts = [f"knots {n['knots']:.2f}", f"landmarks {n['landmarks']:.2f}"]
        if "landmarks_within" in n:
            parts[-1] += (
                f" (common to {s['landmark_split']['window_s']:.0f} s windows {n['landmarks_common']:.2f}, "
                f"within them {n['landmarks_within']:.2f})"
            )
        parts += [
            f"{name} {n[k]:.2f}"
            for k, name in (("camera", "camera"), ("ephemeris", "ephemeris"), ("state", "whole state"))
            if k in n
        ]
        console.print("NEES / dim: " + ", ".join(parts) + " (1 = honest)")
