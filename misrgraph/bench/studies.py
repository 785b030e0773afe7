"""``misrgraph bench ...``: speed measured as ratios against a baseline run in the same process.

Never used by the tests for timing assertions (machines are shared and noisy); the tests only
check that the commands run and report consistent figures.
"""

from __future__ import annotations

import hashlib
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.bench.work import bench_workdir
from misrgraph.estimate.graph import GraphConfig, build_pass_graph
from misrgraph.estimate.solver import SolverParams, linearize, solve, solve_gtsam_lm
from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

__all__ = [
    "run_bench_solver",
    "run_bench_scaling",
    "run_bench_nees",
    "pool_bench_nees",
    "run_bench_sources",
    "standard_pass",
    "MODEL_TRUTH_ADJUST",
    "POOL_KEYS",
    "SOURCE_CLASSES",
]

log = logging.getLogger(__name__)


def standard_pass(tie_points: int, seed: int, workdir: Path, duration_s: float = 2700.0, check_points: int = 0):
    """Simulate (or reuse) the standard pass scenario with ``tie_points`` tie points (and
    ``check_points`` check points, which only score the products)."""
    out = workdir / (f"pass_{tie_points}_{seed}_{int(duration_s)}" + (f"_c{check_points}" if check_points else ""))
    if not (out / "scenario.json").exists():
        run_simulate(
            ScenarioConfig(
                truth="model",
                scenario="pass",
                seed=seed,
                n_tie_points=tie_points,
                n_check_points=check_points,
                duration_s=duration_s,
            ),
            out,
        )
    sc = load_scenario(out)
    return sc, sc.load_pass(0)


def _time(fn: Callable[[], Any], repeat: int = 3) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return float(best)


def run_bench_solver(
    tie_points: int = 1000, seed: int = 0, workdir: str | Path | None = None, skip_gtsam: bool = False
) -> dict[str, Any]:
    """Core vs ``gtsam.LevenbergMarquardtOptimizer`` on one simulated pass, same graph and criterion.

    Also measures the linearisation strategies: GTSAM calling live per-observation and
    per-landmark ``CustomFactor`` callbacks from Python, and the vectorised cache (the core).
    """
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="misrgraph-bench-")
        workdir = tmp.name
    sc, p = standard_pass(tie_points, seed, Path(workdir))
    params = SolverParams()
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig())
    prob = pg.problem
    core = solve(prob, params)
    out: dict[str, Any] = {
        "tie_points": tie_points,
        "variables": len(prob.dims),
        "factors": int(prob.graph.size()),
        "observations": len(pg.collinearity),
        "core": {
            "seconds": core.seconds,
            "final_cost": core.final_error,
            "iterations": core.iterations,
            "seconds_per_linearize": core.linearize_seconds / max(core.n_linearize, 1),
            "seconds_per_iteration": core.seconds / max(core.iterations, 1),
        },
    }
    # linearisation strategies on the same values
    v = prob.initial
    per_obs = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(group_by="observation")).problem
    strategies = {
        "vectorised_cache_per_landmark": _time(lambda: linearize(prob, v)),
        "live_callbacks_per_landmark": _time(lambda: prob.graph.linearize(v), 1),
        "live_callbacks_per_observation": _time(lambda: per_obs.graph.linearize(per_obs.initial), 1),
    }
    out["linearize_seconds"] = strategies
    if not skip_gtsam:
        ref = solve_gtsam_lm(prob, params)
        out["gtsam_lm"] = {
            "seconds": ref.seconds,
            "final_cost": ref.final_error,
            "iterations": ref.iterations,
            "seconds_per_iteration": ref.seconds / max(ref.iterations, 1),
        }
        out["ratio_gtsam_lm_over_core"] = ref.seconds / core.seconds
        out["relative_cost_difference"] = abs(ref.final_error - core.final_error) / ref.final_error
    if tmp is not None:
        tmp.cleanup()
    return out


