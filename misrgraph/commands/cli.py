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

from misrgraph.errors import InputError, MisrGraphError
from misrgraph.model.errormodels import ATTITUDE_DAMPING

__all__ = ["app", "main"]

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_show_locals=False, help="In-flight geometric calibration of MISR as a GTSAM factor graph.")
console = Console()
err_console = Console(stderr=True)


def _fail(message: str, code: int = 2) -> None:
    err_console.print(f"misrgraph: error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


#: Set by ``misrgraph --debug``: errors propagate with their traceback instead of one line.
_DEBUG = False


def handle_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Decorator, the one error boundary of every command: any failure ends with one line on
    stderr naming what went wrong. Exit status 2 for bad input (InputError, FileFormatError,
    DegenerateProblemError), 1 for a failed computation or an unexpected error, 130 when
    interrupted. ``misrgraph --debug`` re-raises instead, with the traceback."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, SystemExit):
            raise
        except MisrGraphError as exc:
            if _DEBUG:
                raise
            _fail(str(exc), exc.exit_code)
        except KeyboardInterrupt:
            _fail("interrupted", 130)
        except Exception as exc:
            if _DEBUG:
                raise
            where = f" in {fn.__name__}"
            _fail(f"internal error{where} ({exc.__class__.__name__}: {exc}). "
                  "Rerun with 'misrgraph --debug ...' for the traceback", 1)

    return wrapper


def _merge_config(fields: dict[str, Any], config: Optional[Path]) -> None:
    """Update ``fields`` from a ``--config`` JSON file (its keys win over the options)."""
    if config is None:
        return
    try:
        fields.update(json.loads(config.read_text()))
    except (OSError, json.JSONDecodeError) as exc:
        _fail(f"--config: cannot read {config}: {exc}")


def _print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=2, sort_keys=False) + "\n")


