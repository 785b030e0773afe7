"""Solvers compared at equal accuracy of the estimate (``misrgraph bench sba``) and the cost of an
incremental update against a warm-started batch (``misrgraph bench incremental``).

Accuracy is a distance from an optimum that is verified independently of every solver's own
stopping rule: the lowest-cost end point any solver reached, polished by the core to a tight
criterion, where the undamped Gauss-Newton step (:func:`~misrgraph.estimate.solver.gauss_newton_step`)
is checked to be negligible in sigma units. Distances are in sigma units of the marginal
covariance at that optimum: the largest over the attitude knots and ephemeris parameters
(``max_sigma``) and the Mahalanobis norm over the whole state (``||J* (x - x*)||``, ``J*`` the
whitened Jacobian at the optimum).

Times come from one run per solver on a shared machine: read them as ratios, not absolutes.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from misrgraph.bench.studies import standard_pass
from misrgraph.bench.work import bench_workdir
from misrgraph.estimate.graph import GraphConfig, build_pass_graph, merge_flat
from misrgraph.estimate.incremental import DEFAULT_SETTLE_AFTER
from misrgraph.estimate.solver import SolverParams, gauss_newton_step, solve
from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

__all__ = ["SIGMA_LEVELS", "run_bench_sba", "run_bench_incremental"]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]

#: the accuracy levels (sigma units) at which the solvers' times are reported
SIGMA_LEVELS = (1.0, 0.3, 0.1, 0.03)

#: the optimum is accepted as verified when the Gauss-Newton step there is below this (sigma)
VERIFIED_STEP_SIGMA = 1e-3

#: labels of the solvers of ``bench sba``
SOLVER_LABELS = {
    "misrgraph": "misrgraph core (Schur, second-order DEM term near convergence)",
    "misrgraph_gauss_newton": "misrgraph core, Gauss-Newton only",
    "gtsam_lm": "gtsam.LevenbergMarquardtOptimizer on the Python CustomFactors (the design card's baseline)",
    "scipy_trf": "scipy least_squares TRF, sparse J, LSMR, x_scale='jac'",
    "scipy_trf_unscaled": "scipy least_squares TRF, sparse J, LSMR, x_scale=1",
    "scipy_trust_krylov": "scipy minimize trust-krylov, J^T J + DEM curvature (second order)",
    "ceres": "Ceres (pyceres), DENSE_SCHUR, per-landmark cost functions on the pure functions",
    "ceres_batched": "Ceres (pyceres), SPARSE_NORMAL_CHOLESKY (SuiteSparse), one cost function per "
    "16 landmarks on the pure functions",
}

#: landmarks per Ceres cost function of ``ceres_batched`` (16 and 32 are the fastest per
#: iteration on the standard pass; larger groups fill the normal equations with coupled landmarks,
#: one per landmark with DENSE_SCHUR is slower still)
CERES_GROUP = 16


def _level_key(level: float) -> str:
    return f"{level:g}"


class _Budget(Exception):
    """Raised inside a solver's callback when its time budget is spent."""


class _Trace:
    """Improving iterates of one solver run: (seconds, cost, x). The time spent recording is
    not counted in the seconds."""

    def __init__(self, budget_s: float) -> None:
        self.budget_s = budget_s
        self.t0 = time.perf_counter()
        self.paused = 0.0
        self.points: list[tuple[float, float, Array]] = []

    def seconds(self) -> float:
        return time.perf_counter() - self.t0 - self.paused

    def add(self, x: Array, cost: float, check_budget: bool = True) -> None:
        t_in = time.perf_counter()
        now = t_in - self.t0 - self.paused
        if np.isfinite(cost) and (not self.points or cost < self.points[-1][1]):
            self.points.append((now, float(cost), np.array(x, dtype=float, copy=True)))
        self.paused += time.perf_counter() - t_in
        if check_budget and now > self.budget_s:
            raise _Budget()


