"""``misrgraph bench``: speed, memory and statistical studies, measured in one run."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.table import Table

from misrgraph.commands.common import (
    console,
    err_console,
    fail,
    handle_errors,
    print_coregistration,
    print_json,
)

SAVE_HELP = "Also write the result, with its provenance (command, commit, machine), as JSON to this file."

__all__ = [
    "app",
    "bench_solver",
    "bench_calibration",
    "bench_sba",
    "bench_match",
    "bench_scaling",
    "bench_incremental",
    "bench_nees",
    "bench_nees_pool",
    "bench_pp",
    "bench_roi",
    "bench_sources",
    "bench_campaign",
    "bench_campaign_kill",
    "bench_kill",
    "bench_report",
    "bench_worlds",
]


def finish(result: dict, save: Optional[Path]) -> dict:
    """:func:`misrgraph.bench.provenance.finish`, imported when a bench ends (not at start-up)."""
    from misrgraph.bench.provenance import finish as stamp

    return stamp(result, save)


app = typer.Typer(
    help="Speed, memory and statistical studies; each prints ratios and intervals measured in one run.",
    no_args_is_help=True,
)


@app.command("solver")
@handle_errors
def bench_solver(
    tie_points: int = typer.Option(1000, "--tie-points", help="Tie points in the simulated pass."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated inputs."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep/reuse simulated scenarios here."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Solver core vs gtsam.LevenbergMarquardtOptimizer on the same graph (per linearisation, per iteration)."""
    from misrgraph.bench.studies import run_bench_solver

    if tie_points < 10:
        fail(f"--tie-points: got {tie_points}; expected at least 10")
    with err_console.status("simulating and solving (gtsam LM is the slow part)..."):
        res = run_bench_solver(tie_points, seed, workdir)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    t = Table(
        title=f"bench solver: {res['variables']} variables, {res['factors']} factors, {res['observations']} "
        "observations"
    )
    for col in ("solver", "seconds", "iterations", "s / iteration", "final cost"):
        t.add_column(col)
    for name in ("core", "gtsam_lm"):
        r = res[name]
        t.add_row(
            name,
            f"{r['seconds']:.2f}",
            str(r["iterations"]),
            f"{r['seconds_per_iteration']:.3f}",
            f"{r['final_cost']:.6f}",
        )
    console.print(t)
    console.print(
        f"gtsam_lm / core = {res['ratio_gtsam_lm_over_core']:.1f}x; linearisation (s): "
        + ", ".join(f"{k} {v:.3f}" for k, v in res["linearize_seconds"].items())
    )