def run_bench_scaling(
    sizes: tuple[int, ...] = (250, 500, 1000, 2000, 4000),
    seed: int = 0,
    workdir: str | Path | None = None,
    duration_s: float = 2700.0,
) -> dict[str, Any]:
    """Time per pass (solve + knot marginals, Schur backend) against tie points, fitted exponent, memory.

    Each size is solved twice from the same start: once timed, and once under ``tracemalloc`` for
    the peak of Python allocations (``tracemalloc`` slows the Python parts about twofold, so it
    stays out of the timed run)."""
    import resource
    import tracemalloc

    from misrgraph.estimate.problem import flat_marginals

    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="misrgraph-bench-")
        workdir = tmp.name
    rows = []

    def graph(n: int) -> Any:
        sc, p = standard_pass(n, seed, Path(workdir), duration_s)
        return build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig())

    def run(pg: Any) -> Any:  # what is timed and traced: the solve and the marginals
        res = solve(pg.problem, SolverParams(backend="schur"))
        flat = pg.problem.flat()
        flat_marginals(flat, flat.from_values(res.values))
        return res

    run(graph(sizes[0]))  # warm-up (numba compilation or cache load, imports) outside the timed runs
    for n in sizes:
        pg = graph(n)
        t0 = time.perf_counter()
        res = run(pg)
        dt = time.perf_counter() - t0
        fresh = graph(n)
        tracemalloc.start()
        try:
            run(fresh)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        rows.append(
            {
                "tie_points": n,
                "observations": len(pg.collinearity),
                "seconds": dt,
                "iterations": res.iterations,
                "seconds_per_iteration": dt / max(res.iterations, 1),
                "peak_python_mb": peak / 2**20,
            }
        )
    x = np.log([r["observations"] for r in rows])
    y = np.log([r["seconds_per_iteration"] for r in rows])
    slope = float(np.polyfit(x, y, 1)[0]) if len(rows) > 1 else float("nan")
    yt = np.log([r["seconds"] for r in rows])
    slope_total = (
        float(np.polyfit(np.log([r["tie_points"] for r in rows]), yt, 1)[0]) if len(rows) > 1 else float("nan")
    )
    if tmp is not None:
        tmp.cleanup()
    return {
        "rows": rows,
        "exponent_per_iteration_vs_observations": slope,
        "exponent_total_vs_tie_points": slope_total,
        "process_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


#: the scenario of each study and size: reduced (the suite's size) and standard (what users run)
NEES_SCENARIOS = {
    ("calibration", "reduced"): dict(scenario="month", n_gcps=24, month_days=16),
    ("calibration", "standard"): dict(scenario="month"),
    ("adjust", "reduced"): dict(
        scenario="pass", n_tie_points=80, n_check_points=20, duration_s=600.0, start_lat_deg=50.0
    ),
    ("adjust", "standard"): dict(scenario="pass", n_tie_points=600, n_check_points=20, duration_s=2700.0),
}


def _rms_interval(values: list[float]) -> dict[str, Any]:
    """For per-run ratios of an actual RMS over a predicted one: their RMS over the runs and its
    95 % interval (the Student-t interval of the squared ratios, square-rooted). The squared ratio
    has expectation 1 when the prediction is honest; the ratio itself does not (a run whose check
    points share one navigation error has few effective degrees of freedom ``k``, and
    ``E[sqrt(chi2_k / k)]`` is 0.92 for ``k = 3``), so the mean of the ratios is biased low."""
    iv = _interval([float(v) ** 2 for v in values])
    return {
        "rms": float(np.sqrt(iv["mean"])),
        "ci95": [float(np.sqrt(max(b, 0.0))) if np.isfinite(b) else float("nan") for b in iv["ci95"]],
    }


def _interval(values: list[float]) -> dict[str, float]:
    """Mean and its 95 % interval from the run-to-run scatter (Student t)."""
    from scipy import stats

    v = np.asarray(values, float)
    if v.size < 2:
        return {"mean": float(v.mean()), "ci95": [float("nan"), float("nan")]}
    half = float(stats.t.ppf(0.975, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size))
    return {"mean": float(v.mean()), "ci95": [float(v.mean() - half), float(v.mean() + half)]}


#: the adjustment settings ``bench nees`` changes under the model truth, which has no attitude
#: error faster than the knots: no fast attitude noise added to the predicted geolocation sigma
#: (the DEM is weighted at its stated sigma by default, as that truth draws it)
MODEL_TRUTH_ADJUST: dict[str, Any] = {"attitude_jitter_arcsec": 0.0}


#: the NEES classes of an adjustment (:func:`misrgraph.evaluate.score.score_pass`): the whole
#: state also split exactly into the landmarks given the other variables and those jointly, and
#: the landmarks into what those seen within 300 s of each other share and what each has alone
#: (:mod:`misrgraph.evaluate.landmarks`)
NEES_CLASSES = (
    "knots",
    "ephemeris",
    "camera",
    "landmarks",
    "landmarks_common",
    "landmarks_within",
    "state",
    "state_landmarks_given_rest",
    "state_rest",
)


def run_bench_nees(
    study: str = "calibration",
    runs: int = 20,
    seed: int = 1000,
    workdir: str | Path | None = None,
    size: str = "reduced",
    truth: str = "model",
    overrides: dict[str, Any] | None = None,
    calibrate_params: tuple[str, ...] | None = None,
) -> dict[str, Any]:
    """NEES over seeded runs against its two-sided 95 % chi-square band, per class of variables.

    ``calibration``: months (reduced: 24 GCPs over 16 days; standard: 120 GCPs over 30 days), NEES
    of the 27 camera corrections. ``adjust``: passes (reduced: 10 minutes, 80 tie points, 20 check
    points; standard: 45 minutes, 600 tie points, 20 check points), NEES of the knots (joint),
    the ephemeris (joint), the camera corrections, the landmarks (also split into the mean error
    of the landmarks within 300 s of each other and each one's deviation from it, with their full
    joint covariance: :mod:`misrgraph.evaluate.landmarks`) and the whole state (also split
    into the landmarks given the other variables' errors and those others jointly,
    :data:`NEES_CLASSES`), and with
    check points their actual RMS over the RMS the covariance predicts (over all cameras, and per
    camera in ``by_camera``: the RMS of the runs' ratios with its interval). Per class: the pooled
    NEES/dim with its chi-square band (which assumes independent runs and, for landmarks,
    independent landmarks) and the mean of the per-run values with a 95 % interval from the
    run-to-run scatter (which assumes neither). ``truth``: the simulator's truth (``"model"`` or
    ``"independent"``, :class:`misrgraph.sim.simulate.ScenarioConfig`); under an independent truth
    the ephemeris and whole-state NEES are not defined (no true value of the estimator's own
    parameters) and are left out. ``overrides``: further :class:`ScenarioConfig` fields (e.g. one
    error source of the independent truth switched off, :func:`run_bench_sources`).
    ``calibrate_params``: the camera parameters the calibration estimates (default its own).

    The adjustment runs with its defaults, except under the model truth (:data:`MODEL_TRUTH_ADJUST`):
    that truth has no attitude error faster than the knots, so the check points' predicted sigma
    adds no fast attitude noise. The result names the settings it changed (``adjust_overrides``).
    """
    from misrgraph.errors import InputError
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.runs.calibrate import run_calibrate

    if study not in ("calibration", "adjust"):
        raise InputError("study", study, ("calibration", "adjust"))
    if size not in ("reduced", "standard"):
        raise InputError("size", size, ("reduced", "standard"))
    from misrgraph.estimate.adjust import AdjustConfig

    adjust_overrides = dict(MODEL_TRUTH_ADJUST) if truth == "model" else {}
    adjust_cfg = AdjustConfig.from_dict(adjust_overrides)
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="misrgraph-bench-")
        workdir = tmp.name
    totals: dict[str, list[float]] = {}
    per_class: dict[str, list[float]] = {}
    per_run = []
    for i in range(runs):
        extra = dict(overrides or {})
        tag = "" if not extra else "_" + hashlib.sha256(json.dumps(extra, sort_keys=True).encode()).hexdigest()[:10]
        out = Path(workdir) / f"nees_{study}_{size}_{truth}{tag}_{seed + i}"
        if not (out / "scenario.json").exists():
            run_simulate(
                ScenarioConfig.from_dict(dict(NEES_SCENARIOS[(study, size)], seed=seed + i, truth=truth, **extra)), out
            )
        if study == "calibration":
            from misrgraph.estimate.calibrate import CalibrateConfig

            s = run_calibrate(
                out, cfg=CalibrateConfig(params=tuple(calibrate_params)) if calibrate_params else CalibrateConfig()
            )
            vals = {"camera": (s["nees"], s["nees_dim"])}
            per_run.append({"seed": seed + i, "nees": s["nees"], "max_pointing_error_px": s["max_pointing_error_px"]})
            if "nees_given_others" in s:
                per_class.setdefault("camera_given_others", []).append(s["nees_given_others"])
                per_run[-1]["nees_given_others"] = s["nees_given_others"]
        else:
            s = run_adjust(out, cfg=adjust_cfg)
            vals = {k: (s["nees"][k], s["nees"][f"{k}_dim"]) for k in NEES_CLASSES if k in s["nees"]}
            per_run.append({"seed": seed + i, **{k: v[0] for k, v in vals.items()}})
            if "checkpoint_rms_over_predicted" in s:
                per_class.setdefault("checkpoint_rms_over_predicted", []).append(s["checkpoint_rms_over_predicted"])
                per_run[-1]["checkpoint_rms_over_predicted"] = s["checkpoint_rms_over_predicted"]
                per_run[-1]["checkpoint_by_camera"] = {
                    c: {"rms_m": v["after"]["rms"], "predicted_rms_m": v["after"]["predicted_rms"]}
                    for c, v in s.get("checkpoint_geolocation_m", {}).items()
                    if "predicted_rms" in v["after"]
                }
            cp = _checkpoint_rms_after(s)
            if cp is not None:
                per_class.setdefault("checkpoint_rms_m", []).append(cp)
                per_run[-1]["checkpoint_rms_m"] = cp
        for k, (v, d) in vals.items():
            t = totals.setdefault(k, [0.0, 0])
            t[0] += v * d
            t[1] += d
            per_class.setdefault(k, []).append(v)
    if tmp is not None:
        tmp.cleanup()
    return {
        "study": study,
        "size": size,
        "truth": truth,
        "overrides": dict(overrides or {}),
        "adjust_overrides": adjust_overrides if study == "adjust" else {},
        "calibrate_params": list(calibrate_params) if calibrate_params else None,
        "runs": runs,
        "summary": _nees_summary(totals, per_class, per_run),
        "per_run": per_run,
    }