@app.callback()
def _root(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress details."),
          debug: bool = typer.Option(False, "--debug", help="Show the full traceback of an error instead of one line.")) -> None:
    global _DEBUG
    _DEBUG = debug
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
    from misrgraph.evaluate.sensitivity import run_sensitivity

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
def simulate(
    scenario: str = typer.Option("pass", "--scenario", help="pass (one adjustment pass), month (GCP passes for calibration) or path (repeat passes of one path seeing the same features)."),
    passes: int = typer.Option(10, "--passes", help="Repeat passes of the path scenario (16 days apart)."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same files."),
    out: Path = typer.Option(..., "--out", help="Output directory (created; replaced if it is an earlier scenario)."),
    path: int = typer.Option(37, "--path", help="WRS-2 path (1..233) of the pass / reference path of the month."),
    tie_points: int = typer.Option(1000, "--tie-points", help="Tie points per pass (pass scenario)."),
    check_points: int = typer.Option(100, "--check-points", help="Independent check points per pass."),
    gcps: int = typer.Option(120, "--gcps", help="GCPs in the database."),
    days: int = typer.Option(30, "--days", help="Length of the month scenario (days)."),
    duration: float = typer.Option(2700.0, "--duration", help="Pass duration (s)."),
    gcp_blunder_rate: float = typer.Option(0.05, "--gcp-blunder-rate", help="Fraction of GCP observations that are blunders."),
    tie_blunder_rate: float = typer.Option(0.0, "--tie-blunder-rate", help="Fraction of tie-point observations that are blunders."),
    nav_sigma: float = typer.Option(50.0, "--nav-sigma-m", help="Ephemeris offset 1 sigma per axis (m)."),
    misalignment: float = typer.Option(60.0, "--misalignment-arcsec", help="Camera misalignment 1 sigma (arcsec)."),
    noise_free: bool = typer.Option(False, "--noise-free", help="No measurement noise and no blunders."),
    camera_truth: Optional[Path] = typer.Option(None, "--camera-truth", help="Use this true camera model (e.g. another scenario's camera_truth.h5) instead of drawing one."),
    chips: bool = typer.Option(False, "--chips", help="Store nine 64x64 image chips per GCP."),
    thermal: float = typer.Option(0.0, "--thermal-arcsec-per-c", help="Thermal truth: 1 sigma of each camera's delta and beta slopes (arcsec per deg C; 0 = none). The true camera is then a temperature table and each pass is simulated at its own camera temperature."),
    thermal_ppm: float = typer.Option(0.0, "--thermal-ppm-per-c", help="Thermal truth: 1 sigma of each camera's focal-length scale slope (ppm per deg C)."),
    bands: str = typer.Option("red", "--bands", help="Bands observed, comma-separated from blue, green, red, nir (e.g. all four for band-to-band calibration)."),
    band_misalignment: float = typer.Option(0.0, "--band-misalignment-arcsec", help="Per-band truth: 1 sigma of each band's own delta, beta, epsilon offsets (arcsec)."),
    truth: str = typer.Option("independent", "--truth", help="independent (the default) or model (navigation errors drawn from the estimator's own parameterisations: checks the algebra only). independent: error sources the estimator does not share: an attitude process with jitter, a once-per-revolution ephemeris term, sub-posting terrain, DEM error correlated over 28 km, f/alpha camera errors, Student-t matching noise with 1-2 px mismatches, scene-correlated GCP errors (see docs/design.md); it checks the estimator."),
    imagery: bool = typer.Option(False, "--imagery", help="Also render the image windows matching reads (ray-cast through the true geometry, 14-bit; tie points in red, GCP windows and chips in every band of --bands) and the GCPs' reference chips, into each pass file (every scenario; a month gets its GCP windows and chips, ~0.3 s per GCP observation and band)."),
    coast_ramp: float = typer.Option(8000.0, "--coast-ramp-m", help="Distance inland (m) over which the terrain's relief rises from 0 at the coast to its full height (0: a cliff of the relief's height, ~1.2 km on average, at every coast, as in scenarios simulated before 2026-11-25)."),
    cloud_fraction: float = typer.Option(0.0, "--cloud-fraction", help="With --imagery: fraction of the sky covered by clouds on a layer 3 km up (they appear displaced with view angle; each pass has its own)."),
    roi_blocks: Optional[str] = typer.Option(None, "--roi-blocks", help="With --imagery: also render every pass's whole image lines over these SOM blocks A-B (red band, all cameras; ~12 microseconds per pixel: ~80 s a block and pass of 9 cameras on 2 cores) and write dem_som.h5, for 'misrgraph products --roi'."),
    config: Optional[Path] = typer.Option(None, "--config", help="JSON file of ScenarioConfig fields (overrides the options; strip_cameras, strip_samples and roi_dem_sigma_m are set here)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Simulate a scenario directory: passes, GCP database, DEM, supplied and true camera models."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    fields = dict(scenario=scenario, seed=seed, path=path, n_passes=passes, n_tie_points=tie_points, n_check_points=check_points,
                  n_gcps=gcps, month_days=days, duration_s=duration, gcp_blunder_rate=gcp_blunder_rate,
                  tie_blunder_rate=tie_blunder_rate, nav_sigma_m=nav_sigma, camera_misalignment_arcsec=misalignment,
                  noise_free=noise_free, with_chips=chips, camera_truth=str(camera_truth) if camera_truth else "",
                  thermal_arcsec_per_c=thermal, thermal_focal_ppm_per_c=thermal_ppm,
                  bands=tuple(b.strip() for b in bands.split(",") if b.strip()), band_misalignment_arcsec=band_misalignment,
                  truth=truth, imagery=imagery, cloud_fraction=cloud_fraction, coast_ramp_m=coast_ramp)
    if roi_blocks:
        from misrgraph.runs.products import parse_blocks

        rb = parse_blocks(roi_blocks)
        fields["roi_blocks"] = (int(rb[0]), int(rb[-1]))
    _merge_config(fields, config)
    cfg = ScenarioConfig.from_dict(fields)
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=err_console,
                  disable=as_json) as bar:
        task = bar.add_task("simulating", total=None)

        def progress(desc: str, k: int, n: int) -> None:
            bar.update(task, description=desc, completed=k, total=max(n, 1))

        summary = run_simulate(cfg, out, progress=progress)
    if as_json:
        _print_json({k: v for k, v in summary.items() if k != "pass_summaries"})
        return
    console.print(f"[bold]{cfg.scenario}[/] scenario (seed {cfg.seed}) written to {out}: {summary['passes']} passes, "
                  f"{summary['observations']} observations, {summary['gcps_seen']} GCPs seen "
                  f"({summary['gcps_seen_in_3_or_more_passes']} in 3 or more passes)")


@app.command()
@handle_errors
def info(file: Path = typer.Argument(..., help="A misrgraph HDF5 file."),
         as_json: bool = typer.Option(False, "--json", help="Print JSON.")) -> None:
    """Validate a misrgraph HDF5 file and print what it holds."""
    from misrgraph.io.info import run_info

    res = run_info(file)
    if as_json:
        _print_json(res)
        return
    table = Table(title=str(file), show_header=False)
    for k, v in res.items():
        table.add_row(k, json.dumps(v) if isinstance(v, (dict, list)) else str(v))
    console.print(table)


@app.command()
@handle_errors
def adjust(
    scenario_dir: Path = typer.Argument(..., help="Scenario directory (misrgraph simulate --scenario pass)."),
    camera_model: Optional[Path] = typer.Option(None, "--camera-model", help="Camera model HDF5, or 'preflight' (Table 1) or 'nominal' (default: the scenario's, e.g. one written by calibrate)."),
    pass_file: Optional[Path] = typer.Option(None, "--pass", help="Pass file (needed when SCENARIO_DIR/passes holds several)."),
    gcp_file: Optional[Path] = typer.Option(None, "--gcps", help="GCP database (default SCENARIO_DIR/gcp.h5)."),
    dem_file: Optional[Path] = typer.Option(None, "--dem", help="DEM tiles (default SCENARIO_DIR/dem.h5)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write RESULT.h5 (error models, landmarks, covariances, residuals)."),
    plots: Optional[Path] = typer.Option(None, "--plots", help="Write PNG plots here (needs --out)."),
    pitch_spacing: float = typer.Option(60.0, "--pitch-knots-s", help="Pitch knot spacing (s)."),
    rollyaw_spacing: float = typer.Option(60.0, "--roll-yaw-knots-s", help="Roll and yaw knot spacing (s); the seed used 120 s, see docs/conventions.md."),
    threshold1: int = typer.Option(1, "--threshold1", help="Eq. 28: minimum observations per knot support (the seed suggests ~20; see docs/conventions.md)."),
    threshold2: int = typer.Option(1, "--threshold2", help="Eq. 29: minimum cameras per knot support (the seed suggests 3)."),
    knot_rule: str = typer.Option("support", "--knot-rule", help="Eqs. 28-29 on each knot's support (default) or, literally, on [t_i, t_i+1) ('interval'); with --knot-prior independent only."),
    knot_prior: str = typer.Option("process", "--knot-prior", help="'process': consecutive knots tied by the attitude error process, every knot kept (default); 'independent': the seed's independent knot priors with eqs. 28-29's knot removal."),
    knot_damping: float = typer.Option(ATTITUDE_DAMPING, "--knot-damping", help="Damping ratio of the process knot prior (1: Matern-3/2; the default fits an attitude error with periods of 200-2000 s, see docs/conventions.md)."),
    no_dem: bool = typer.Option(False, "--no-dem", help="Leave out the DEM height factors."),
    dem_sigma_scale: float = typer.Option(1.0, "--dem-sigma-scale", help="The DEM height factors' sigma is the DEM's stated sigma times this (1: as stated; it was 2 until 2026-11-26, see docs/design.md)."),
    dem_smoothing: float = typer.Option(1.0, "--dem-smoothing", help="1 sigma (DEM postings, 0-2) of the Gaussian low-pass of the DEM the height factors read (0: the raw DEM); removes posting-level roughness that makes the DEM term non-quadratic, see docs/design.md."),
    robust: str = typer.Option("cauchy", "--robust", help="Loss of the first (blunder-finding) solve: cauchy, huber or none."),
    max_iterations: int = typer.Option(100, "--max-iterations", help="Levenberg-Marquardt iterations per solve."),
    snooping_rounds: int = typer.Option(4, "--snooping-rounds", help="Rounds of iterated data snooping (Baarda, alpha 0.001) after the least-squares solve; 0: off."),
    drop_rejected: bool = typer.Option(False, "--drop-rejected-tie-points", help="Drop a tie point whole when any of its observations is rejected (robust screen or snooping): its other rays were selected by the same test; see docs/design.md."),
    variance_components: int = typer.Option(0, "--variance-components", help="Rounds of variance-component estimation (tie-point and GCP sigmas rescaled by their sigma0); 0: keep the stated sigmas."),
    jitter_arcsec: float = typer.Option(1.0, "--jitter-arcsec", help="1 sigma (arcsec, per angle) of the GN&C's attitude jitter; the part the knots cannot follow (0.86 of it with 60 s knots) is noise in every image observation (added to its line and sample sigma through its pointing sensitivity) and in every geolocation sigma derived from the adjustment. 0: none."),
    no_jitter_weights: bool = typer.Option(False, "--no-jitter-in-weights", help="Weight the image observations by the matcher's sigma alone (the unresolved jitter still enters the geolocation sigmas)."),
    jitter_periods: str = typer.Option("8,120", "--jitter-periods-s", help="The jitter's periods (s), MIN,MAX, equal power per log-period."),
    once_per_rev: float = typer.Option(0.0, "--ephemeris-once-per-rev-m", help="1 sigma amplitude (m, per orbital axis) of a once-per-revolution ephemeris error; the ephemeris segments then get one joint prior, the covariance of their fit to an offset, a drift and the term (see docs/conventions.md). 0: none."),
    eph_segments: int = typer.Option(1, "--ephemeris-segments", help="Eq. 19 segments over the pass (1 or 2 with --ephemeris-once-per-rev-m; 2 follow the term's curvature over a long pass)."),
    accept_unconverged: bool = typer.Option(False, "--accept-unconverged", help="Keep the result of a solve that did not converge (flagged in the summary and RESULT.h5) instead of failing with exit 1."),
    observations: str = typer.Option("simulated", "--observations", help="simulated (the pass's observations) or matched (those 'misrgraph match' measured in the imagery)."),
    tie_height: str = typer.Option("auto", "--tie-height-sigma-m", help="1 sigma (m) of the height error a matched tie point's rays share (relief under the template), added to each tie point's covariance along An's ray: 'auto' estimates it from the pass's DEM residuals for matched tie points and leaves it out for simulated ones; 'estimate' always estimates it; a number fixes it (0: off). See docs/conventions.md."),
    tie_offset: str = typer.Option("auto", "--tie-offset-sigma-px", help="1 sigma (px) of the offset a matched tie point's conjugates share (they all match An's template), its effect added to each tie point's covariance: 'auto' takes what 'misrgraph match' measured for the pass and leaves it out for simulated tie points; a number fixes it (0: off). See docs/design.md."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Simultaneous bundle adjustment of one pass: ephemeris and attitude error models with covariances."""
    from misrgraph.estimate.adjust import AdjustConfig
    from misrgraph.runs.adjust import run_adjust

    try:
        periods = tuple(float(x) for x in jitter_periods.split(","))
    except ValueError:
        _fail(f"--jitter-periods-s: got {jitter_periods!r}; expected two periods in s, MIN,MAX (e.g. 8,120)")
    def mode_or_sigma(option: str, value: str, modes: tuple[str, ...], unit: str) -> float | str:
        """A named setting of the option, or its 1 sigma as a number (a clear error otherwise)."""
        if value in modes:
            return value
        try:
            return float(value)
        except ValueError:
            _fail(f"{option}: got {value!r}; expected {', '.join(modes)} or a 1 sigma in {unit} (0: off)")
            raise  # _fail exits

    tie_height_setting = mode_or_sigma("--tie-height-sigma-m", tie_height, ("auto", "estimate"), "m")
    tie_offset_setting = mode_or_sigma("--tie-offset-sigma-px", tie_offset, ("auto",), "px")
    cfg = AdjustConfig.from_dict(dict(knot_spacing_s=(rollyaw_spacing, pitch_spacing, rollyaw_spacing),
                                      threshold1=threshold1, threshold2=threshold2, knot_rule=knot_rule,
                                      knot_prior=knot_prior, knot_prior_damping=knot_damping, use_dem=not no_dem,
                                      dem_sigma_scale=dem_sigma_scale, dem_smoothing_postings=dem_smoothing,
                                      robust=robust, max_iterations=max_iterations,
                                      snooping_rounds=snooping_rounds, variance_component_rounds=variance_components,
                                      drop_rejected_tie_points=drop_rejected, accept_unconverged=accept_unconverged,
                                      attitude_jitter_arcsec=jitter_arcsec, attitude_jitter_periods_s=periods,
                                      jitter_in_weights=not no_jitter_weights,
                                      ephemeris_once_per_rev_m=once_per_rev, ephemeris_segments=eph_segments,
                                      tie_height_sigma_m=tie_height_setting, tie_offset_sigma_px=tie_offset_setting))
    with err_console.status("adjusting...") as st:
        summary = run_adjust(scenario_dir, camera_model, pass_file, gcp_file, dem_file, out, cfg,
                             progress=lambda s: st.update(s), observations=observations)
    if plots is not None:
        if out is None:
            _fail("--plots: needs --out RESULT.h5 (the plots are drawn from it)")
        from misrgraph.viz.plots import plot_adjustment

        plot_adjustment(out, plots)
    if as_json:
        _print_json(summary)
        return
    _print_adjust_summary(summary)


@app.command("tie-height")
@handle_errors
def tie_height(
    results: list[Path] = typer.Argument(..., help="RESULT.h5 files of 'adjust --observations matched --out', one per pass."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
) -> None:
    """Pool the matched tie points' shared height error over passes (each result's own estimate): on a short pass one estimate is as uncertain as the variance itself; the pooled 1 sigma is the value to fix with 'adjust --tie-height-sigma-m' (docs/conventions.md)."""
    from misrgraph.runs.adjust import run_tie_height_pool

    res = run_tie_height_pool(results)
    if as_json:
        _print_json(res)
        return
    console.print(f"tie points' shared height error, pooled over {res['passes']} passes ({res['dem_factors']} DEM factors): "
                  f"[bold]{res['sigma_m']:.1f} m[/bold] (variance {res['unclipped_variance_m2']:.0f} "
                  f"± {res['standard_error_m2']:.0f} m², 1 sigma from the passes' scatter)", soft_wrap=True)
    for path, why in res["skipped"].items():
        console.print(f"  skipped {path}: {why}", soft_wrap=True, markup=False, highlight=False)
    console.print(f"fix it with: misrgraph adjust ... --observations matched --tie-height-sigma-m {res['sigma_m']:.1f}",
                  soft_wrap=True, highlight=False)


@app.command()
@handle_errors
def match(
    scenario_dir: Path = typer.Argument(..., help="Scenario directory with imagery (misrgraph simulate --imagery)."),
    pass_file: Optional[Path] = typer.Option(None, "--pass", help="Match only this pass file (default: every pass with imagery)."),
    search: Optional[int] = typer.Option(None, "--search-px", help="Search range (px) each side of the predicted position; it must cover the navigation's 3-sigma error (default: the range the windows were rendered for)."),
    min_cameras: int = typer.Option(3, "--min-cameras", help="Keep a tie point matched in at least this many cameras (An included)."),
    config: Optional[Path] = typer.Option(None, "--config", help="JSON file of MatchConfig fields (overrides the options)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Measure GCPs (chip NCC + least-squares matching) and tie points (An interest points matched in the other cameras) in the imagery; write them into each pass file beside the simulated observations."""
    from misrgraph.match.pipeline import MatchConfig
    from misrgraph.runs.match import run_match

    fields: dict[str, Any] = dict(search_px=search, min_cameras=min_cameras)
    _merge_config(fields, config)
    cfg = MatchConfig.from_dict(fields)
    with err_console.status("matching...") as st:
        res = run_match(scenario_dir, cfg, pass_file, progress=lambda s: st.update(s))
    out = {k: v for k, v in res.items() if k != "passes"}
    if as_json:
        _print_json(out)
        return
    t = Table(title=f"matching in {scenario_dir}")
    for col in ("kind", "candidates", "matched", "error RMS (px)", "error p95 (px)", "error / sigma RMS",
                "error / sigma RMS, correct matches", "wrong", "s"):
        t.add_column(col, justify="right")
    for kind in ("gcp", "tie"):
        v = out[kind]
        e = v.get("error_px") or {}
        fmt = (lambda x: f"{x:.3f}" if isinstance(x, float) else "-")
        t.add_row(kind, str(v["candidates"]), str(v["matched"]), fmt(e.get("rms")), fmt(e.get("p95")),
                  fmt(v.get("normalised_error_rms")), fmt(v.get("normalised_error_rms_correct")),
                  str(v.get("wrong_matches", "-")), f"{v['seconds']:.1f}")
    console.print(t)
    for p in res["passes"]:
        scales = (p.get("tie") or {}).get("sigma_scale")
        if scales:
            console.print(f"{p['pass_id']} tie sigma scale (redundancy): " + ", ".join(
                f"{c} {v['scale']:.2f} ({v['redundancy']:.0f}"
                + ("" if v["estimated"] else f", {v['scale_from']}'s" if "scale_from" in v else ", LSM sigma kept") + ")"
                for c, v in scales.items()), soft_wrap=True, highlight=False)
        g = (p.get("gcp") or {}).get("sigma_scale")
        if g:
            console.print(f"{p['pass_id']} GCP sigma scale (redundancy): {g['scale']:.2f} ({g['redundancy']:.0f}"
                          + ("" if g["estimated"] else ", LSM sigma kept") + ")", soft_wrap=True, highlight=False)


def _print_adjust_summary(s: dict) -> None:
    console.print(f"pass {s['pass_id']}: {s['observations']} observations, {s['landmarks']} landmarks, "
                  f"{s['iterations']} iterations ({s['solver_status'].replace('_', ' ')}), cost {s['final_cost']:.1f}, "
                  f"{s['seconds']:.1f} s")
    console.print("knots kept/removed: " + ", ".join(f"{a} {v['kept']}/{v['removed']}" for a, v in s["knots"].items()))
    rej = s["rejected_observations"]
    console.print(f"rejected observations: {rej['count']}" + (f" (all in {rej['full_list']})" if rej["full_list"] else ""))
    for d in s.get("diagnostics", []):
        console.print(f"[yellow]note:[/] {d}")
    th = s.get("tie_height", {})
    if th.get("source") == "estimated":
        console.print(f"tie points' shared height error (template relief, from {th['dem_factors']} DEM residuals): "
                      f"{th['sigma_m']:.1f} m (variance {th['unclipped_variance_m2']:.0f} +- {th['standard_error_m2']:.0f} m^2), "
                      "added to their covariance along An's ray")
    elif th.get("source") == "fixed":
        console.print(f"tie points' shared height error: {th['sigma_m']:.1f} m (fixed), added to their covariance along An's ray")
    to = s.get("tie_offset", {})
    if to.get("source") in ("matched", "fixed"):
        console.print(f"offset shared by a tie point's conjugates: {to['sigma_px']:.3f} px "
                      f"({'measured by the matcher' if to['source'] == 'matched' else 'fixed'}), its effect added to "
                      f"{to.get('tie_points', 0)} tie points' covariance")
    if "checkpoint_geolocation_m" in s:
        t = Table(title="check points: ground error (m) with supplied -> corrected navigation")
        for col in ("camera", "before mean", "before std", "after mean", "after std", "ratio", "co-reg vs An (px)"):
            t.add_column(col, justify="right")
        for cam, v in s["checkpoint_geolocation_m"].items():
            t.add_row(cam, f"{v['before']['mean']:.1f}", f"{v['before']['std']:.1f}", f"{v['after']['mean']:.1f}",
                      f"{v['after']['std']:.1f}", f"{v['ratio_before_over_after']:.1f}",
                      f"{s['coregistration_px'].get(cam, float('nan')):.3f}")
        console.print(t)
        att, obs = s["attitude_rms_arcsec"], s["attitude_rms_arcsec_observed"]
        console.print("attitude RMS error (arcsec) where observed / whole pass: "
                      + ", ".join(f"{k} {obs[k]:.2f}/{v:.2f}" for k, v in att.items())
                      + f" ({100 * s['observed_fraction_of_pass']:.0f} % of the pass observed); "
                      f"ephemeris RMS error {s['ephemeris_rms_m']:.1f} m")
        n = s["nees"]
        parts = [f"knots {n['knots']:.2f}", f"landmarks {n['landmarks']:.2f}"]
        if "landmarks_within" in n:
            parts[-1] += (f" (common to {s['landmark_split']['window_s']:.0f} s windows {n['landmarks_common']:.2f}, "
                          f"within them {n['landmarks_within']:.2f})")
        parts += [f"{name} {n[k]:.2f}" for k, name in (("camera", "camera"), ("ephemeris", "ephemeris"), ("state", "whole state"))
                  if k in n]
        console.print("NEES / dim: " + ", ".join(parts) + " (1 = honest)")


@app.command()
@handle_errors
def calibrate(
    scenario_dir: Path = typer.Argument(..., help="Scenario directory (misrgraph simulate --scenario month)."),
    camera_model: Optional[Path] = typer.Option(None, "--camera-model", help="Supplied model: HDF5, or 'preflight' (Table 1) or 'nominal'; default SCENARIO_DIR/camera_model.h5."),
    gcp_file: Optional[Path] = typer.Option(None, "--gcps", help="GCP database; default SCENARIO_DIR/gcp.h5."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write the recalibrated camera model (HDF5, with covariance)."),
    params: str = typer.Option("delta,beta,epsilon,alpha2,alpha3", "--params", help="Comma list from: delta, beta, epsilon, f, alpha0..alpha5, omega."),
    focal_prior_px: float = typer.Option(0.05, "--focal-prior-px", help="Prior of f and alpha_i (when in --params): the pre-flight focal plane known to this many pixels at the swath edge; 0: the wide post-launch prior."),
    per_band: bool = typer.Option(False, "--per-band", help="Separate corrections per camera and band."),
    temperature_bins: int = typer.Option(1, "--temperature-bins", help="Thermal calibration: split the passes into N bins of equal count by camera temperature, estimate the corrections per bin, write a temperature table and report each parameter's slope per deg C (1: one set for all temperatures)."),
    max_passes: Optional[int] = typer.Option(None, "--max-passes", help="Use only the first N passes."),
    plots: Optional[Path] = typer.Option(None, "--plots", help="Write PNG plots here."),
    max_iterations: int = typer.Option(100, "--max-iterations", help="Levenberg-Marquardt iterations per solve."),
    accept_unconverged: bool = typer.Option(False, "--accept-unconverged", help="Keep the result of a solve that did not converge (flagged) instead of failing with exit 1."),
    observations: str = typer.Option("simulated", "--observations", help="simulated (each pass's observations) or matched (those 'misrgraph match' measured in a month simulated with --imagery)."),
    variance_components: int = typer.Option(0, "--variance-components", help="Rounds of variance-component estimation: each camera's observation sigmas rescaled by its sigma0 from the redundancy numbers, and the month re-solved; the summary gives every round's sigma0 per camera. 0 (default): keep the stated sigmas."),
    jitter_arcsec: float = typer.Option(0.0, "--jitter-arcsec", help="1 sigma (arcsec, per angle) of the GN&C's attitude jitter whose unresolved part is added to every GCP observation's line and sample sigma, as adjust does (measured on 10 standard months: NEES 0.97 -> 0.94, pointing unchanged; see docs/conventions.md). 0 (default): the matcher's sigma alone."),
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
        _fail(f"--params: got {bad[0] if bad else params!r}; expected a comma list of {', '.join(CAMERA_PARAMS)}, omega")
    cfg = CalibrateConfig.from_dict(dict(params=tuple(names), per_band=per_band, estimate_omega=omega, focal_prior_px=focal_prior_px,
                                         temperature_bins=temperature_bins, max_iterations=max_iterations,
                                         accept_unconverged=accept_unconverged,
                                         variance_component_rounds=variance_components,
                                         attitude_jitter_arcsec=jitter_arcsec))
    with err_console.status("calibrating...") as st:
        s = run_calibrate(scenario_dir, camera_model, gcp_file, out, cfg, max_passes, progress=lambda m: st.update(m),
                          observations=observations)
    if plots is not None:
        from misrgraph.viz.plots import plot_calibration

        plot_calibration(s, plots)
    if as_json:
        _print_json({k: v for k, v in s.items() if k != "rejected"})
        return
    t = Table(title=f"camera calibration: {s['passes']} passes, {s['iterations']} iterations, {s['rejected_observations']['count']} observations rejected")
    t.add_column("camera")
    t.add_column("corrections (arcsec for angles) +- sigma")
    t.add_column("pointing error (px)", justify="right")
    t.add_column("sigma (px)", justify="right")
    for cam, v in s["cameras"].items():
        par = ", ".join(f"{k} {v_['value'] / 4.8481e-6:.1f}+-{v_['sigma'] / 4.8481e-6:.1f}" if k.split(".")[-1] in ("delta", "beta", "epsilon")
                        else f"{k} {v_['value']:.3g}+-{v_['sigma']:.2g}" for k, v_ in v["params"].items())
        t.add_row(cam, par, f"{v.get('pointing_error_px', float('nan')):.3f}", f"{v['sigma_px']:.3f}")
    console.print(t)
    if "max_pointing_error_px" in s:
        console.print(f"max pointing error {s['max_pointing_error_px']:.3f} px (requirement 0.125); NEES/dim {s['nees']:.2f}")
    for pd in s["poorly_determined"]:
        console.print(f"[yellow]poorly determined:[/] {pd['parameter']} (posterior sigma {pd['ratio']:.0%} of its prior)")
    if "thermal" in s:
        th = s["thermal"]
        tt = Table(title="thermal slopes per deg C (angles in arcsec) over bins at "
                         + ", ".join(f"{x:.1f}" for x in th["bins_c"]) + " C")
        tt.add_column("camera")
        tt.add_column("slope +- sigma (true)")
        for cam, ps in th["slopes"].items():
            tt.add_row(cam, ", ".join(
                f"{p} {e.get('slope_arcsec_per_c', e['slope_per_c']):.3g}+-{e.get('sigma_arcsec_per_c', e['sigma_per_c']):.2g}"
                + (f" ({e['true_slope_per_c'] / (4.8481e-6 if 'slope_arcsec_per_c' in e else 1):.3g})" if "true_slope_per_c" in e else "")
                for p, e in ps.items()))
        console.print(tt)
        if "nees" in th:
            console.print(f"thermal slopes NEES/dim {th['nees']:.2f} over {th['nees_dim']}")


@app.command()
@handle_errors
def update(
    state: Path = typer.Argument(..., help="State directory (created on first use)."),
    passes: Optional[list[Path]] = typer.Argument(None, help="New pass files (HDF5) to add, in order."),
    camera_model: Optional[Path] = typer.Option(None, "--camera-model", help="Camera model HDF5, or 'preflight' / 'nominal' (needed when creating the state)."),
    gcp_file: Optional[Path] = typer.Option(None, "--gcps", help="GCP database (needed when creating the state)."),
    dem_file: Optional[Path] = typer.Option(None, "--dem", help="DEM tiles (recommended when creating the state)."),
    compare_batch: bool = typer.Option(False, "--compare-batch", help="Also re-solve all passes in batch and report the cost ratio and the difference in sigma."),
    report: Optional[str] = typer.Option(None, "--report", help="Also report error models, marginals and scores of this earlier pass id."),
    linearization_tol: Optional[float] = typer.Option(None, "--linearization-tol", min=1e-6,
                                                      help="Re-linearise until the linear model's error is at most this many sigma "
                                                           "(smaller: closer to the optimum, slower) [default: misrgraph.estimate.incremental.DEFAULT_LINEARIZATION_TOL]."),
    observations: Optional[str] = typer.Option(None, "--observations", help="simulated (each pass's observations) or matched (those 'misrgraph match' measured in its imagery, the tie points' height and offset terms in their covariance as in adjust): fixed when the state is created [default: simulated]; a later update may repeat it, not change it."),
    as_json: bool = typer.Option(False, "--json", help="Print the summaries as JSON."),
) -> None:
    """Add passes to a persistent state and re-solve incrementally with iSAM2 (crash- and restart-safe)."""
    import numpy as np

    from misrgraph.runs.update import run_update

    with err_console.status("updating...") as st:
        if not passes and report is None:
            _fail("PASSES: give new pass files to add, or --report PASS_ID for an earlier pass")
        out = run_update(state, [str(p) for p in passes or []], camera_model, gcp_file, dem_file,
                         compare_batch=compare_batch, progress=lambda m: st.update(m), report=report,
                         linearization_tol=linearization_tol, observations=observations)  # None: the library default
    if as_json:
        _print_json(out)
        return
    console.print(f"state {out['state']}: {out['passes_in_state']} passes ({out['observation_set']} observations)")
    if "report" in out:
        r = out["report"]
        console.print(f"{r['pass_id']}: knots kept/removed " + ", ".join(f"{a} {v['kept']}/{v['removed']}" for a, v in r["knots"].items())
                      + "; mean knot sigma (arcsec) " + ", ".join(f"{a} {np.mean(v):.2f}" for a, v in r["attitude_knot_sigma_arcsec"].items()))
    for u in out["updates"]:
        if u["status"] != "added":
            console.print(f"{u['pass_id']}: {u['status']}")
            continue
        line = (f"{u['pass_id']}: added in {u['update_seconds']:.2f} s ({u['relinearization_rounds']} re-linearisation rounds)")
        if "batch" in u:
            b = u["batch"]
            line += f"; batch re-solve {b['seconds']:.2f} s (update/batch {b['ratio_update_over_batch']:.2f}), max difference {b['max_difference_in_sigma']:.1e} sigma"
        console.print(line)
        th, to = u["tie_height"], u["tie_offset"]
        if th["source"] != "off" or to["source"] != "off":
            console.print(f"   tie points: shared height error {th['sigma_m']:.1f} m ({th['source']}), conjugates' shared offset "
                          f"{to['sigma_px']:.3f} px ({to['source']}), both in their covariance")
        if "nees" in u:
            console.print(f"   NEES/dim knots {u['nees']['knots']:.2f}, landmarks {u['nees']['landmarks']:.2f}; "
                          "attitude RMS where observed (arcsec) " + ", ".join(f"{k} {v:.1f}" for k, v in u["attitude_rms_arcsec_observed"].items()))


@app.command()
@handle_errors
def view(
    result: Path = typer.Argument(..., help="RESULT.h5 from adjust, or a camera model written by calibrate."),
    save: Optional[Path] = typer.Option(None, "--save", help="Write a .rrd recording."),
    spawn: bool = typer.Option(False, "--spawn", help="Open the rerun viewer."),
    exaggeration: float = typer.Option(200.0, "--exaggeration", help="Scale of the 3-sigma landmark ellipsoids."),
) -> None:
    """Inspect covariances and residuals in the rerun viewer (entity paths: see misrgraph.viz.viewer)."""
    from misrgraph.viz.viewer import run_view

    out = run_view(result, save, spawn, exaggeration)
    console.print(f"logged {len(out['entities'])} entities ({out['kind']})" + (f" to {out['rrd']}" if out["rrd"] else ""))


CAMPAIGN_HELP = """The calibration campaign as one command, on Dask: calibrate the cameras on a GCP month, adjust the chosen repeat passes of each path with the calibrated model, build each path's incremental state and Projection Parameters, and write a report (OUT/report/campaign.md) and OUT/summary.json.

Inputs are simulated into OUT/inputs unless --inputs names scenario directories (month/ and path_PPP/). Tasks run on a LocalCluster of --workers processes (default: one per core), on the cluster at --scheduler (its workers must see OUT at the same path), or with --workers 0 in this process without Dask. Rerun the same command to resume: every output is named by a digest of its inputs and written atomically, so nothing done is redone and nothing is counted twice. Exit status 1 when any task failed (each failure is reported with its reason; none stops the others)."""


@app.command(help=CAMPAIGN_HELP)
@handle_errors
def campaign(
    out: Path = typer.Option(..., "--out", help="Campaign directory (created; rerun into it to resume)."),
    months: float = typer.Option(6.0, "--months", help="Months of data after the epoch (a path repeats every 16 days)."),
    fraction: float = typer.Option(0.3, "--fraction", help="Fraction of each path's repeat passes adjusted."),
    paths: Optional[str] = typer.Option(None, "--paths", help="Paths, comma-separated or ranges (37,38 or 30-33); default all 233."),
    passes_per_path: int = typer.Option(4, "--passes-per-path", help="At least this many passes per path (if the period has them)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="LocalCluster worker processes (default: cores; 0: this process, no Dask)."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Address of a running Dask scheduler, tcp://HOST:PORT."),
    inputs: Optional[Path] = typer.Option(None, "--inputs", help="Existing scenarios: a directory with month/ and path_PPP/ (default: simulate)."),
    size: str = typer.Option("standard", "--size", help="Simulated scenario size: standard (45-minute passes, 600 tie points) or reduced."),
    truth: str = typer.Option("independent", "--truth", help="Simulator truth: independent or model (see misrgraph simulate --help)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the simulated inputs."),
    pp_blocks: int = typer.Option(0, "--pp-blocks", help="SOM blocks of each path's PP (0: 10 standard, 2 reduced)."),
    no_products: bool = typer.Option(False, "--no-products", help="Skip the per-path state and products."),
    roi: bool = typer.Option(False, "--roi", help="Build each path's Reference Orbit Imagery from its state (inputs with "
                                                  "whole-swath strips and a SOM DEM; simulated ones get them, ~80 s a block and pass)."),
    roi_blocks: int = typer.Option(1, "--roi-blocks", help="Blocks of strips a simulated path gets with --roi, from the one under mid-pass."),
    observations: str = typer.Option("simulated", "--observations", help="simulated (each pass's own) or matched (measured in the imagery by 'misrgraph match': simulated inputs then get imagery and are matched, brought ones must have been) for the calibration, the adjustments and the path states."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.campaign.plan import CampaignConfig
    from misrgraph.campaign.run import run_campaign
    from misrgraph.campaign.plan import parse_paths

    if workers is not None and scheduler is not None:
        _fail("--workers and --scheduler: give one (--workers starts a local cluster, --scheduler uses yours)")
    cfg = CampaignConfig.from_dict(dict(months=months, fraction=fraction, paths=parse_paths(paths) if paths else (),
                                        passes_per_path=passes_per_path, size=size, truth=truth, seed=seed,
                                        pp_blocks=pp_blocks, products=not no_products, roi=roi, roi_blocks=roi_blocks,
                                        observations=observations))
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=err_console, disable=as_json) as bar:
        task = bar.add_task("campaign: starting", total=None)

        def progress(done: int, total: int, message: str) -> None:
            if message.startswith("Dask dashboard"):
                bar.console.print(message)
            bar.update(task, description=message, completed=done, total=total)

        res = run_campaign(out, cfg, inputs=inputs, workers=workers, scheduler=scheduler, progress=progress)
    if as_json:
        _print_json(res)
    else:
        p = res["passes"]
        console.print(f"{p['done']}/{p['planned']} passes adjusted ({p['failed']} failed) in {res['seconds']:.0f} s "
                      f"on {res['cluster'].get('kind')}; report: {res['report']}")
        cal = res["calibration"]
        if cal.get("status") == "done" and cal.get("max_pointing_error_px") is not None:
            console.print(f"calibration: largest pointing error {cal['max_pointing_error_px']:.3f} px -> {cal['file']}")
        table = Table(title="per path")
        for col in ("path", "passes", "check-point RMS (m)", "co-registration max (px)", "PP error RMS (m)", "ROI co-registration (px)"):
            table.add_column(col, justify="right")
        fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
        for path_, v in res["paths"].items():
            table.add_row(path_, f"{v['passes']['done']}/{v['passes']['planned']}", fmt(v["checkpoint_rms_m"], ".1f"),
                          fmt(v["coregistration_px_max"], ".3f"), fmt((v.get("products") or {}).get("pp_error_rms_m"), ".1f"),
                          fmt(((v.get("products") or {}).get("roi") or {}).get("coregistration_px_max"), ".2f"))
        console.print(table)
        for f in res["failed"]:
            err_console.print(f"failed: {f['stage']} {f['name']}: {f['reason']}", markup=False)
    if res["failed"]:
        raise typer.Exit(1)


@app.command()
@handle_errors
def products(
    scenario_dir: Path = typer.Argument(..., help="A scenario directory (misrgraph simulate), or an update state "
                                                   "(misrgraph update; PP of its passes from the current estimate)."),
    out: Path = typer.Option(..., "--out", help="Output directory for PP_<pass id>.h5 and products.json."),
    blocks: Optional[str] = typer.Option(None, "--blocks", help="SOM blocks A-B (inclusive, 1..180); default 10 around the pass's features."),
    pass_file: Optional[Path] = typer.Option(None, "--pass", help="The pass (default: the scenario's first)."),
    camera_model: Optional[Path] = typer.Option(None, "--camera-model", help="Camera model (default: the scenario's camera_model.h5)."),
    band: str = typer.Option("red", "--band", help="blue, green, red or nir."),
    roi: bool = typer.Option(False, "--roi", help="Also build the Reference Orbit Imagery from every pass with whole-swath strips (at least 4): ROI_P<path>.h5 on the 275 m SOM grid, the clearest pass per block, a per-pixel source map, co-registration measured on it."),
    geotiff: bool = typer.Option(False, "--geotiff", help="With --roi: one Cloud-Optimised GeoTIFF per camera in the path's misrsom CRS."),
    quicklooks: bool = typer.Option(False, "--quicklooks", help="With --roi: one quick-look PNG per camera."),
    som_dem: Optional[Path] = typer.Option(None, "--som-dem", help="With --roi: heights on the path's 275 m SOM grid (default: the scenario's dem_som.h5)."),
    coreg_points: int = typer.Option(64, "--coreg-points", help="With --roi: co-registration matches per image pair and block (0: not measured)."),
    observations: str = typer.Option("simulated", "--observations", help="simulated (the pass's own) or matched (those 'misrgraph match' measured) for the scenario's adjustment; a state adjusts its own set."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Projection Parameters of an adjusted pass on its path's 1.1 km SOM grid, with their 1 sigma
    (the pass is adjusted on the way; from an update state, every pass of the state from its
    current estimate); scored against the simulator's truth when the pass has it. With --roi, the
    Reference Orbit Imagery of the path from all passes with imagery."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.runs.products import run_products

    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=err_console,
                  disable=as_json) as bar:
        task = bar.add_task("products", total=None)

        def progress(desc: str, k: int, n: int) -> None:
            bar.update(task, description=desc, completed=k, total=max(n, 1))

        from misrgraph.runs.products import RoiOptions

        if not roi and (geotiff or quicklooks or som_dem):
            raise InputError("--geotiff/--quicklooks/--som-dem", "given without --roi", "--roi as well")
        opts = RoiOptions(som_dem=str(som_dem) if som_dem else None, geotiff=geotiff, quicklooks=quicklooks,
                          coregistration_points=coreg_points) if roi else None
        res = run_products(scenario_dir, out, blocks=blocks, pass_file=pass_file, camera_model=camera_model,
                           band=band, progress=progress, roi=roi, roi_options=opts, observations=observations)
    if as_json:
        _print_json(res)
        return
    for one in res.get("passes", [res]):
        console.print(f"PP of pass {one['pass_id']}, path {res['path']}, blocks {res['blocks'][0]}-{res['blocks'][1]} "
                      f"-> {one['files']['pp']}")
        table = Table(title="geolocation of the PP (m)")
        for col in ("camera", "seen", "median 1 sigma", "RMS vs truth", "predicted RMS", "NEES"):
            table.add_column(col, justify="right")
        err = one.get("pp_error_m", {})
        for cam, frac in one["fraction_seen"].items():
            e = err.get(cam, {})
            sig = one["sigma_m_median"][cam]
            table.add_row(cam, f"{frac:.0%}", "-" if sig is None else f"{sig:.1f}",
                          *([f"{e['rms']:.1f}", f"{e['predicted_rms']:.1f}", f"{e['nees']:.2f}"] if e else ["-"] * 3))
        console.print(table)
    if res.get("roi"):
        _print_coregistration(f"Reference Orbit Imagery -> {res['roi']['file']}: co-registration (px)", res["roi"]["cameras"],
                              res["roi_coregistration_px"], res.get("roi_truth", {}), res.get("roi_predicted_px"))
    console.print(f"{res['seconds']['total']:.0f} s")


def _print_coregistration(title: str, cameras: list[str], matched: dict[str, float], truth: dict[str, dict[str, float]],
                          predicted: dict[str, dict[str, float]] | None = None) -> None:
    """The ROI's co-registration per camera (pixels, worst block): matched on the ROI (beyond
    matching noise, a block's pairs pooled), what the adjustment's own uncertainty allows and,
    when simulated, the truth against An and between passes (pooled as the matches are) and of
    the worst single pair of images."""
    table = Table(title=title)
    for col in ("camera", "matched, beyond noise", "allowed: vs An", "allowed: between passes", "truth: vs An",
                "truth: between passes", "truth: worst pair"):
        table.add_column(col, justify="right")
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    predicted = predicted or {}
    for cam in cameras:
        worst = [v for k in ("between_cameras_px", "between_passes_px") if (v := truth.get(k, {}).get(cam)) is not None]
        table.add_row(cam, fmt(matched.get(cam)), fmt(predicted.get(cam, {}).get("vs_An")),
                      fmt(predicted.get(cam, {}).get("between_passes")),
                      fmt(truth.get("between_cameras_pooled_px", {}).get(cam)),
                      fmt(truth.get("between_passes_pooled_px", {}).get(cam)), fmt(max(worst) if worst else None))
    console.print(table)


som_app = typer.Typer(help="MISR space: a path's SOM grid and blocks, and orbit <-> path <-> time.", no_args_is_help=True)
app.add_typer(som_app, name="som")


@som_app.command("convert")
@handle_errors
def som_convert(
    path: int = typer.Option(..., "--path", help="MISR/WRS-2 path, 1..233."),
    resolution: int = typer.Option(1100, "--resolution", help="Grid resolution (m): 275 or 1100 (also 2200, 4400, 8800, 17600)."),
    block: Optional[int] = typer.Option(None, "--block", help="Block, 1..180 (with --line and --sample)."),
    line: Optional[float] = typer.Option(None, "--line", help="Fractional line in the block (-0.5 is the edge of the first pixel)."),
    sample: Optional[float] = typer.Option(None, "--sample", help="Fractional sample in the block."),
    lat: Optional[float] = typer.Option(None, "--lat", help="Geodetic WGS84 latitude (deg), with --lon."),
    lon: Optional[float] = typer.Option(None, "--lon", help="Longitude (deg), with --lat."),
    som_x: Optional[float] = typer.Option(None, "--som-x", help="SOM x (m, along the path), with --som-y."),
    som_y: Optional[float] = typer.Option(None, "--som-y", help="SOM y (m, across the path), with --som-x."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Print one point as block/line/sample, lat/lon and SOM x/y, given any one of them."""
    from misrgraph.runs.som import run_som_convert

    res = run_som_convert(path, resolution, block=block, line=line, sample=sample, lat=lat, lon=lon, som_x=som_x, som_y=som_y)
    if as_json:
        _print_json(res)
        return
    table = Table(title=f"path {res['path']}, {res['resolution_m']} m", show_header=False)
    for k in ("block", "line", "sample", "lat", "lon", "som_x", "som_y"):
        v = res[k]
        table.add_row(k, "off the grid" if v is None else (f"{v:.6f}" if isinstance(v, float) else str(v)))
    console.print(table)


@som_app.command("orbit")
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
        _print_json(res)
        return
    console.print(f"orbit {res['orbit']}  path {res['path']}  {res['start']} .. {res['end']}")


import_app = typer.Typer(help="Real inputs: GCP lists (CSV, GeoJSON) and DEM rasters (any GDAL raster) into misrgraph's files.",
                         no_args_is_help=True)
app.add_typer(import_app, name="import")


@import_app.command("gcps")
@handle_errors
def import_gcps(
    source: Path = typer.Argument(..., help="GCP list: .csv (header row) or .geojson (Point features)."),
    out: Path = typer.Option(..., "--out", help="GCP database to write (HDF5), e.g. SCENARIO_DIR/gcp.h5."),
    sigma_m: Optional[float] = typer.Option(None, "--sigma-m", help="1-sigma (m, every ENU axis) where the list has no sigma column."),
    geoid: Optional[Path] = typer.Option(None, "--geoid", help="Geoid grid raster (e.g. us_nga_egm96_15.tif) for heights above the geoid."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Import a GCP list with its sigmas (columns: lat, lon, height [m ellipsoidal] or height_msl,
    sigma_m or sigma_h_m + sigma_v_m or sigma_e_m + sigma_n_m + sigma_u_m, optional id, region)."""
    from misrgraph.runs.imports import run_import_gcps

    res = run_import_gcps(source, out, sigma_m, geoid)
    if as_json:
        _print_json(res)
        return
    console.print(f"{res['gcps']} GCPs -> {res['out']} (sigma {res['sigma_m']['min']:.3g}..{res['sigma_m']['max']:.3g} m)")


@import_app.command("dem")
@handle_errors
def import_dem(
    sources: list[Path] = typer.Argument(..., help="DEM rasters (GeoTIFF, DTED, ... any CRS), heights in metres."),
    out: Path = typer.Option(..., "--out", help="DEM file to write (HDF5), e.g. SCENARIO_DIR/dem.h5."),
    posting_arcsec: float = typer.Option(3.0, "--posting-arcsec", help="Posting of the geographic grid (arc seconds)."),
    tile_postings: int = typer.Option(1201, "--tile-postings", help="Postings per tile side (>= 32)."),
    quality: int = typer.Option(1, "--quality", help="Accuracy class: 1 (30 m), 2 (60 m), 3 (120 m) 1-sigma."),
    geoid: Optional[Path] = typer.Option(None, "--geoid", help="Geoid grid raster; heights above it become ellipsoidal."),
    as_json: bool = typer.Option(False, "--json", help="Print JSON."),
) -> None:
    """Import DEM rasters as square geographic tiles (bilinear onto the posting grid)."""
    from misrgraph.runs.imports import run_import_dem

    res = run_import_dem(sources, out, posting_arcsec, tile_postings, quality, geoid)
    if as_json:
        _print_json(res)
        return
    console.print(f"{res['tiles']} tiles of {res['tile_postings']} postings -> {res['out']} "
                  f"(heights {res['height_m']['min']:.0f}..{res['height_m']['max']:.0f} m, {res['height_reference']})")


bench_app = typer.Typer(help="Speed and memory, as ratios against a baseline run in the same process.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")


@bench_app.command("solver")
@handle_errors
def bench_solver(
    tie_points: int = typer.Option(1000, "--tie-points", help="Tie points in the simulated pass."),
    seed: int = typer.Option(0, "--seed"),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep/reuse simulated scenarios here."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Solver core vs gtsam.LevenbergMarquardtOptimizer on the same graph (per linearisation, per iteration)."""
    from misrgraph.bench.studies import run_bench_solver

    if tie_points < 10:
        _fail(f"--tie-points: got {tie_points}; expected at least 10")
    with err_console.status("simulating and solving (gtsam LM is the slow part)..."):
        res = run_bench_solver(tie_points, seed, workdir)
    if as_json:
        _print_json(res)
        return
    t = Table(title=f"bench solver: {res['variables']} variables, {res['factors']} factors, {res['observations']} observations")
    for col in ("solver", "seconds", "iterations", "s / iteration", "final cost"):
        t.add_column(col)
    for name in ("core", "gtsam_lm"):
        r = res[name]
        t.add_row(name, f"{r['seconds']:.2f}", str(r["iterations"]), f"{r['seconds_per_iteration']:.3f}", f"{r['final_cost']:.6f}")
    console.print(t)
    console.print(f"gtsam_lm / core = {res['ratio_gtsam_lm_over_core']:.1f}x; linearisation (s): "
                  + ", ".join(f"{k} {v:.3f}" for k, v in res["linearize_seconds"].items()))


@bench_app.command("calibration")
@handle_errors
def bench_calibration(
    size: str = typer.Option("standard", "--size", help="standard (120 GCPs, 30 days) or reduced (24 GCPs, 16 days)."),
    seed: int = typer.Option(3, "--seed"),
    repeat: int = typer.Option(3, "--repeat", help="Timings are the best of this many runs."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep/reuse the simulated month here."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """A month calibration's linear algebra: the LM step by the former (landmarks-first) and the
    current (COLAMD, cameras last) ordering, the cameras' covariance by SuperLU's unsymmetric LU
    and by its symmetric mode; seconds, ratios and the differences of the results."""
    from misrgraph.bench.calibration import run_bench_calibration

    with err_console.status(f"simulating (or reusing) the {size} month and linearising it..."):
        res = run_bench_calibration(size, seed, workdir, repeat)
    if as_json:
        _print_json(res)
        return
    t = Table(title=f"bench calibration: {res['size']} month, {res['passes']} passes, {res['variables']} variables "
                    f"({res['landmarks']} GCP landmarks, {res['cameras']} cameras)")
    for col in ("part", "former", "s", "current", "s", "former / current", "relative difference"):
        t.add_column(col)
    for part in ("step", "camera_covariance"):
        r = res[part]
        t.add_row(part.replace("_", " "), r["former"], f"{r['former_s']:.3f}", r["current"], f"{r['current_s']:.3f}",
                  f"{r['ratio']:.1f}x", f"{r['relative_difference']:.1e}")
    console.print(t)


@bench_app.command("sba")
@handle_errors
def bench_sba(
    tie_points: int = typer.Option(2000, "--tie-points", min=20),
    seed: int = typer.Option(0, "--seed"),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep/reuse simulated scenarios here."),
    skip: str = typer.Option("", "--skip", help="Comma list of solvers to leave out (names as in the table, e.g. gtsam_lm,ceres)."),
    budget_s: float = typer.Option(60.0, "--budget", help="Seconds each solver may run at most."),
    check_points: int = typer.Option(200, "--check-points", min=0, help="Check points of the simulated pass (for the products' errors)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Solvers at equal accuracy of the estimate: seconds until each is within 1, 0.3, 0.1 and 0.03 sigma of a verified optimum, and the products' errors where each stops."""
    from misrgraph.bench.accuracy import run_bench_sba

    if budget_s <= 0.0:
        _fail(f"--budget: got {budget_s}; expected a positive number of seconds")
    names = tuple(x.strip() for x in skip.split(",") if x.strip())
    with err_console.status("simulating and solving with every alternative..."):
        res = run_bench_sba(tie_points, seed, workdir, skip=names, budget_s=budget_s, check_points=check_points)
    if as_json:
        _print_json(res)
        return
    ref = res["reference"]
    t = Table(title=f"bench sba: {res['tie_points']} tie points, {res['observations']} observations, {res['unknowns']} unknowns; "
                    f"seconds until within a distance of the optimum (max over knots and ephemeris, in sigma)")
    for col in ("solver", *(f"{lv} sigma" for lv in res["sigma_levels"]), "0.1 / core", "stop: s", "max sigma",
                "check points (m)", "co-reg. (px)", "ended"):
        t.add_column(col, no_wrap=col == "solver")
    for name, r in res["solvers"].items():
        if "skipped" in r:
            t.add_row(name, *[""] * (len(res["sigma_levels"]) + 5), r["skipped"])
            continue
        st = r["stop"]
        ratio = res["ratio_to_core_at_0.1_sigma"].get(name)
        bound = ">= " if name in res["ratios_that_are_lower_bounds"] else ""
        fmt = (lambda v, f: "-" if v is None else format(v, f))
        t.add_row(name, *(fmt(v, ".2f") for v in r["seconds_to_sigma"].values()),
                  "1" if name == "misrgraph" else ("never" if ratio is None else f"{bound}{ratio:.1f}"),
                  f"{st['seconds']:.1f}", f"{st['max_sigma']:.3g}", fmt(st["checkpoint_rms_m"], ".2f"),
                  fmt(st["coregistration_px"], ".3f"), str(st["ended"])[:40])
    console.print(t)
    console.print(f"optimum: cost {ref['cost']:.3f}, Gauss-Newton step there {ref['gauss_newton_step_max_sigma']:.1e} sigma "
                  f"({'verified' if ref['verified'] else 'NOT verified'}); its check points {ref['checkpoint_rms_m']} m. "
                  f"Marginals (one routine for all): {res['marginals']['seconds']:.2f} s, not included above.")
    console.print("'-': never within that distance before its own stop or its time budget "
                  f"({res['budget_seconds']:.0f} s); '>=': the ratio is then a lower bound (its whole run).")


@bench_app.command("match")
@handle_errors
def bench_match(
    tie_points: int = typer.Option(1000, "--tie-points", min=10),
    seed: int = typer.Option(0, "--seed"),
    duration: float = typer.Option(2700.0, "--duration", help="Pass duration (s)."),
    cloud_fraction: float = typer.Option(0.0, "--cloud-fraction"),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the simulated scenarios here."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Imagery, matching and the matched adjustment on one pass: rendering cost, matching accuracy against truth, NCC+LSM vs a plain scikit-image template match on the same GCP chips, check points matched vs simulated."""
    from misrgraph.bench.match import run_bench_match

    with err_console.status("simulating with imagery, matching, adjusting..."):
        res = run_bench_match(tie_points, seed, duration, cloud_fraction, workdir=workdir)
    if as_json:
        _print_json(res)
        return
    m, g, a = res["match"], res["gcp_chips"], res["adjust"]
    for kind in ("gcp", "tie"):
        v = m[kind]
        console.print(f"{kind}: {v['matched']}/{v['candidates']} matched, error RMS {v['error_px']['rms']:.3f} px, "
                      f"error/sigma {v['normalised_error_rms']:.2f}, wrong {v['wrong_matches']}, {v['seconds']:.1f} s")
    if "ncc_lsm" in g:
        console.print(f"GCP chips: NCC+LSM {g['ncc_lsm']['error_rms_px']:.3f} px at {g['ncc_lsm']['chips_per_second']:.0f}/s; "
                      f"skimage+parabola {g['skimage_parabola']['error_rms_px']:.3f} px at "
                      f"{g['skimage_parabola']['chips_per_second']:.0f}/s")
    console.print(f"rendering {res['simulate_seconds']['rendering']:.0f} s; check points matched/simulated "
                  f"{a['checkpoint_ratio_matched_over_simulated']:.2f}, co-registration max "
                  f"{a['matched']['coregistration_px_max']:.3f} px")


@bench_app.command("scaling")
@handle_errors
def bench_scaling(
    sizes: str = typer.Option("250,500,1000,2000,4000", "--sizes", help="Comma list of tie-point counts."),
    seed: int = typer.Option(0, "--seed"),
    workdir: Optional[Path] = typer.Option(None, "--workdir"),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Time per pass against tie points, with a fitted exponent, and peak memory."""
    from misrgraph.bench.studies import run_bench_scaling

    try:
        ns = tuple(int(x) for x in sizes.split(","))
    except ValueError:
        _fail(f"--sizes: got {sizes!r}; expected comma-separated integers such as 250,500,1000")
    with err_console.status("simulating and solving..."):
        res = run_bench_scaling(ns, seed, workdir)
    if as_json:
        _print_json(res)
        return
    t = Table(title="bench scaling (Schur backend, with knot marginals)")
    for col in ("tie points", "observations", "seconds", "iterations", "s / iteration", "peak Python MB"):
        t.add_column(col)
    for r in res["rows"]:
        t.add_row(str(r["tie_points"]), str(r["observations"]), f"{r['seconds']:.2f}", str(r["iterations"]),
                  f"{r['seconds_per_iteration']:.3f}", f"{r['peak_python_mb']:.0f}")
    console.print(t)
    console.print(f"fitted exponent: per iteration vs observations {res['exponent_per_iteration_vs_observations']:.2f}, "
                  f"total vs tie points {res['exponent_total_vs_tie_points']:.2f}; peak RSS {res['process_peak_rss_mb']:.0f} MB")


@bench_app.command("incremental")
@handle_errors
def bench_incremental(
    passes: int = typer.Option(10, "--passes", min=1),
    tie_points: int = typer.Option(150, "--tie-points", min=20),
    seed: int = typer.Option(0, "--seed"),
    workdir: Optional[Path] = typer.Option(None, "--workdir"),
    linearization_tol: Optional[float] = typer.Option(None, "--linearization-tol", min=1e-6,
                                                      help="iSAM2 re-linearisation tolerance in sigma [default: the library's]."),
    settle_after: Optional[int] = typer.Option(None, "--settle-after", min=0,
                                               help="Marginalise a pass out of iSAM2 once this many newer passes have arrived; 0: never "
                                                    "[default: the library's, 3]."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Adding the k-th pass with iSAM2 against a warm-started batch re-solve of all k passes at the same accuracy, pass after pass."""
    from misrgraph.bench.accuracy import run_bench_incremental

    with err_console.status(f"simulating {passes} repeat passes and solving..."):
        kw = {} if settle_after is None else {"settle_after": settle_after or None}
        res = run_bench_incremental(passes, tie_points, seed, workdir, linearization_tol, **kw)
    if as_json:
        _print_json(res)
        return
    t = Table(title=f"bench incremental: {res['passes']} repeat passes x {res['tie_points']} tie points")
    for col in ("pass k", "iSAM2 update (s)", "warm batch, same accuracy (s)", "update / batch", "iSAM2 from optimum (sigma)", "rounds"):
        t.add_column(col)
    marks = {int(k) for k in res["at"]} | {1, res["passes"]}
    for r in res["per_pass"]:
        if r["pass"] in marks or r["pass"] % 10 == 0:
            t.add_row(str(r["pass"]), f"{r['update_seconds']:.3f}", f"{r['batch_seconds']:.3f}",
                      f"{r['update_seconds'] / r['batch_seconds']:.2f}", f"{r['max_difference_sigma']:.4f}",
                      str(r["relinearization_rounds"]))
    console.print(t)
    if res["update_last_over_update_10"] is not None:
        console.print(f"update at pass {res['passes']} / update at pass 10 = {res['update_last_over_update_10']:.2f}; ", end="")
    console.print(f"iSAM2's largest distance from the converged batch over all passes: {res['max_difference_sigma_worst']:.4f} sigma")


@bench_app.command("nees")
@handle_errors
def bench_nees(
    study: str = typer.Option("calibration", "--study", help="calibration or adjust."),
    runs: int = typer.Option(20, "--runs", help="Seeded runs."),
    seed: int = typer.Option(1000, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(None, "--workdir"),
    size: str = typer.Option("reduced", "--size", help="reduced (the test suite's size) or standard (45-minute passes with 600 tie points and check points; full months)."),
    truth: str = typer.Option("model", "--truth", help="The simulator's truth: model or independent (see misrgraph simulate --help)."),
    calibrate_params: Optional[str] = typer.Option(None, "--calibrate-params", help="Calibration study: the parameters to estimate (as calibrate --params; default delta,beta,epsilon,alpha2,alpha3)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Covariance honesty: NEES per class over seeded runs, against its 95 % chi-square band and with a 95 % interval from the run-to-run scatter."""
    from misrgraph.bench.studies import run_bench_nees

    if runs < 1:
        _fail(f"--runs: got {runs}; expected at least 1")
    with err_console.status(f"{runs} seeded {study} runs..."):
        res = run_bench_nees(study, runs, seed, workdir, size, truth,
                             calibrate_params=tuple(p.strip() for p in calibrate_params.split(",")) if calibrate_params else None)
    if as_json:
        _print_json(res)
        return
    _print_nees(res)


def _print_nees(res: dict) -> None:
    """``bench nees`` / ``bench nees-pool``: one line per class (and per camera for check points)."""
    study, truth = res["study"], res["truth"]
    if res["adjust_overrides"]:
        console.print(f"adjustment settings under the {truth} truth: {res['adjust_overrides']}")
    for k, v in res["summary"].items():
        pr = v["per_run"]
        scatter = f"mean of runs {pr['mean']:.3f}, 95 % interval [{pr['ci95'][0]:.3f}, {pr['ci95'][1]:.3f}]"
        if "nees_per_dim" not in v:
            rr = v.get("rms_of_runs")
            rms = f"; RMS of runs {rr['rms']:.3f} [{rr['ci95'][0]:.3f}, {rr['ci95'][1]:.3f}]" if rr else ""
            console.print(f"{study} {k}: {scatter}{rms}")
            for c, bc in v.get("by_camera", {}).items():
                console.print(f"    {c}: RMS of {bc['runs']} runs {bc['rms']:.3f} [{bc['ci95'][0]:.3f}, {bc['ci95'][1]:.3f}]")
            continue
        console.print(f"{study} {k}: NEES/dim {v['nees_per_dim']:.3f}, 95 % band [{v['band'][0]:.3f}, {v['band'][1]:.3f}] "
                      f"({v['dof']} dof) -> {'inside' if v['inside'] else 'OUTSIDE'}; {scatter}")


@bench_app.command("nees-pool")
@handle_errors
def bench_nees_pool(
    files: list[Path] = typer.Argument(..., help="bench nees --json outputs of the same study, size, truth and settings."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Pool several bench nees results (e.g. held-out seed sets run apart) into one study: pooled NEES/dim and its band, and intervals from the scatter of all their runs."""
    from misrgraph.bench.studies import pool_bench_nees

    results = []
    for f in files:
        try:
            results.append(json.loads(Path(f).read_text()))
        except OSError as e:
            _fail(f"FILES: {f} cannot be read ({e.strerror}); expected a bench nees --json output")
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            _fail(f"FILES: {f} is not JSON ({e}); expected a bench nees --json output")
        if not isinstance(results[-1], dict):
            _fail(f"FILES: {f} holds a {type(results[-1]).__name__}; expected a bench nees --json output (an object)")
    res = pool_bench_nees(results)
    if as_json:
        _print_json(res)
        return
    seeds = sorted(int(r["seed"]) for r in res["per_run"])
    console.print(f"pooled {res['runs']} runs from {res['pooled_from']} results ({res['study']}, {res['size']}, "
                  f"{res['truth']} truth; seeds {seeds[0]}-{seeds[-1]})")
    _print_nees(res)


@bench_app.command("pp")
@handle_errors
def bench_pp(
    runs: int = typer.Option(20, "--runs", help="Seeded passes."),
    seed: int = typer.Option(5000, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the simulated passes and PP here (reused by a rerun)."),
    size: str = typer.Option("reduced", "--size", help="reduced or standard (as bench nees --study adjust)."),
    truth: str = typer.Option("model", "--truth", help="model or independent (see misrgraph simulate --help)."),
    blocks: int = typer.Option(2, "--blocks", help="SOM blocks per pass, around its features."),
    block_range: Optional[str] = typer.Option(None, "--block-range", help="Score these blocks (A-B) in every pass instead of --blocks, and also per block."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Honesty of the Projection Parameters' 1 sigma: PP geolocation RMS against the truth over the predicted RMS, and NEES, per camera, over seeded passes (mean and 95 % interval from the run-to-run scatter)."""
    from misrgraph.bench.studies import run_bench_pp

    if runs < 2:
        _fail(f"--runs: got {runs}; expected at least 2 (the interval needs a scatter)")
    with err_console.status(f"{runs} seeded passes..."):
        res = run_bench_pp(runs, seed, workdir, size, truth, blocks, block_range)
    if as_json:
        _print_json(res)
        return
    table = Table(title=f"PP honesty over {runs} {size} passes ({truth} truth): mean and 95 % interval of the runs")
    for col in ("camera", "passes", "RMS / predicted (mean)", "RMS / predicted (RMS of runs)", "NEES", "better than supplied"):
        table.add_column(col, justify="right")
    fmt = lambda v: f"{v['mean']:.2f} [{v['ci95'][0]:.2f}, {v['ci95'][1]:.2f}]"  # noqa: E731
    fmr = lambda v: f"{v['rms']:.2f} [{v['ci95'][0]:.2f}, {v['ci95'][1]:.2f}]"  # noqa: E731
    for cam, v in res["summary"]["per_camera"].items():
        table.add_row(cam, str(v["passes"]), fmt(v["rms_over_predicted"]), fmr(v["rms_over_predicted_rms_of_runs"]),
                      fmt(v["nees"]), f"{v['improvement_over_supplied']['mean']:.1f}x")
    table.add_row("all", str(runs), fmt(res["summary"]["rms_over_predicted_all_cameras"]),
                  fmr(res["summary"]["rms_over_predicted_all_cameras_rms_of_runs"]), fmt(res["summary"]["nees_all_cameras"]), "")
    console.print(table)
    per_block = res["summary"].get("per_block")
    if per_block:
        names = sorted({b for v in per_block.values() for b in v}, key=int)
        bt = Table(title="per block: pixel error RMS / predicted 1-sigma RMS over the runs (px)")
        bt.add_column("camera")
        for b in names:
            bt.add_column(f"block {b}", justify="right")
        for cam, v in per_block.items():
            bt.add_row(cam, *(f"{v[b]['error_px_rms']:.2f} / {v[b]['predicted_px_rms']:.2f}" if b in v else "-" for b in names))
        console.print(bt)


@bench_app.command("roi")
@handle_errors
def bench_roi(
    passes: int = typer.Option(4, "--passes", help="Standard repeat passes of path 37 (at least 4)."),
    blocks: int = typer.Option(2, "--blocks", help="Consecutive SOM blocks from --first-block (whole-line imagery of 9 cameras: ~80 s of rendering a block and pass on 2 cores)."),
    first_block: int = typer.Option(62, "--first-block", help="The first block (path 37's passes have their last tie points in block 69)."),
    seed: int = typer.Option(0, "--seed"),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the scenario and products here (a rerun reuses the scenario)."),
    tie_points: int = typer.Option(1000, "--tie-points", help="Tie points per pass (1000: the standard size)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Reference Orbit Imagery end to end at the seed's size: stage times, PP errors, and the ROI's co-registration measured by matching and against the truth."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.bench.roi import run_bench_roi

    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=err_console,
                  disable=as_json) as bar:
        task = bar.add_task("bench roi", total=None)
        res = run_bench_roi(passes, blocks, seed, workdir, tie_points=tie_points, first_block=first_block,
                            progress=lambda d, k, n: bar.update(task, description=d, completed=k, total=max(n, 1)))
    if as_json:
        _print_json(res)
        return
    _print_coregistration(f"ROI of {passes} passes x {blocks} blocks x 9 cameras: co-registration (px)",
                          list(res["roi_coregistration_px"]), res["roi_coregistration_px"], res["roi_truth"],
                          res.get("roi_predicted_px"))
    console.print("seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in res["seconds"].items() if v is not None))


@bench_app.command("sources")
@handle_errors
def bench_sources(
    runs: int = typer.Option(10, "--runs", help="Seeded passes per row (the same seeds in every row)."),
    seed: int = typer.Option(3000, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the simulated passes here (reused by a rerun)."),
    size: str = typer.Option("reduced", "--size", help="reduced or standard (as bench nees)."),
    mode: str = typer.Option("alone", "--mode", help="alone: each source switched on alone (base row: none); "
                             "without: each source switched off from all of them (base row: all)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """The error-source table: each source of the independent truth switched on alone (or off alone), its effect on
    accuracy and NEES, with the per-seed difference from the base row (paired draw for draw where the source allows)."""
    from misrgraph.bench.studies import run_bench_sources

    if runs < 2:
        _fail(f"--runs: got {runs}; expected at least 2 (the intervals come from the run-to-run scatter)")
    if mode not in ("alone", "without"):
        _fail(f"--mode: got {mode!r}; expected alone or without")
    with err_console.status("error sources...") as st:
        res = run_bench_sources(runs, seed, workdir, size, progress=lambda m: st.update(m), mode=mode)
    if as_json:
        _print_json(res)
        return
    from rich.table import Table

    def fmt(v: dict) -> str:
        return f"{v.get('mean', v.get('rms')):.2f} [{v['ci95'][0]:.2f}, {v['ci95'][1]:.2f}]"

    def fmt_diff(v: dict) -> str:
        return f"{v['mean']:+.3f} [{v['ci95'][0]:+.3f}, {v['ci95'][1]:+.3f}]"

    cols = ("knots", "landmarks", "checkpoint_rms_over_predicted", "checkpoint_rms_over_predicted_rms_of_runs", "checkpoint_rms_m")
    table = Table(title=f"independent truth, {size} passes, {runs} seeds: mean (the ratio also as the RMS of runs) [95 % interval]; "
                        f"landmarks' per-seed difference from {res['base']!r} (paired: the row differs by its source alone)")
    table.add_column("source")
    for c in cols:
        table.add_column(c)
    table.add_column(f"landmarks - {res['base']}")
    table.add_column("paired")
    for name, row in res["rows"].items():
        d = row.get("difference", {}).get("landmarks")
        table.add_row(name, *[fmt(row[c]) if c in row else "-" for c in cols], fmt_diff(d) if d else "-",
                      "base" if name == res["base"] else "yes" if row["paired"] else "no")
    console.print(table)


@bench_app.command("campaign")
@handle_errors
def bench_campaign(
    paths: int = typer.Option(4, "--paths", help="Paths (37, 38, ...), each with its repeat passes."),
    months: float = typer.Option(2.0, "--months", help="Months of data (2: four passes a path)."),
    size: str = typer.Option("reduced", "--size", help="reduced or standard (45-minute passes, 600 tie points)."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the inputs and outputs here (inputs reused)."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Campaign throughput: the adjustment stage on a LocalCluster of 1 and of 2 workers on the same passes (passes per minute, the scaling ratio, peak memory per worker) and an estimate of the full six-month plan."""
    from misrgraph.bench.campaign import run_bench_campaign

    with err_console.status("campaign throughput...") as st:
        res = run_bench_campaign(paths, months, size, workdir=workdir, progress=lambda m: st.update(m))
    if as_json:
        _print_json(res)
        return
    table = Table(title=f"adjustment of {res['passes']} {size} passes")
    for col in ("workers", "passes/minute", "task s/pass", "peak MB per worker"):
        table.add_column(col, justify="right")
    for n, v in res["workers"].items():
        table.add_row(n, f"{v['passes_per_minute']:.1f}", f"{v['task_seconds_per_pass']:.2f}",
                      ", ".join(f"{m:.0f}" for m in v["peak_rss_mb_per_worker"].values()))
    console.print(table)
    fp = res["full_plan"]
    console.print(f"scaling 1 -> 2 workers: {res['scaling_1_to_2']:.2f}x; full plan ({fp['passes']} passes): "
                  f"{fp['adjust_hours_at_2_workers']:.1f} h of adjustment on 2 workers ({fp['note']})")


@bench_app.command("campaign-kill")
@handle_errors
def bench_campaign_kill(
    trials: int = typer.Option(10, "--trials", help="Trials of each kind."),
    kinds: str = typer.Option("client,worker", "--kinds", help="client (SIGKILL the whole campaign, then rerun) and/or worker (SIGKILL one worker mid-run)."),
    paths: int = typer.Option(2, "--paths", help="Paths of the reduced campaign."),
    seed: int = typer.Option(0, "--seed", help="Seed of the inputs and the kill times."),
    workdir: Optional[Path] = typer.Option(None, "--workdir"),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Kill the campaign at random points and resume: every trial must end with outputs identical to an uninterrupted run, one output per planned pass and every pass counted once. Exit 1 on any failure."""
    from misrgraph.bench.campaign import run_campaign_kill_trials

    with err_console.status("campaign kill trials...") as st:
        res = run_campaign_kill_trials(trials, tuple(k.strip() for k in kinds.split(",") if k.strip()), seed, workdir,
                                       paths=paths, progress=lambda m: st.update(m))
    if as_json:
        _print_json(res)
    else:
        table = Table(title=f"campaign kill trials (uninterrupted run {res['uninterrupted_seconds']:.0f} s)")
        for col in ("kind", "trials", "killed while running", "identical", "duplicates", "counted twice", "failed"):
            table.add_column(col, justify="right")
        for kind in sorted({t["kind"] for t in res["trials"]}):
            ts = [t for t in res["trials"] if t["kind"] == kind]
            table.add_row(kind, str(len(ts)), str(sum(bool(t["killed_while_running"]) for t in ts)),
                          str(sum(bool(t.get("identical")) for t in ts)), str(sum(t.get("duplicates", 0) for t in ts)),
                          str(sum(max(0, t.get("counted", 0) - t.get("planned", 0)) for t in ts)),
                          str(sum(t in res["failures"] for t in ts)))
        console.print(table)
    if res["failures"]:
        raise typer.Exit(1)


@bench_app.command("kill")
@handle_errors
def bench_kill(
    commands: str = typer.Option(",".join(("simulate", "calibrate", "adjust", "update")), "--commands",
                                 help="Comma list of simulate, calibrate, adjust, update."),
    trials: int = typer.Option(20, "--trials", help="SIGKILL trials per command."),
    seed: int = typer.Option(0, "--seed", help="Seed of the kill times."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the scenarios and outputs here."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Fault tolerance: SIGKILL each command at random points; every file must be the old one or
    a complete new one, no pass counted twice, and a rerun must complete. Exit 1 on any failure."""
    from misrgraph.bench.faults import run_kill_trials

    with err_console.status("kill trials...") as st:
        res = run_kill_trials(tuple(c.strip() for c in commands.split(",") if c.strip()), trials, seed, workdir,
                              progress=lambda m: st.update(m))
    if as_json:
        _print_json(res)
    else:
        table = Table(title=f"SIGKILL trials ({trials} per command)")
        cols = ("trials", "killed_while_running", "old", "new", "none", "half_written", "lost", "counted_twice",
                "rerun_failed", "debris")
        heads = ("trials", "killed", "old", "new", "none", "half", "lost", "twice", "rerun✗", "debris")
        table.add_column("command")
        for c in heads:
            table.add_column(c, justify="right")
        for name, r in res["commands"].items():
            table.add_row(name, *(str(r[c]) for c in cols))
        console.print(table)
    if res["failures"]:
        raise typer.Exit(1)


@app.command()
@handle_errors
def demo(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Directory for the demo's products."),
    small: bool = typer.Option(False, "--small", help="Reduced sizes (about a minute)."),
) -> None:
    """The whole workflow on simulated data: calibrate, adjust, update, record; prints a summary."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.runs.demo import STAGES, run_demo

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=err_console) as bar:
        task = bar.add_task("demo", total=len(STAGES))
        done = {"n": 0}

        def step(name: str) -> None:
            bar.update(task, description=name, completed=done["n"])
            done["n"] += 1

        records = run_demo(out, progress=step, small=small)
        bar.update(task, completed=len(STAGES), description="done")
    table = Table(title=f"misrgraph demo (products in {out})")
    for col in ("stage", "result against the simulator's truth", "time (s)"):
        table.add_column(col)
    for r in records:
        table.add_row(r["stage"], r["summary"], f"{r['seconds']:.1f}")
    console.print(table)
    console.print(f"total {sum(r['seconds'] for r in records):.0f} s")


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