@app.command("calibration")
@handle_errors
def bench_calibration(
    size: str = typer.Option("standard", "--size", help="standard (120 GCPs, 30 days) or reduced (24 GCPs, 16 days)."),
    seed: int = typer.Option(3, "--seed", help="Random seed of the simulated inputs."),
    repeat: int = typer.Option(3, "--repeat", help="Timings are the best of this many runs."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep/reuse the simulated month here."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """A month calibration's linear algebra: the LM step by the former (landmarks-first) and the
    current (COLAMD, cameras last) ordering, the cameras' covariance by SuperLU's unsymmetric LU
    and by its symmetric mode; seconds, ratios and the differences of the results."""
    from misrgraph.bench.calibration import run_bench_calibration

    with err_console.status(f"simulating (or reusing) the {size} month and linearising it..."):
        res = run_bench_calibration(size, seed, workdir, repeat)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    t = Table(
        title=f"bench calibration: {res['size']} month, {res['passes']} passes, {res['variables']} variables "
        f"({res['landmarks']} GCP landmarks, {res['cameras']} cameras)"
    )
    for col in ("part", "former", "s", "current", "s", "former / current", "relative difference"):
        t.add_column(col)
    for part in ("step", "camera_covariance"):
        r = res[part]
        t.add_row(
            part.replace("_", " "),
            r["former"],
            f"{r['former_s']:.3f}",
            r["current"],
            f"{r['current_s']:.3f}",
            f"{r['ratio']:.1f}x",
            f"{r['relative_difference']:.1e}",
        )
    console.print(t)


@app.command("sba")
@handle_errors
def bench_sba(
    tie_points: int = typer.Option(2000, "--tie-points", min=20, help="Tie points in the simulated pass."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated inputs."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep/reuse simulated scenarios here."),
    skip: str = typer.Option(
        "", "--skip", help="Comma list of solvers to leave out (names as in the table, e.g. gtsam_lm,ceres)."
    ),
    budget_s: float = typer.Option(60.0, "--budget", help="Seconds each solver may run at most."),
    check_points: int = typer.Option(
        200, "--check-points", min=0, help="Check points of the simulated pass (for the products' errors)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Solvers at equal accuracy of the estimate.

    Seconds until each is within 1, 0.3, 0.1 and 0.03 sigma of a verified optimum, and the products'
    errors where each stops.
    """
    from misrgraph.bench.accuracy import run_bench_sba

    if budget_s <= 0.0:
        fail(f"--budget: got {budget_s}; expected a positive number of seconds")
    names = tuple(x.strip() for x in skip.split(",") if x.strip())
    with err_console.status("simulating and solving with every alternative..."):
        res = run_bench_sba(tie_points, seed, workdir, skip=names, budget_s=budget_s, check_points=check_points)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    ref = res["reference"]
    t = Table(
        title=f"bench sba: {res['tie_points']} tie points, {res['observations']} observations, {res['unknowns']} "
        "unknowns; "
        f"seconds until within a distance of the optimum (max over knots and ephemeris, in sigma)"
    )
    for col in (
        "solver",
        *(f"{lv} sigma" for lv in res["sigma_levels"]),
        "0.1 / core",
        "stop: s",
        "max sigma",
        "check points (m)",
        "co-reg. (px)",
        "ended",
    ):
        t.add_column(col, no_wrap=col == "solver")
    for name, r in res["solvers"].items():
        if "skipped" in r:
            t.add_row(name, *[""] * (len(res["sigma_levels"]) + 5), r["skipped"])
            continue
        st = r["stop"]
        ratio = res["ratio_to_core_at_0.1_sigma"].get(name)
        bound = ">= " if name in res["ratios_that_are_lower_bounds"] else ""

        def fmt(v, f):
            return "-" if v is None else format(v, f)

        t.add_row(
            name,
            *(fmt(v, ".2f") for v in r["seconds_to_sigma"].values()),
            "1" if name == "misrgraph" else ("never" if ratio is None else f"{bound}{ratio:.1f}"),
            f"{st['seconds']:.1f}",
            f"{st['max_sigma']:.3g}",
            fmt(st["checkpoint_rms_m"], ".2f"),
            fmt(st["coregistration_px"], ".3f"),
            str(st["ended"])[:40],
        )
    console.print(t)
    console.print(
        f"optimum: cost {ref['cost']:.3f}, Gauss-Newton step there {ref['gauss_newton_step_max_sigma']:.1e} sigma "
        f"({'verified' if ref['verified'] else 'NOT verified'}); its check points {ref['checkpoint_rms_m']} m. "
        f"Marginals (one routine for all): {res['marginals']['seconds']:.2f} s, not included above."
    )
    console.print(
        "'-': never within that distance before its own stop or its time budget "
        f"({res['budget_seconds']:.0f} s); '>=': the ratio is then a lower bound (its whole run)."
    )


@app.command("match")
@handle_errors
def bench_match(
    tie_points: int = typer.Option(1000, "--tie-points", min=10, help="Tie points in the simulated pass."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated inputs."),
    duration: float = typer.Option(2700.0, "--duration", help="Pass duration (s)."),
    cloud_fraction: float = typer.Option(0.0, "--cloud-fraction", help="Fraction of the sky covered by clouds."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the simulated scenarios here."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Imagery, matching and the matched adjustment on one pass.

    Rendering cost, matching accuracy against truth, NCC+LSM vs a plain scikit-image template match on
    the same GCP chips, check points matched vs simulated.
    """
    from misrgraph.bench.match import run_bench_match

    with err_console.status("simulating with imagery, matching, adjusting..."):
        res = run_bench_match(tie_points, seed, duration, cloud_fraction, workdir=workdir)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    m, g, a = res["match"], res["gcp_chips"], res["adjust"]
    for kind in ("gcp", "tie"):
        v = m[kind]
        console.print(
            f"{kind}: {v['matched']}/{v['candidates']} matched, error RMS {v['error_px']['rms']:.3f} px, "
            f"error/sigma {v['normalised_error_rms']:.2f}, wrong {v['wrong_matches']}, {v['seconds']:.1f} s"
        )
    if "ncc_lsm" in g:
        console.print(
            f"GCP chips: NCC+LSM {g['ncc_lsm']['error_rms_px']:.3f} px at {g['ncc_lsm']['chips_per_second']:.0f}/s; "
            f"skimage+parabola {g['skimage_parabola']['error_rms_px']:.3f} px at "
            f"{g['skimage_parabola']['chips_per_second']:.0f}/s"
        )
    console.print(
        f"rendering {res['simulate_seconds']['rendering']:.0f} s; check points matched/simulated "
        f"{a['checkpoint_ratio_matched_over_simulated']:.2f}, co-registration max "
        f"{a['matched']['coregistration_px_max']:.3f} px"
    )


@app.command("scaling")
@handle_errors
def bench_scaling(
    sizes: str = typer.Option("250,500,1000,2000,4000", "--sizes", help="Comma list of tie-point counts."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated inputs."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated inputs here (a rerun reuses them)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Time per pass against tie points, with a fitted exponent, and peak memory."""
    from misrgraph.bench.studies import run_bench_scaling

    try:
        ns = tuple(int(x) for x in sizes.split(","))
    except ValueError:
        fail(f"--sizes: got {sizes!r}; expected comma-separated integers such as 250,500,1000")
    with err_console.status("simulating and solving..."):
        res = run_bench_scaling(ns, seed, workdir)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    t = Table(title="bench scaling (Schur backend, with knot marginals)")
    for col in ("tie points", "observations", "seconds", "iterations", "s / iteration", "peak Python MB"):
        t.add_column(col)
    for r in res["rows"]:
        t.add_row(
            str(r["tie_points"]),
            str(r["observations"]),
            f"{r['seconds']:.2f}",
            str(r["iterations"]),
            f"{r['seconds_per_iteration']:.3f}",
            f"{r['peak_python_mb']:.0f}",
        )
    console.print(t)
    console.print(
        f"fitted exponent: per iteration vs observations {res['exponent_per_iteration_vs_observations']:.2f}, "
        f"total vs tie points {res['exponent_total_vs_tie_points']:.2f}; peak RSS {res['process_peak_rss_mb']:.0f} MB"
    )


@app.command("incremental")
@handle_errors
def bench_incremental(
    passes: int = typer.Option(10, "--passes", min=1, help="Repeat passes added one after another."),
    tie_points: int = typer.Option(150, "--tie-points", min=20, help="Tie points per pass."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated inputs."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated inputs here (a rerun reuses them)."
    ),
    linearization_tol: Optional[float] = typer.Option(
        None,
        "--linearization-tol",
        min=1e-6,
        help="iSAM2 re-linearisation tolerance in sigma [default: the library's].",
    ),
    settle_after: Optional[int] = typer.Option(
        None,
        "--settle-after",
        min=0,
        help="Marginalise a pass out of iSAM2 once this many newer passes have arrived; 0: never "
        "[default: the library's, 3].",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Adding the k-th pass with iSAM2 against a warm-started batch re-solve of all k passes at the same
    accuracy, pass after pass.
    """
    from misrgraph.bench.accuracy import run_bench_incremental

    with err_console.status(f"simulating {passes} repeat passes and solving..."):
        kw = {} if settle_after is None else {"settle_after": settle_after or None}
        res = run_bench_incremental(passes, tie_points, seed, workdir, linearization_tol, **kw)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    t = Table(title=f"bench incremental: {res['passes']} repeat passes x {res['tie_points']} tie points")
    for col in (
        "pass k",
        "iSAM2 update (s)",
        "warm batch, same accuracy (s)",
        "update / batch",
        "iSAM2 from optimum (sigma)",
        "rounds",
    ):
        t.add_column(col)
    marks = {int(k) for k in res["at"]} | {1, res["passes"]}
    for r in res["per_pass"]:
        if r["pass"] in marks or r["pass"] % 10 == 0:
            t.add_row(
                str(r["pass"]),
                f"{r['update_seconds']:.3f}",
                f"{r['batch_seconds']:.3f}",
                f"{r['update_seconds'] / r['batch_seconds']:.2f}",
                f"{r['max_difference_sigma']:.4f}",
                str(r["relinearization_rounds"]),
            )
    console.print(t)
    if res["update_last_over_update_10"] is not None:
        console.print(
            f"update at pass {res['passes']} / update at pass 10 = {res['update_last_over_update_10']:.2f}; ", end=""
        )
    console.print(
        f"iSAM2's largest distance from the converged batch over all passes: {res['max_difference_sigma_worst']:.4f} "
        "sigma"
    )


@app.command("nees")
@handle_errors
def bench_nees(
    study: str = typer.Option("calibration", "--study", help="calibration or adjust."),
    runs: int = typer.Option(20, "--runs", help="Seeded runs."),
    seed: int = typer.Option(1000, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated inputs here (a rerun reuses them)."
    ),
    size: str = typer.Option(
        "reduced",
        "--size",
        help="reduced (the test suite's size) or standard (45-minute passes with 600 tie points and check points; "
        "full months).",
    ),
    truth: str = typer.Option(
        "model", "--truth", help="The simulator's truth: model or independent (see misrgraph simulate --help)."
    ),
    calibrate_params: Optional[str] = typer.Option(
        None,
        "--calibrate-params",
        help="Calibration study: the parameters to estimate (as calibrate --params; default "
        "delta,beta,epsilon,alpha2,alpha3).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Covariance honesty.

    NEES per class over seeded runs, against its 95 % chi-square band and with a 95 % interval from the
    run-to-run scatter.
    """
    from misrgraph.bench.studies import run_bench_nees

    if runs < 1:
        fail(f"--runs: got {runs}; expected at least 1")
    with err_console.status(f"{runs} seeded {study} runs..."):
        res = run_bench_nees(
            study,
            runs,
            seed,
            workdir,
            size,
            truth,
            calibrate_params=tuple(p.strip() for p in calibrate_params.split(",")) if calibrate_params else None,
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
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
                console.print(
                    f"    {c}: RMS of {bc['runs']} runs {bc['rms']:.3f} [{bc['ci95'][0]:.3f}, {bc['ci95'][1]:.3f}]"
                )
            continue
        console.print(
            f"{study} {k}: NEES/dim {v['nees_per_dim']:.3f}, 95 % band [{v['band'][0]:.3f}, {v['band'][1]:.3f}] "
            f"({v['dof']} dof) -> {'inside' if v['inside'] else 'OUTSIDE'}; {scatter}"
        )


@app.command("nees-pool")
@handle_errors
def bench_nees_pool(
    files: list[Path] = typer.Argument(
        ..., help="bench nees --json outputs of the same study, size, truth and settings."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Pool several bench nees results (e.g. held-out seed sets run apart) into one study.

    Pooled NEES/dim and its band, and intervals from the scatter of all their runs.
    """
    from misrgraph.bench.studies import pool_bench_nees

    results = []
    for f in files:
        try:
            results.append(json.loads(Path(f).read_text()))
        except OSError as e:
            fail(f"FILES: {f} cannot be read ({e.strerror}); expected a bench nees --json output")
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            fail(f"FILES: {f} is not JSON ({e}); expected a bench nees --json output")
        if not isinstance(results[-1], dict):
            fail(f"FILES: {f} holds a {type(results[-1]).__name__}; expected a bench nees --json output (an object)")
    res = pool_bench_nees(results)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    seeds = sorted(int(r["seed"]) for r in res["per_run"])
    console.print(
        f"pooled {res['runs']} runs from {res['pooled_from']} results ({res['study']}, {res['size']}, "
        f"{res['truth']} truth; seeds {seeds[0]}-{seeds[-1]})"
    )
    _print_nees(res)


@app.command("pp")
@handle_errors
def bench_pp(
    runs: int = typer.Option(20, "--runs", help="Seeded passes."),
    seed: int = typer.Option(5000, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated passes and PP here (reused by a rerun)."
    ),
    size: str = typer.Option("reduced", "--size", help="reduced or standard (as bench nees --study adjust)."),
    truth: str = typer.Option("model", "--truth", help="model or independent (see misrgraph simulate --help)."),
    blocks: int = typer.Option(2, "--blocks", help="SOM blocks per pass, around its features."),
    block_range: Optional[str] = typer.Option(
        None, "--block-range", help="Score these blocks (A-B) in every pass instead of --blocks, and also per block."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Honesty of the Projection Parameters' 1 sigma.

    PP geolocation RMS against the truth over the predicted RMS, and NEES, per camera, over seeded
    passes (mean and 95 % interval from the run-to-run scatter).
    """
    from misrgraph.bench.studies import run_bench_pp

    if runs < 2:
        fail(f"--runs: got {runs}; expected at least 2 (the interval needs a scatter)")
    with err_console.status(f"{runs} seeded passes..."):
        res = run_bench_pp(runs, seed, workdir, size, truth, blocks, block_range)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    table = Table(title=f"PP honesty over {runs} {size} passes ({truth} truth): mean and 95 % interval of the runs")
    for col in (
        "camera",
        "passes",
        "RMS / predicted (mean)",
        "RMS / predicted (RMS of runs)",
        "NEES",
        "better than supplied",
    ):
        table.add_column(col, justify="right")
    fmt = lambda v: f"{v['mean']:.2f} [{v['ci95'][0]:.2f}, {v['ci95'][1]:.2f}]"  # noqa: E731
    fmr = lambda v: f"{v['rms']:.2f} [{v['ci95'][0]:.2f}, {v['ci95'][1]:.2f}]"  # noqa: E731
    for cam, v in res["summary"]["per_camera"].items():
        table.add_row(
            cam,
            str(v["passes"]),
            fmt(v["rms_over_predicted"]),
            fmr(v["rms_over_predicted_rms_of_runs"]),
            fmt(v["nees"]),
            f"{v['improvement_over_supplied']['mean']:.1f}x",
        )
    table.add_row(
        "all",
        str(runs),
        fmt(res["summary"]["rms_over_predicted_all_cameras"]),
        fmr(res["summary"]["rms_over_predicted_all_cameras_rms_of_runs"]),
        fmt(res["summary"]["nees_all_cameras"]),
        "",
    )
    console.print(table)
    per_block = res["summary"].get("per_block")
    if per_block:
        names = sorted({b for v in per_block.values() for b in v}, key=int)
        bt = Table(title="per block: pixel error RMS / predicted 1-sigma RMS over the runs (px)")
        bt.add_column("camera")
        for b in names:
            bt.add_column(f"block {b}", justify="right")
        for cam, v in per_block.items():
            bt.add_row(
                cam, *(f"{v[b]['error_px_rms']:.2f} / {v[b]['predicted_px_rms']:.2f}" if b in v else "-" for b in names)
            )
        console.print(bt)


@app.command("roi")
@handle_errors
def bench_roi(
    passes: int = typer.Option(4, "--passes", help="Standard repeat passes of path 37 (at least 4)."),
    blocks: int = typer.Option(
        2,
        "--blocks",
        help="Consecutive SOM blocks from --first-block (whole-line imagery of 9 cameras: ~80 s of rendering a "
        "block and pass on 2 cores).",
    ),
    first_block: int = typer.Option(
        62, "--first-block", help="The first block (path 37's passes have their last tie points in block 69)."
    ),
    seed: int = typer.Option(0, "--seed", help="Random seed of the simulated inputs."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the scenario and products here (a rerun reuses the scenario)."
    ),
    tie_points: int = typer.Option(1000, "--tie-points", help="Tie points per pass (1000: the standard size)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Reference Orbit Imagery end to end at the seed's size.

    Stage times, PP errors, and the ROI's co-registration measured by matching and against the truth.
    """
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from misrgraph.bench.roi import run_bench_roi

    with Progress(
        TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=err_console, disable=as_json
    ) as bar:
        task = bar.add_task("bench roi", total=None)
        res = run_bench_roi(
            passes,
            blocks,
            seed,
            workdir,
            tie_points=tie_points,
            first_block=first_block,
            progress=lambda d, k, n: bar.update(task, description=d, completed=k, total=max(n, 1)),
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    print_coregistration(
        f"ROI of {passes} passes x {blocks} blocks x 9 cameras: co-registration (px)",
        list(res["roi_coregistration_px"]),
        res["roi_coregistration_px"],
        res["roi_truth"],
        res.get("roi_predicted_px"),
    )
    console.print("seconds: " + ", ".join(f"{k} {v:.0f}" for k, v in res["seconds"].items() if v is not None))


@app.command("sources")
@handle_errors
def bench_sources(
    runs: int = typer.Option(10, "--runs", help="Seeded passes per row (the same seeds in every row)."),
    seed: int = typer.Option(3000, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated passes here (reused by a rerun)."
    ),
    size: str = typer.Option("reduced", "--size", help="reduced or standard (as bench nees)."),
    mode: str = typer.Option(
        "alone",
        "--mode",
        help="alone: each source switched on alone (base row: none); "
        "without: each source switched off from all of them (base row: all).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """The error-source table: each source of the independent truth switched on alone (or off alone), its effect on
    accuracy and NEES, with the per-seed difference from the base row (paired draw for draw where the source allows)."""
    from misrgraph.bench.studies import run_bench_sources

    if runs < 2:
        fail(f"--runs: got {runs}; expected at least 2 (the intervals come from the run-to-run scatter)")
    if mode not in ("alone", "without"):
        fail(f"--mode: got {mode!r}; expected alone or without")
    with err_console.status("error sources...") as st:
        res = run_bench_sources(runs, seed, workdir, size, progress=lambda m: st.update(m), mode=mode)
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    from rich.table import Table

    def fmt(v: dict) -> str:
        return f"{v.get('mean', v.get('rms')):.2f} [{v['ci95'][0]:.2f}, {v['ci95'][1]:.2f}]"

    def fmt_diff(v: dict) -> str:
        return f"{v['mean']:+.3f} [{v['ci95'][0]:+.3f}, {v['ci95'][1]:+.3f}]"

    cols = (
        "knots",
        "landmarks",
        "checkpoint_rms_over_predicted",
        "checkpoint_rms_over_predicted_rms_of_runs",
        "checkpoint_rms_m",
    )
    table = Table(
        title=f"independent truth, {size} passes, {runs} seeds: mean (the ratio also as the RMS of runs) [95 % "
        "interval]; "
        f"landmarks' per-seed difference from {res['base']!r} (paired: the row differs by its source alone)"
    )
    table.add_column("source")
    for c in cols:
        table.add_column(c)
    table.add_column(f"landmarks - {res['base']}")
    table.add_column("paired")
    for name, row in res["rows"].items():
        d = row.get("difference", {}).get("landmarks")
        table.add_row(
            name,
            *[fmt(row[c]) if c in row else "-" for c in cols],
            fmt_diff(d) if d else "-",
            "base" if name == res["base"] else "yes" if row["paired"] else "no",
        )
    console.print(table)


@app.command("campaign")
@handle_errors
def bench_campaign(
    paths: int = typer.Option(4, "--paths", help="Paths (37, 38, ...), each with its repeat passes."),
    months: float = typer.Option(2.0, "--months", help="Months of data (2: four passes a path)."),
    size: str = typer.Option("reduced", "--size", help="reduced or standard (45-minute passes, 600 tie points)."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the inputs and outputs here (inputs reused)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Campaign throughput.

    The adjustment stage on a LocalCluster of 1 and of 2 workers on the same passes (passes per minute,
    the scaling ratio, peak memory per worker) and an estimate of the full six-month plan.
    """
    from misrgraph.bench.campaign import run_bench_campaign

    with err_console.status("campaign throughput...") as st:
        res = run_bench_campaign(paths, months, size, workdir=workdir, progress=lambda m: st.update(m))
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    table = Table(title=f"adjustment of {res['passes']} {size} passes")
    for col in ("workers", "passes/minute", "task s/pass", "peak MB per worker"):
        table.add_column(col, justify="right")
    for n, v in res["workers"].items():
        table.add_row(
            n,
            f"{v['passes_per_minute']:.1f}",
            f"{v['task_seconds_per_pass']:.2f}",
            ", ".join(f"{m:.0f}" for m in v["peak_rss_mb_per_worker"].values()),
        )
    console.print(table)
    fp = res["full_plan"]
    console.print(
        f"scaling 1 -> 2 workers: {res['scaling_1_to_2']:.2f}x; full plan ({fp['passes']} passes): "
        f"{fp['adjust_hours_at_2_workers']:.1f} h of adjustment on 2 workers ({fp['note']})"
    )


@app.command("campaign-kill")
@handle_errors
def bench_campaign_kill(
    trials: int = typer.Option(10, "--trials", help="Trials of each kind."),
    kinds: str = typer.Option(
        "client,worker",
        "--kinds",
        help="client (SIGKILL the whole campaign, then rerun) and/or worker (SIGKILL one worker mid-run).",
    ),
    paths: int = typer.Option(2, "--paths", help="Paths of the reduced campaign."),
    seed: int = typer.Option(0, "--seed", help="Seed of the inputs and the kill times."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated inputs here (a rerun reuses them)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Kill the campaign at random points and resume.

    Every trial must end with outputs identical to an uninterrupted run, one output per planned pass and
    every pass counted once. Exit 1 on any failure.
    """
    from misrgraph.bench.campaign import run_campaign_kill_trials

    with err_console.status("campaign kill trials...") as st:
        res = run_campaign_kill_trials(
            trials,
            tuple(k.strip() for k in kinds.split(",") if k.strip()),
            seed,
            workdir,
            paths=paths,
            progress=lambda m: st.update(m),
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
    else:
        table = Table(title=f"campaign kill trials (uninterrupted run {res['uninterrupted_seconds']:.0f} s)")
        for col in ("kind", "trials", "killed while running", "identical", "duplicates", "counted twice", "failed"):
            table.add_column(col, justify="right")
        for kind in sorted({t["kind"] for t in res["trials"]}):
            ts = [t for t in res["trials"] if t["kind"] == kind]
            table.add_row(
                kind,
                str(len(ts)),
                str(sum(bool(t["killed_while_running"]) for t in ts)),
                str(sum(bool(t.get("identical")) for t in ts)),
                str(sum(t.get("duplicates", 0) for t in ts)),
                str(sum(max(0, t.get("counted", 0) - t.get("planned", 0)) for t in ts)),
                str(sum(t in res["failures"] for t in ts)),
            )
        console.print(table)
    if res["failures"]:
        raise typer.Exit(1)


@app.command("kill")
@handle_errors
def bench_kill(
    commands: str = typer.Option(
        ",".join(("simulate", "calibrate", "adjust", "update")),
        "--commands",
        help="Comma list of simulate, calibrate, adjust, update.",
    ),
    trials: int = typer.Option(20, "--trials", help="SIGKILL trials per command."),
    seed: int = typer.Option(0, "--seed", help="Seed of the kill times."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the scenarios and outputs here."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Fault tolerance: SIGKILL each command at random points; every file must be the old one or
    a complete new one, no pass counted twice, and a rerun must complete. Exit 1 on any failure."""
    from misrgraph.bench.faults import run_kill_trials

    with err_console.status("kill trials...") as st:
        res = run_kill_trials(
            tuple(c.strip() for c in commands.split(",") if c.strip()),
            trials,
            seed,
            workdir,
            progress=lambda m: st.update(m),
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
    else:
        table = Table(title=f"SIGKILL trials ({trials} per command)")
        cols = (
            "trials",
            "killed_while_running",
            "old",
            "new",
            "none",
            "half_written",
            "lost",
            "counted_twice",
            "rerun_failed",
            "debris",
        )
        heads = ("trials", "killed", "old", "new", "none", "half", "lost", "twice", "rerun✗", "debris")
        table.add_column("command")
        for c in heads:
            table.add_column(c, justify="right")
        for name, r in res["commands"].items():
            table.add_row(name, *(str(r[c]) for c in cols))
        console.print(table)
    if res["failures"]:
        raise typer.Exit(1)


@app.command("report")
@handle_errors
def bench_report(
    data: Path = typer.Option(Path("docs/results/data"), "--data", help="Directory of stored results (*.json)."),
    pages: Path = typer.Option(Path("docs/results"), "--pages", help="Directory of the generated results pages."),
    readme: Optional[Path] = typer.Option(
        Path("README.md"), "--readme", help="README whose generated blocks are rendered ('-': leave it alone)."
    ),
    check: bool = typer.Option(
        False, "--check", help="Write nothing; exit 1 when a page differs from what the stored results render."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print what was rendered as JSON."),
) -> None:
    """Render the results pages and the README's figures from stored bench results.

    Every figure in the README and docs/results comes from a JSON file written by a bench command's
    --save; each page is headed by that command, the commit and the machine.
    """
    from misrgraph.bench.report import ReportConfig, run_report

    cfg = ReportConfig(data=data, pages=pages, readme=None if readme is None or str(readme) == "-" else readme)
    res = run_report(cfg, check=check)
    if as_json:
        print_json(res)
    elif check:
        for p in res["changed"]:
            err_console.print(f"out of date: {p} (run 'misrgraph bench report')", markup=False, highlight=False)
        if not res["changed"]:
            console.print(f"{len(res['files'])} generated files up to date")
    else:
        console.print(f"{len(res['changed'])} of {len(res['files'])} generated files written", highlight=False)
    if check and res["changed"]:
        raise typer.Exit(1)


@app.command("worlds")
@handle_errors
def bench_worlds(
    passes: int = typer.Option(4, "--passes", help="Passes scored per world."),
    fit_passes: int = typer.Option(
        2, "--fit-passes", help="Passes per world the noise model is fitted on (not scored)."
    ),
    worlds: Optional[str] = typer.Option(
        None, "--worlds", help="Comma-separated world names (default all; 'misrgraph bench worlds --list' names them)."
    ),
    list_worlds: bool = typer.Option(False, "--list", help="List the worlds and what each changes, and exit."),
    seed: int = typer.Option(20000, "--seed", help="First seed (world w uses seed + 100 w + i)."),
    size: str = typer.Option("reduced", "--size", help="reduced (20-minute passes, 300 tie points) or tiny."),
    workdir: Optional[Path] = typer.Option(
        None, "--workdir", help="Keep the simulated passes here (a rerun reuses them)."
    ),
    workers: int = typer.Option(
        1, "--workers", help="Worlds run at once, each in a process of its own (1: one after the other)."
    ),
    knot_prior: str = typer.Option(
        "process",
        "--knot-prior",
        help="Every adjustment's knot prior (as 'adjust --knot-prior'); another than 'process' keeps its "
        "fitted passes and noise models beside the default's in --workdir.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Honesty in worlds the estimator was not tuned for: fixed, learned and oracle noise levels.

    Per world: NEES of landmarks, knots and camera and the check points' actual/predicted RMS, each
    with a 95 % interval from the run-to-run scatter, and the check points' RMS error (m).
    """
    from misrgraph.bench.worlds import WORLDS, run_bench_worlds

    if list_worlds:
        for name, over in WORLDS.items():
            console.print(f"{name}: {over or 'the base world'}", highlight=False)
        return
    names = [w.strip() for w in worlds.split(",")] if worlds else None
    with err_console.status("worlds...") as st:
        res = run_bench_worlds(
            passes,
            fit_passes,
            names,
            seed,
            size,
            workdir,
            progress=lambda m: st.update(m),
            workers=workers,
            knot_prior=knot_prior,
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    _print_worlds(res)


def _print_worlds(res: dict) -> None:
    from misrgraph.bench.report import WORLDS_COLUMNS, worlds_table

    table = Table(title=f"worlds: {res['passes']} scored passes each (mean, 95 % interval)")
    for col in WORLDS_COLUMNS:
        table.add_column(col, justify="right")
    for row in worlds_table(res):
        table.add_row(*row)
    console.print(table)
    a = res["acceptance"]
    console.print(f"learned levels meet the acceptance bounds in {a['worlds_passing']} of {a['worlds']} worlds")


@app.command("knot-prior")
@handle_errors
def bench_knot_prior(
    workdir: Path = typer.Option(..., "--workdir", help="The --workdir of a 'misrgraph bench worlds' run."),
    worlds: Optional[str] = typer.Option(
        None, "--worlds", help="Comma-separated world names (default: every world the workdir holds a noise model of)."
    ),
    size: str = typer.Option("reduced", "--size", help="The size the worlds run used (reduced or tiny)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """The knots' NEES and error under other knot priors, in closed form, on the passes a 'bench
    worlds' run fitted its noise models on.

    Per world: the damped process at the world's levels and at the learned ones, each with and
    without a jitter component, and the truth's own covariance (NEES 1, the least error).
    """
    from misrgraph.bench.knotprior import run_bench_knot_prior

    names = [w.strip() for w in worlds.split(",")] if worlds else None
    with err_console.status("knot priors...") as st:
        res = run_bench_knot_prior(workdir, names, size, progress=lambda m: st.update(m))
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    from misrgraph.bench.report import knot_prior_table

    head, rows = knot_prior_table(res)
    table = Table(title="knot priors in closed form: expected NEES/dim (value RMS error, arcsec)")
    for col in head:
        table.add_column(col, justify="right")
    for row in rows:
        table.add_row(*row)
    console.print(table)


@app.command("monitor")
@handle_errors
def bench_monitor(
    campaigns: int = typer.Option(20, "--campaigns", help="Campaigns of each kind (a step, a drift, no change)."),
    years: float = typer.Option(5.0, "--years", help="Length of a campaign (years)."),
    recalibrate_days: float = typer.Option(30.0, "--recalibrate-days", help="Days between recalibrations."),
    calibration: Optional[Path] = typer.Option(
        None,
        "--calibration",
        help="A calibration summary ('calibrate --json' output) whose per-parameter sigma_px and correlations the "
        "recalibrations have. Default: calibrate a standard simulated window of --recalibrate-days days first "
        "(about a minute per 30 days).",
    ),
    step_px: float = typer.Option(0.1, "--step-px", help="Size of the step in one camera (px)."),
    drift_px_per_year: float = typer.Option(0.05, "--drift-px-per-year", help="Rate of the drift in one camera."),
    alpha: float = typer.Option(0.05, "--alpha", help="False-alarm probability of a campaign without change."),
    seed: int = typer.Option(0, "--seed", help="Seed of the campaigns."),
    view: str = typer.Option(
        "conditional", "--view", help="What the monitor tests: conditional (each camera given the others) or marginal."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """How soon the drift monitor asks for a new camera model (a step, a drift) and how often it
    asks with no change, over simulated multi-year series of recalibrations; fractions with Wilson
    95 % intervals."""
    from misrgraph.bench.monitor import run_bench_monitor

    with err_console.status("monitor...") as st:
        res = run_bench_monitor(
            campaigns,
            years,
            recalibrate_days,
            calibration,
            step_px,
            drift_px_per_year,
            alpha,
            seed=seed,
            progress=lambda m: st.update(m),
            view=view,
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    table = Table(
        title=f"monitor ({res['view']} view): {res['campaigns']} campaigns of {res['years']:g} years each kind"
    )
    for col in ("what", "value", "95 % interval"):
        table.add_column(col, justify="right")

    def row(name: str, v: float, iv: list[float], fmt: str = "{:.0%}") -> None:
        table.add_row(name, fmt.format(v), "[" + ", ".join(fmt.format(x) for x in iv) + "]")

    st, dr = res["step"], res["drift"]
    row(f"step {st['step_px']:g} px detected within one window", st["detected"], st["interval"]["detected"])
    row("  naming the right camera", st["right_camera"], st["interval"]["right_camera"])
    row("  delay (windows)", st["delay_windows"], st["interval"]["delay_windows"], "{:.2f}")
    row(f"drift {dr['drift_px_per_year']:g} px/yr flagged before 1/16 px", dr["flagged"], dr["interval"]["flagged"])
    row("  drift when flagged (px)", dr["px_when_flagged"], dr["interval"]["px_when_flagged"], "{:.3f}")
    row(f"false alarms (configured {res['alpha']:.0%})", res["false_alarm_rate"], res["interval"]["false_alarm_rate"])
    console.print(table)


@app.command("cgm")
@handle_errors
def bench_cgm(
    passes: int = typer.Option(6, "--passes", help="Repeat passes before and after the step."),
    window_days: int = typer.Option(30, "--window-days", help="Days of GCP passes in each calibration window."),
    gcps: int = typer.Option(120, "--gcps", help="GCPs in the simulated world."),
    step_camera: str = typer.Option("Da", "--step-camera", help="The camera whose delta steps."),
    step_px: float = typer.Option(0.1, "--step-px", help="Size of the step (px, pointing RMS over the swath)."),
    seed: int = typer.Option(0, "--seed", help="First seed."),
    workdir: Optional[Path] = typer.Option(None, "--workdir", help="Keep the scenarios here (a rerun reuses them)."),
    as_json: bool = typer.Option(False, "--json", help="Print the result as JSON (with its provenance)."),
    save: Optional[Path] = typer.Option(None, "--save", help=SAVE_HELP),
) -> None:
    """Passes after a camera step adjusted with the new camera-model version (picked by orbit
    from a store) and with the stale one, paired pass by pass: check points (m), the stepped
    camera's co-registration (px) and the camera NEES, with 95 % intervals; passes before the
    step beside them."""
    from misrgraph.bench.cgm import run_bench_cgm

    with err_console.status("cgm...") as st:
        res = run_bench_cgm(
            passes, window_days, gcps, step_camera, step_px, seed=seed, workdir=workdir, progress=lambda m: st.update(m)
        )
    res = finish(res, save)
    if as_json:
        print_json(res)
        return
    s = res["step"]
    table = Table(title=f"{s['camera']} steps by {s['px']:g} px on {s['date']}: {res['passes']} passes each")
    for col in ("", "check points (m)", f"{s['camera']} co-registration (px)", "camera NEES"):
        table.add_column(col, justify="right")
    from misrgraph.bench.cgm import ROWS

    for key, name in ROWS:
        v = res[key]
        table.add_row(
            name,
            *(
                f"{v[k]['mean']:.3f} [{v[k]['ci95'][0]:.3f}, {v[k]['ci95'][1]:.3f}]"
                for k in ("checkpoint_rms_m", "coregistration_px", "camera_nees")
            ),
        )
    console.print(table)