def _nees_summary(
    totals: dict[str, list[float]], per_class: dict[str, list[float]], per_run: list[dict[str, Any]]
) -> dict[str, Any]:
    """``bench nees``'s summary: per class the pooled NEES/dim (``totals[k]`` = [sum of chi-square,
    sum of dof]) with its chi-square band, and the runs' mean with its interval (``per_class``);
    the check points' ratio also as the RMS of the runs, over all cameras and per camera; a
    calibration's mean squared error of each camera's angle given the others
    (``camera_given_others``, :func:`misrgraph.evaluate.calibration.given_others_z`: correlated
    terms, so only the runs' mean with its interval)."""
    from scipy import stats

    summary: dict[str, Any] = {}
    for k, (chi2, dof) in totals.items():
        lo, hi = stats.chi2.ppf([0.025, 0.975], dof)
        summary[k] = {
            "nees_per_dim": chi2 / dof,
            "band": [lo / dof, hi / dof],
            "inside": bool(lo < chi2 < hi),
            "dof": int(dof),
            "per_run": _interval(per_class[k]),
        }
    for k in ("checkpoint_rms_over_predicted", "checkpoint_rms_m", "camera_given_others"):
        if k in per_class:
            summary[k] = {"per_run": _interval(per_class[k])}
    if "checkpoint_rms_over_predicted" in per_class:
        summary["checkpoint_rms_over_predicted"]["rms_of_runs"] = _rms_interval(
            per_class["checkpoint_rms_over_predicted"]
        )
        by_cam: dict[str, list[float]] = {}
        for r in per_run:
            for c, v in r.get("checkpoint_by_camera", {}).items():
                by_cam.setdefault(c, []).append(v["rms_m"] / v["predicted_rms_m"])
        summary["checkpoint_rms_over_predicted"]["by_camera"] = {
            c: {"runs": len(v), **_rms_interval(v)} for c, v in by_cam.items()
        }
    return summary