class _Metric:
    """Distances from the optimum ``x_ref`` in its marginal sigmas (module docstring); the
    marginals are computed once, the whitened Jacobian there when first needed."""

    def __init__(self, flat: Any, x_ref: Array, nav_keys: list[int] | None = None) -> None:
        from misrgraph.estimate.problem import flat_marginals

        self.flat, self.x_ref = flat, x_ref
        m = flat_marginals(flat, x_ref)
        self.sigma = np.concatenate([np.sqrt(np.diag(m[k])) for k in flat.keys])
        keys = flat.keys if nav_keys is None else nav_keys
        self.idx = np.concatenate([np.arange(flat.offset[k], flat.offset[k] + flat.problem.dims[k]) for k in keys])
        self._jac: Any = None

    @property
    def jac(self) -> Any:
        if self._jac is None:
            self._jac = self.flat.jacobian(self.x_ref)
        return self._jac

    def max_sigma(self, x: Array) -> float:
        """Largest |x - x*| / sigma over the chosen keys (the knots and ephemeris parameters in
        ``bench sba``; every variable when none were chosen)."""
        return float(np.max(np.abs(x[self.idx] - self.x_ref[self.idx]) / self.sigma[self.idx]))

    def mahalanobis(self, x: Array) -> float:
        """sqrt((x - x*)^T J*^T J* (x - x*)) over the whole state."""
        return float(np.linalg.norm(self.jac @ (x - self.x_ref)))

    def gauss_newton_step(self) -> tuple[float, Array]:
        """The undamped Gauss-Newton step ``d`` at ``x_ref`` (the verification of the optimum):
        its largest |d| / sigma over every variable, and ``d`` itself."""
        d = gauss_newton_step(self.flat, self.x_ref)
        return float(np.max(np.abs(d) / self.sigma)), d


def _verified_optimum(
    flat: Any, prob: Any, candidates: list[Array], nav_keys: list[int]
) -> tuple[_Metric, dict[str, Any]]:
    """The lowest-cost of the candidates' end points after a tight polish by the core, as the
    metric of distances from it, with the Gauss-Newton step there in sigma units (the check)."""
    tight = SolverParams(relative_error_tol=1e-14, absolute_error_tol=1e-14, max_iterations=100, backend="schur")
    best: tuple[float, Array] | None = None
    for x in candidates:
        res = solve(prob, tight, initial=flat.to_values(x))
        for b in prob.batches:
            b.clear()
        xp = flat.from_values(res.values)
        c = flat.cost(xp)
        if best is None or c < best[0]:
            best = (c, xp)
    assert best is not None
    cost, x_ref = best
    metric = _Metric(flat, x_ref, nav_keys)
    step_sigma, d = metric.gauss_newton_step()
    check = {
        "cost": cost,
        "gauss_newton_step_max_sigma": step_sigma,
        "gauss_newton_step_mahalanobis": metric.mahalanobis(x_ref + d),
        "verified": step_sigma <= VERIFIED_STEP_SIGMA,
        "criterion_sigma": VERIFIED_STEP_SIGMA,
    }
    if not check["verified"]:
        log.warning(
            "the reference optimum is not verified: Gauss-Newton step %.2g sigma > %.0e",
            step_sigma,
            VERIFIED_STEP_SIGMA,
        )
    return metric, check


def _first_time(points: list[tuple[float, float, Array]], dist: list[float], level: float) -> float | None:
    for (t, _, _), d in zip(points, dist):
        if d <= level:
            return float(t)
    return None