#: what must agree between ``bench nees`` results before they are pooled
POOL_KEYS = ("study", "size", "truth", "overrides", "adjust_overrides", "calibrate_params")


def pool_bench_nees(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Pool several ``bench nees`` results (:func:`run_bench_nees`, e.g. held-out seed sets run
    apart) into one, as if their runs had been one study: the pooled NEES/dim sums each class's
    chi-square and dof, the intervals come from the scatter of all runs together.

    The results must share :data:`POOL_KEYS` (the same study, size, truth and settings) and no
    seed may appear twice; otherwise :class:`~misrgraph.errors.InputError` names the field."""
    from misrgraph.errors import InputError

    if len(results) < 1:
        raise InputError("results", len(results), "at least one bench nees result")
    for i, r in enumerate(results):
        missing = [k for k in (*POOL_KEYS, "summary", "per_run") if k not in r]
        if missing:
            raise InputError(f"results[{i}]", missing, "a bench nees result (--json) with these fields")
        bad = [j for j, run in enumerate(r["per_run"]) if not (isinstance(run, dict) and "seed" in run)]
        if bad:
            raise InputError(
                f"results[{i}].per_run", bad, "runs that each name their seed (a bench nees --json output)"
            )
    for k in POOL_KEYS:
        vals = [r[k] for r in results]
        if any(v != vals[0] for v in vals[1:]):
            raise InputError(k, vals, "the same value in every result (pool like with like)")
    seeds = [int(run["seed"]) for r in results for run in r["per_run"]]
    dup = sorted({s for s in seeds if seeds.count(s) > 1})
    if dup:
        raise InputError("seeds", dup, "each seed in one result only (a run pooled twice would count twice)")
    totals: dict[str, list[float]] = {}
    for r in results:
        for k, v in r["summary"].items():
            if "dof" in v:
                t = totals.setdefault(k, [0.0, 0])
                t[0] += v["nees_per_dim"] * v["dof"]
                t[1] += v["dof"]
    per_run = [run for r in results for run in r["per_run"]]
    per_class: dict[str, list[float]] = {}
    for run in per_run:
        for k, v in run.items():
            if k in totals or k in ("checkpoint_rms_over_predicted", "checkpoint_rms_m"):
                per_class.setdefault(k, []).append(float(v))
    counts = {k: len(v) for k, v in per_class.items() if k in totals}
    short = {k: n for k, n in counts.items() if n != len(per_run)}
    if short:
        raise InputError("per_run", short, f"every class in every one of the {len(per_run)} runs")
    return {
        **{k: results[0][k] for k in POOL_KEYS},
        "runs": len(per_run),
        "pooled_from": len(results),
        "summary": _nees_summary(totals, per_class, per_run),
        "per_run": per_run,
    }


def _checkpoint_rms_after(summary: dict[str, Any]) -> float | None:
    """RMS (m) over cameras of the check points' geolocation error after the adjustment."""
    cp = summary.get("checkpoint_geolocation_m") or {}
    n = np.array([v["n"] for v in cp.values() if "rms" in v["after"]], float)
    rms = np.array([v["after"]["rms"] for v in cp.values() if "rms" in v["after"]])
    return float(np.sqrt(np.sum(n * rms**2) / np.sum(n))) if n.size else None


#: the classes ``bench sources`` reports per row (and compares, seed by seed, with its base row)
SOURCE_CLASSES = ("knots", "landmarks", "camera", "checkpoint_rms_over_predicted", "checkpoint_rms_m")


def run_bench_sources(
    runs: int = 10,
    seed: int = 3000,
    workdir: str | Path | None = None,
    size: str = "reduced",
    progress: Callable[[str], None] | None = None,
    mode: str = "alone",
) -> dict[str, Any]:
    """The error-source table: the adjustment under the independent truth, per row the NEES of
    knots, landmarks and camera, the check points' actual/predicted RMS and their RMS error (m),
    each the mean of ``runs`` seeded passes with its 95 % interval. The same seeds in every row.

    ``mode="alone"``: every source of :data:`~misrgraph.sim.simulate.INDEPENDENT_SOURCES` off
    ("none": the attitude and ephemeris processes only), each source alone, and all of them; the
    base row is "none". ``mode="without"``: all of them, and each source switched off from all
    (``"without <source>"``); the base row is "all".

    Each row also carries ``difference``: per class the mean of the per-seed differences from the
    base row with its 95 % interval (the check points' ratio as its square, whose expectation is 1
    when the prediction is honest), and ``paired``: whether the row differs from the base by its
    source alone, draw for draw (:data:`~misrgraph.sim.simulate.PAIRED_SOURCES`). Only then is the
    difference's interval much narrower than the rows' own; for the other sources the other draws
    change too, and the difference carries the scatter of two independent sets of passes."""
    from misrgraph.errors import InputError
    from misrgraph.sim.simulate import INDEPENDENT_SOURCES, PAIRED_SOURCES

    if mode not in ("alone", "without"):
        raise InputError("mode", mode, ("alone", "without"))
    off = dict(INDEPENDENT_SOURCES)
    if mode == "alone":
        base = "none"
        plan = [("none", off, True)] + [(k, {**off, k: getattr(ScenarioConfig(), k)}, k in PAIRED_SOURCES) for k in off]
        plan.append(("all", {}, False))
    else:
        base = "all"
        plan = [("all", {}, True)] + [(f"without {k}", {k: v}, k in PAIRED_SOURCES) for k, v in off.items()]
    rows: dict[str, dict[str, Any]] = {}
    runs_of: dict[str, dict[int, dict[str, Any]]] = {}
    for name, ov, paired in plan:
        if progress:
            progress(f"sources: {name} ({len(rows) + 1}/{len(plan)})")
        r = run_bench_nees("adjust", runs, seed, workdir, size, "independent", ov)
        rows[name] = {k: v["per_run"] for k, v in r["summary"].items() if k in SOURCE_CLASSES}
        if "checkpoint_rms_over_predicted" in r["summary"]:
            rows[name]["checkpoint_rms_over_predicted_rms_of_runs"] = r["summary"]["checkpoint_rms_over_predicted"][
                "rms_of_runs"
            ]
        rows[name]["paired"] = paired
        runs_of[name] = {int(run["seed"]): run for run in r["per_run"]}
    for name in rows:
        if name != base:
            rows[name]["difference"] = _paired_difference(runs_of[name], runs_of[base])
    return {"size": size, "runs": runs, "seed": seed, "mode": mode, "base": base, "rows": rows}


def _paired_difference(row: dict[int, dict[str, Any]], base: dict[int, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per class of :data:`SOURCE_CLASSES`, the mean and 95 % interval of ``row - base`` over the
    seeds both hold (the check points' ratio squared)."""
    out: dict[str, dict[str, Any]] = {}
    seeds = sorted(set(row) & set(base))
    for k in SOURCE_CLASSES:
        both = [s for s in seeds if k in row[s] and k in base[s]]
        if len(both) < 2:
            continue
        p = 2 if k == "checkpoint_rms_over_predicted" else 1
        out[k if p == 1 else f"{k}_squared"] = {
            "runs": len(both),
            **_interval([float(row[s][k]) ** p - float(base[s][k]) ** p for s in both]),
        }
    return out


def run_bench_pp(
    runs: int = 20,
    seed: int = 5000,
    workdir: str | Path | None = None,
    size: str = "reduced",
    truth: str = "model",
    blocks_per_pass: int = 2,
    block_range: str | None = None,
) -> dict[str, Any]:
    """Honesty of the Projection Parameters' 1-sigma over seeded passes (the passes of
    ``bench nees --study adjust`` at ``size``): per run, each camera's PP geolocation RMS against
    the truth over the RMS its 1-sigma predicts, and the mean NEES (per 2 dof) of its pixel
    errors, on ``blocks_per_pass`` blocks around the pass's features (a camera that does not reach
    them in a pass, e.g. Df in most 10-minute passes, is not scored there: ``passes`` counts where
    it was). The points of one pass share
    its navigation error, so honesty is judged from the mean over runs and its 95 % interval from
    the run-to-run scatter (expected 1).

    ``block_range`` (``"A-B"``): score these blocks in every pass instead, and also per block
    (``summary["per_block"][camera][block]``: the RMS over the runs of the pixel error and of its
    predicted 1-sigma, their ratio, and the RMS of the per-run ratios with its interval), to see
    how honest the PP stay where a pass's data end (path 37's passes: blocks 69-71 for Da)."""
    from misrgraph.errors import InputError
    from misrgraph.runs.products import parse_blocks, run_products

    if size not in ("reduced", "standard"):
        raise InputError("size", size, ("reduced", "standard"))
    if block_range is not None:
        parse_blocks(block_range, "--block-range")  # a bad range fails before any pass is simulated
    with bench_workdir(workdir) as workdir:
        per_run = []
        ratio: dict[str, list[float]] = {}
        nees: dict[str, list[float]] = {}
        improvement: dict[str, list[float]] = {}
        by_block: dict[str, dict[int, list[tuple[float, float]]]] = {}
        seconds = []
        for i in range(runs):
            out = Path(workdir) / f"nees_adjust_{size}_{truth}_{seed + i}"
            if not (out / "scenario.json").exists():
                run_simulate(
                    ScenarioConfig.from_dict(dict(NEES_SCENARIOS[("adjust", size)], seed=seed + i, truth=truth)), out
                )
            tag = f"_{block_range.replace(' ', '')}" if block_range else ""
            s = run_products(
                out,
                Path(workdir) / f"pp_{size}_{truth}_{seed + i}{tag}",
                blocks=block_range,
                default_blocks=blocks_per_pass,
            )
            for cam, bb in s.get("pp_error_by_block", {}).items():
                for b, v in bb.items():
                    by_block.setdefault(cam, {}).setdefault(b, []).append((v["error_px_rms"], v["predicted_px_rms"]))
            seconds.append(s["seconds"]["pp"])
            err = s["pp_error_m"]
            for cam, v in err.items():
                ratio.setdefault(cam, []).append(v["rms_over_predicted"])
                nees.setdefault(cam, []).append(v["nees"])
                improvement.setdefault(cam, []).append(v["supplied_rms"] / v["rms"])
            per_run.append(
                {
                    "seed": seed + i,
                    "blocks": s["blocks"],
                    "rms_over_predicted": {c: v["rms_over_predicted"] for c, v in err.items()},
                    "nees": {c: v["nees"] for c, v in err.items()},
                    "rms_m": {c: v["rms"] for c, v in err.items()},
                }
            )
        all_nees = [float(np.mean([r["nees"][c] for c in r["nees"]])) for r in per_run]
        all_ratio = [
            float(np.sqrt(np.mean([r["rms_over_predicted"][c] ** 2 for c in r["rms_over_predicted"]]))) for r in per_run
        ]
    result: dict[str, Any] = {
        "size": size,
        "truth": truth,
        "runs": runs,
        "blocks_per_pass": blocks_per_pass,
        "summary": {
            "nees_all_cameras": _interval(all_nees),
            "rms_over_predicted_all_cameras": _interval(all_ratio),
            "rms_over_predicted_all_cameras_rms_of_runs": _rms_interval(all_ratio),
            "per_camera": {
                c: {
                    "passes": len(ratio[c]),
                    "rms_over_predicted": _interval(ratio[c]),
                    "rms_over_predicted_rms_of_runs": _rms_interval(ratio[c]),
                    "nees": _interval(nees[c]),
                    "improvement_over_supplied": _interval(improvement[c]),
                }
                for c in ratio
            },
            "pp_seconds_per_pass": _interval(seconds),
        },
        "per_run": per_run,
    }
    if block_range:
        out_blocks: dict[str, dict[int, Any]] = {}
        for cam, bb in by_block.items():
            for b, pairs in bb.items():
                e, p = np.array(pairs).T
                out_blocks.setdefault(cam, {})[b] = {
                    "passes": int(e.size),
                    "error_px_rms": float(np.sqrt(np.mean(e**2))),
                    "predicted_px_rms": float(np.sqrt(np.mean(p**2))),
                    "rms_over_predicted": float(np.sqrt(np.sum(e**2) / np.sum(p**2))),
                    "rms_over_predicted_rms_of_runs": _rms_interval((e / p).tolist()),
                }
        result["summary"]["per_block"] = out_blocks
        result["block_range"] = block_range
    return result