def run_bench_sba(
    tie_points: int = 2000,
    seed: int = 0,
    workdir: str | Path | None = None,
    skip: tuple[str, ...] = (),
    budget_s: float = 60.0,
    check_points: int = 200,
    duration_s: float = 2700.0,
) -> dict[str, Any]:
    """Solvers at equal accuracy of the estimate on the standard pass (issue 20).

    Every solver minimises the same cost (least squares, DEM on) from the same start with a tight
    criterion (relative decrease 1e-10) and at most ``budget_s`` seconds. Its improving iterates
    are recorded; afterwards (untimed) each is measured against the verified optimum (module
    docstring). Per solver: ``seconds_to_sigma`` (first time ``max_sigma`` <= level, for
    :data:`SIGMA_LEVELS`; None if never), ``seconds_to_mahalanobis`` (the same for the whole-state
    norm) and ``stop`` (its own end point: seconds, max_sigma, mahalanobis, cost, and the
    check-point RMS (m) and co-registration (px) of the products made from it). Marginals are
    timed once, with the project's one routine, at the optimum (they cost the same whoever found
    the point). ``skip``: solver names of :data:`SOLVER_LABELS` to leave out.
    """
    import gtsam

    from misrgraph.estimate.adjust import estimated_models
    from misrgraph.estimate.backends import solve_ceres, solve_scipy, solve_scipy_newton
    from misrgraph.estimate.problem import flat_marginals
    from misrgraph.estimate.solver import gtsam_lm_params
    from misrgraph.evaluate.score import geolocation_errors

    unknown = [s for s in skip if s not in SOLVER_LABELS]
    if unknown:
        from misrgraph.errors import InputError

        raise InputError("skip", unknown, f"solver names among {sorted(SOLVER_LABELS)}")
    with bench_workdir(workdir) as wd:
        sc, p = standard_pass(tie_points, seed, wd, duration_s, check_points)
        truth = sc.load_truth(0)
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig())
    prob = pg.problem
    flat = prob.flat()
    # warm-up, not timed: numba compilation or cache load, first-call costs of the kernels
    solve(prob, SolverParams(max_iterations=2, backend="schur"))
    for b in prob.batches:
        b.clear()
    tight = SolverParams(relative_error_tol=1e-10, absolute_error_tol=1e-10, max_iterations=200)
    runs: dict[str, dict[str, Any]] = {}
    x0 = flat.initial()

    def record(name: str, fn: Callable[[_Trace], str]) -> None:
        if name in skip:
            return
        tr = _Trace(budget_s)
        tr.add(x0, flat.cost(x0), False)
        try:
            ended = fn(tr)
        except _Budget:
            ended = f"time budget ({budget_s:g} s)"
        finally:
            for b in prob.batches:
                b.clear()
        runs[name] = {"trace": tr, "run_seconds": tr.seconds(), "ended": ended}
        log.info("bench sba: %s ended (%s) after %.1f s", name, ended, tr.seconds())

    def core(params: SolverParams) -> Callable[[_Trace], str]:
        def go(tr: _Trace) -> str:
            err: list[float] = []  # progress(it, cost, lambda) comes just before on_iterate(x)
            res = solve(prob, params, progress=lambda i, c, lam: err.append(c), on_iterate=lambda x: tr.add(x, err[-1]))
            return res.status

        return go

    record("misrgraph", core(tight.replace(backend="schur")))
    record("misrgraph_gauss_newton", core(tight.replace(backend="schur", dem_second_order=False)))

    def gtsam_lm(tr: _Trace) -> str:
        opt = gtsam.LevenbergMarquardtOptimizer(prob.graph, prob.initial, gtsam_lm_params(prob, tight))
        prev, it = opt.error(), 0
        while it < tight.max_iterations:
            opt.iterate()
            it += 1
            err = opt.error()
            tr.add(flat.from_values(opt.values()), err)
            if prev - err <= tight.relative_error_tol * prev:
                return "converged"
            prev = err
        return "iteration limit"

    record("gtsam_lm", gtsam_lm)

    def scipy_trf(x_scale: str | float) -> Callable[[_Trace], str]:
        def go(tr: _Trace) -> str:
            res = solve_scipy(flat, ftol=1e-10, max_nfev=1000, x_scale=x_scale, on_point=lambda x, c: tr.add(x, c))
            return f"scipy status {res['status']}"

        return go

    record("scipy_trf", scipy_trf("jac"))
    record("scipy_trf_unscaled", scipy_trf(1.0))

    def trust_krylov(tr: _Trace) -> str:
        res = solve_scipy_newton(flat, gtol=1e-8, max_iterations=500, on_point=lambda x, c: tr.add(x, c))
        return f"scipy status {res['status']}"

    record("scipy_trust_krylov", trust_krylov)
    skipped: dict[str, str] = {}
    if not {"ceres", "ceres_batched"} <= set(skip):
        try:
            import pyceres  # noqa: F401
        except ImportError:
            for name in {"ceres", "ceres_batched"} - set(skip):
                skipped[name] = "pyceres is not installed (pip install 'misrgraph[bench]')"
        else:

            def ceres(tr: _Trace) -> str:
                res = solve_ceres(
                    flat,
                    ftol=1e-10,
                    max_iterations=500,
                    max_seconds=budget_s,
                    on_point=lambda x, c: tr.add(x, c, False),
                )
                return res["report"]

            record("ceres", ceres)

            def ceres_batched(tr: _Trace) -> str:
                res = solve_ceres(
                    flat,
                    ftol=1e-10,
                    max_iterations=500,
                    max_seconds=budget_s,
                    group=CERES_GROUP,
                    linear_solver="SPARSE_NORMAL_CHOLESKY",
                    on_point=lambda x, c: tr.add(x, c, False),
                )
                return res["report"]

            record("ceres_batched", ceres_batched)
    # the verified optimum, from every solver's end point (untimed)
    ends = sorted(runs.items(), key=lambda kv: kv[1]["trace"].points[-1][1])
    nav = [k for a in range(3) for k in pg.knot_keys(a)] + pg.ephemeris_keys()
    metric, check = _verified_optimum(flat, prob, [r["trace"].points[-1][2] for _, r in ends[:2]], nav)
    x_ref = metric.x_ref
    t0 = time.perf_counter()
    flat_marginals(flat, x_ref)
    marginal_seconds = time.perf_counter() - t0

    def products(x: Array) -> dict[str, float | None]:
        att, eph, cam = estimated_models(pg, flat.to_values(x), sc.camera_model)
        return geolocation_errors(p, truth, att, eph, cam)

    results: dict[str, Any] = {}
    for name, r in runs.items():
        pts = r["trace"].points
        ms = [metric.max_sigma(x) for _, _, x in pts]
        mh = [metric.mahalanobis(x) for _, _, x in pts]
        x_end = pts[-1][2]
        results[name] = {
            "label": SOLVER_LABELS[name],
            "seconds_to_sigma": {_level_key(lv): _first_time(pts, ms, lv) for lv in SIGMA_LEVELS},
            "seconds_to_mahalanobis": {_level_key(lv): _first_time(pts, mh, lv) for lv in SIGMA_LEVELS},
            "stop": {
                "seconds": r["run_seconds"],
                "ended": r["ended"],
                "cost": pts[-1][1],
                "max_sigma": ms[-1],
                "mahalanobis": mh[-1],
                "improving_iterates": len(pts) - 1,
                **products(x_end),
            },
        }
    for name, why in skipped.items():
        results[name] = {"label": SOLVER_LABELS[name], "skipped": why}
    core_t = results.get("misrgraph", {}).get("seconds_to_sigma", {}).get("0.1")
    ratios: dict[str, float | None] = {}
    bounds: list[str] = []
    for name, r in results.items():
        if name == "misrgraph" or "seconds_to_sigma" not in r or core_t is None:
            continue
        t = r["seconds_to_sigma"]["0.1"]
        if t is not None:
            ratios[name] = t / core_t
        elif runs[name]["ended"].startswith("time budget"):
            ratios[name] = r["stop"]["seconds"] / core_t  # cut by its budget: its whole run is a lower bound
            bounds.append(name)
        else:
            ratios[name] = None  # stopped by its own rule before getting there: it never does
    peers = [n for n in ratios if not n.startswith("misrgraph")]
    return {
        "tie_points": tie_points,
        "check_points": check_points,
        "variables": len(prob.dims),
        "unknowns": flat.n,
        "observations": len(pg.collinearity),
        "budget_seconds": budget_s,
        "sigma_levels": [_level_key(v) for v in SIGMA_LEVELS],
        "reference": {**check, **products(x_ref)},
        "marginals": {
            "seconds": marginal_seconds,
            "routine": "flat_marginals (sparse Schur), the same for every solver",
        },
        "solvers": results,
        "ratio_to_core_at_0.1_sigma": ratios,
        "ratios_that_are_lower_bounds": bounds,
        "never_within_0.1_sigma": [n for n, v in ratios.items() if v is None],
        "core_at_least_3x_faster_than_every_peer_at_0.1_sigma": (
            bool(peers) and core_t is not None and all(ratios[n] is None or ratios[n] >= 3.0 for n in peers)
        ),
    }


def run_bench_incremental(
    passes: int = 10,
    tie_points: int = 150,
    seed: int = 0,
    workdir: str | Path | None = None,
    linearization_tol: float | None = None,
    settle_after: int | None = DEFAULT_SETTLE_AFTER,
) -> dict[str, Any]:
    """iSAM2 update per pass against a warm-started batch, over ``passes`` repeat passes (issue 20).

    ``settle_after``: :class:`~misrgraph.estimate.incremental.IncrementalSolver`'s (None: every
    factor stays live).

    For every k: the seconds of adding pass k to the iSAM2 state (``update_seconds``); the batch
    re-solve of all k passes (``batch_seconds``) -- the LM core on the Schur backend
    (:func:`~misrgraph.estimate.graph.merge_flat`), warm-started from its own estimate after pass
    k - 1 (pass k's variables at their ray-cast start), stopped once an iterate is within the
    iSAM2 estimate's own distance from the optimum (equal accuracy; at least its first
    iteration is timed); and ``max_difference_sigma``, the iSAM2 estimate's largest distance
    from the tightly converged batch (verified like ``bench sba``'s optimum) over every variable,
    in marginal sigmas of that batch. The batch runs once per pass, to a tight criterion, with its
    iterates recorded; its end point is the optimum (verified by the Gauss-Newton step there,
    ``optimum_gauss_newton_step_sigma``), and ``batch_seconds`` is the time of its first iterate
    within the target. Recording, marginals and distances are not timed, nor is building the
    batch's problem (the merge of the pass graphs iSAM2 built; the iSAM2 update's seconds include
    building its pass graph), which favours the batch.
    """
    from misrgraph.estimate.adjust import AdjustConfig
    from misrgraph.estimate.incremental import DEFAULT_LINEARIZATION_TOL, IncrementalSolver

    tol = DEFAULT_LINEARIZATION_TOL if linearization_tol is None else linearization_tol
    cfg = AdjustConfig()
    with bench_workdir(workdir) as wd:
        out = wd / f"path_{passes}_{tie_points}_{seed}"
        if not (out / "scenario.json").exists():
            run_simulate(
                ScenarioConfig(
                    truth="model",
                    scenario="path",
                    seed=seed,
                    n_passes=passes,
                    n_tie_points=tie_points,
                    n_check_points=0,
                    duration_s=900.0,
                    start_lat_deg=55.0,
                ),
                out,
            )
        sc = load_scenario(out)
        orbit_passes = [sc.load_pass(k) for k in range(len(sc.pass_files))]
    solver = IncrementalSolver(sc.camera_model, sc.gcps, sc.dem, cfg, linearization_tol=tol, settle_after=settle_after)
    tight = SolverParams(relative_error_tol=1e-14, absolute_error_tol=1e-14, max_iterations=100, backend="schur")
    warm = None
    rows = []
    for k, op in enumerate(orbit_passes):
        update_s = solver.add_passes([op])
        # the batch over the very pass graphs iSAM2 holds (merge_flat builds new batches from them)
        prob = merge_flat([g.problem for g in solver.graphs])
        flat = prob.flat()
        # one tight solve from the warm start, its iterates recorded (the recording is not timed)
        start = prob.initial if warm is None else _values_with(prob.initial, warm)
        tr = _Trace(float("inf"))
        tr.add(flat.from_values(start), flat.cost(flat.from_values(start)), False)
        err: list[float] = []
        res = solve(
            prob,
            tight,
            initial=start,
            progress=lambda i, c, lam: err.append(c),
            on_iterate=lambda x: tr.add(x, err[-1], False),
        )
        whole = tr.seconds()
        for b in prob.batches:
            b.clear()
        warm = res.values
        # its end point is the optimum, verified by the Gauss-Newton step there (untimed)
        metric = _Metric(flat, flat.from_values(res.values))
        step_sigma, _ = metric.gauss_newton_step()
        isam_dist = metric.max_sigma(flat.from_values(solver.estimate))
        # the batch's time: its first iterate as close to the optimum as the iSAM2 estimate
        target = max(isam_dist, 1e-3)
        dist = [metric.max_sigma(x) for _, _, x in tr.points]
        hit = _first_time(tr.points[1:], dist[1:], target)  # at least one iteration
        rows.append(
            {
                "pass": k + 1,
                "update_seconds": update_s,
                "batch_seconds": whole if hit is None else hit,
                "batch_reached_target": hit is not None,
                "batch_iterations": res.iterations,
                "max_difference_sigma": isam_dist,
                "optimum_gauss_newton_step_sigma": step_sigma,
                "relinearization_rounds": solver.last_rounds,
                "linearization_error_sigma": solver.last_linearization_error,
            }
        )
        log.info(
            "bench incremental: pass %d: update %.3f s, batch %.3f s, iSAM2 %.4f sigma from the optimum",
            k + 1,
            update_s,
            rows[-1]["batch_seconds"],
            isam_dist,
        )
    by_pass = {r["pass"]: r for r in rows}
    marks = [k for k in (10, 25, 50) if k in by_pass] or [rows[-1]["pass"]]
    return {
        "passes": len(rows),
        "tie_points": tie_points,
        "linearization_tol": tol,
        "settle_after": settle_after,
        "per_pass": rows,
        "at": {
            str(k): {
                "update_seconds": by_pass[k]["update_seconds"],
                "batch_seconds": by_pass[k]["batch_seconds"],
                "update_over_batch": by_pass[k]["update_seconds"] / by_pass[k]["batch_seconds"],
            }
            for k in marks
        },
        "update_last_over_update_10": (rows[-1]["update_seconds"] / by_pass[10]["update_seconds"])
        if 10 in by_pass
        else None,
        "max_difference_sigma_worst": max(r["max_difference_sigma"] for r in rows),
    }


def _values_with(initial: Any, previous: Any) -> Any:
    """``initial`` with every variable that ``previous`` holds replaced by its value there."""
    import gtsam

    out = gtsam.Values()
    for key in initial.keys():
        k = int(key)
        out.insert(k, previous.atVector(k) if previous.exists(k) else initial.atVector(k))
    return out
