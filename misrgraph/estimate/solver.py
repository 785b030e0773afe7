"""The solver core: Levenberg-Marquardt driven from Python over GTSAM's sparse elimination.

Why (a measured trap): when GTSAM's C++ optimisers call a Python
``CustomFactor`` each call receives a copy of the whole ``Values`` (1.56 s for one LM iteration
of a 2000-landmark graph here), while ``graph.linearize(values)`` called from Python does not
copy. So the core:

1. evaluates every Python factor family at once, vectorised (``batch.evaluate``), and caches
   residuals/Jacobians; the ``CustomFactor`` callbacks then only slice the cache;
2. calls ``graph.linearize(values)`` once per iteration (one C++ call, Python callbacks ~20 us each);
3. adds the LM damping ``sqrt(lambda) I`` per variable and eliminates with GTSAM
   (``GaussianFactorGraph.optimize(ordering)``, COLAMD with the shared cameras last,
   the ordering computed once and reused); or, with ``backend="schur"`` (``"auto"``, the
   default, where the problem allows it), accumulates the normal
   equations directly from the per-observation blocks (:meth:`misrgraph.estimate.problem.Problem.flat`) and solves
   them by a numpy Schur complement on the 3x3 landmark blocks -- no Python callback at all, ~4x faster
   than GTSAM's elimination at 2000 tie points, identical iterates with
   ``dem_second_order=False``; by default it adds the DEM factors' second-order term near the
   minimum (``SolverParams.dem_second_order``; docs/explanation/conventions.md), where Gauss-Newton creeps;
4. accepts/rejects the step and updates lambda exactly as ``gtsam.LevenbergMarquardtOptimizer``
   does (same initial lambda, factor 10, same convergence test), so both reach the same optimum.

Marginal covariances: :mod:`misrgraph.estimate.problem` (one Schur-complement routine for every
solver, equal to ``gtsam.Marginals``).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from misrgraph.config import Config
from misrgraph.errors import ConvergenceError, DegenerateProblemError, InputError
from misrgraph.estimate.problem import Problem, error, linearize

__all__ = [
    "gauss_newton_step",
    "SolverParams",
    "SolveResult",
    "STATUSES",
    "solve",
    "error",
    "linearize",
    "solve_gtsam_lm",
    "gtsam_lm_params",
    "information_norm_split",
    "check_converged",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]


#: Linear-solver backends of :func:`solve`.
BACKENDS = ("auto", "schur", "gtsam")


@dataclass(frozen=True)
class SolverParams(Config):
    """Levenberg-Marquardt settings, with the meaning and defaults of ``gtsam.LevenbergMarquardtParams``."""

    max_iterations: int = 100
    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_upper: float = 1e10
    relative_error_tol: float = 1e-5
    absolute_error_tol: float = 1e-5
    #: ``"auto"`` (the Schur backend where the problem allows it, else GTSAM elimination; the
    #: result's ``backend`` says which ran), ``"schur"`` or ``"gtsam"`` (an explicit choice that
    #: cannot apply is an error, never a silent substitute).
    backend: str = "auto"
    #: Add the DEM factors' second-order term (exact Hessian of the DEM part, see
    #: :meth:`misrgraph.estimate.problem.FlatProblem.normal_equations`) once an accepted step decreased the
    #: cost by less than ``second_order_below`` (relative). Gauss-Newton alone creeps on the DEM's
    #: sub-posting curvature (measured: 60 iterations still 1.5e-5 above the minimum). Only the
    #: Schur backend has it: None = wherever the backend that runs has it; True = required (an
    #: error where it cannot apply); False = never.
    dem_second_order: bool | None = None
    second_order_below: float = 1e-4

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise InputError("backend", self.backend, BACKENDS)
        if self.backend == "gtsam" and self.dem_second_order:
            raise InputError(
                "dem_second_order",
                self.dem_second_order,
                "False or None with backend 'gtsam' (only the Schur backend has the second-order DEM term)",
            )


#: How a solve ended (:attr:`SolveResult.status`).
STATUSES = ("converged", "stalled", "iteration_limit")


#: a small accepted decrease is "stalled", not "converged", when the undamped Gauss-Newton model
#: still predicts this many times the convergence tolerance
STALL_FACTOR = 100.0


@dataclass
class SolveResult:
    """The outcome of a solve. ``status``: ``"converged"`` (an accepted step decreased the cost by
    less than the tolerances and the undamped Gauss-Newton model predicts no more than
    :data:`STALL_FACTOR` times them, or no step decreases it and the model predicts a decrease
    below them: the start is a numerical optimum); ``"stalled"`` (lambda reached its bound, or a
    damped step decreased little, while the model still predicts more: not an optimum); or
    ``"iteration_limit"``. ``converged`` is ``status == "converged"``. ``predicted_decrease``:
    the undamped model's decrease at the end (cost units), where it was evaluated."""

    values: gtsam.Values
    iterations: int
    converged: bool
    final_error: float
    history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    linearize_seconds: float = 0.0
    n_linearize: int = 0
    #: the backend that ran (``"schur"`` or ``"gtsam"``; ``"auto"`` resolved)
    backend: str = ""
    status: str = ""
    predicted_decrease: float | None = None


def _ordering(problem: Problem) -> gtsam.Ordering:
    """GTSAM's COLAMD ordering of the problem's graph with the shared variables
    (``eliminate_last``: the cameras) last. Landmarks first (the classic Schur order) is as good
    for one pass, but where GCP landmarks are shared by many passes (a month of calibration)
    eliminating them first couples every pass's knots: a standard month's step took 1.78 s that
    way and 0.16 s with COLAMD, the same step to 3e-14 (``misrgraph bench calibration``)."""
    return gtsam.Ordering.ColamdConstrainedLastNonlinearFactorGraph(
        problem.graph, [int(k) for k in problem.eliminate_last]
    )


def _damped(lin: gtsam.GaussianFactorGraph, problem: Problem, lam: float) -> gtsam.GaussianFactorGraph:
    g = lin.clone()
    s = np.sqrt(lam)
    for k, d in problem.dims.items():
        g.add(gtsam.JacobianFactor(int(k), s * np.eye(d), np.zeros(d), gtsam.noiseModel.Unit.Create(d)))
    return g


def solve(
    problem: Problem,
    params: SolverParams = SolverParams(),
    initial: gtsam.Values | None = None,
    progress: Callable[[int, float, float], None] | None = None,
    on_iterate: Callable[[Any], None] | None = None,
) -> SolveResult:
    """Minimise the problem's error with Levenberg-Marquardt (see the module docstring).

    ``progress(iteration, cost, lambda)`` and ``on_iterate(x)`` are called after every iteration;
    ``x`` is the current estimate as the backend holds it (the flat vector of
    :meth:`misrgraph.estimate.problem.FlatProblem.from_values` for ``"schur"``, a
    ``gtsam.Values`` for ``"gtsam"``; do not modify it) -- for time-to-accuracy traces.

    ``params.backend`` chooses the linear solver of each step: ``"gtsam"`` (GTSAM's sparse
    elimination of the linearised factor graph, any problem), ``"schur"`` (the vectorised flat
    problem with a numpy Schur complement on the 3x3 landmark blocks; single-pass least squares
    without robust losses, see :mod:`misrgraph.estimate.problem`; :class:`InputError` for any other problem)
    or ``"auto"`` (Schur where it applies, else GTSAM; ``SolveResult.backend`` says which ran).
    Both apply the same damping, acceptance and convergence rules.
    """
    try:
        return _solve(problem, params, initial, progress, on_iterate)
    except _NonFiniteStart:
        _explain_nonfinite_start(problem, initial if initial is not None else problem.initial)
        raise


class _NonFiniteStart(DegenerateProblemError):
    """The cost is not finite at the initial values (explained by :func:`_explain_nonfinite_start`)."""


def _solve(
    problem: Problem,
    params: SolverParams,
    initial: gtsam.Values | None,
    progress: Callable[[int, float, float], None] | None,
    on_iterate: Callable[[Any], None] | None = None,
) -> SolveResult:
    if params.backend in ("schur", "auto"):
        from misrgraph.estimate.problem import NotFlat

        try:
            res = _solve_schur(
                problem,
                params.replace(dem_second_order=params.dem_second_order is not False),
                initial,
                progress,
                on_iterate,
            )
            res.backend = "schur"
            return res
        except NotFlat as exc:
            if params.backend == "schur":
                raise InputError(
                    "backend", "schur", f"'auto' or 'gtsam' for this problem (the Schur backend cannot solve it: {exc})"
                ) from exc
            if params.dem_second_order:
                raise InputError(
                    "dem_second_order",
                    True,
                    f"False or None for this problem (it needs the Schur backend, which cannot solve it: {exc})",
                ) from exc
            log.info("backend auto: GTSAM elimination (the Schur backend cannot solve this problem: %s)", exc)
    params = params.replace(dem_second_order=False)
    values = gtsam.Values(initial if initial is not None else problem.initial)
    ordering = _ordering(problem)

    def step(x: gtsam.Values, lin: gtsam.GaussianFactorGraph, lam: float) -> gtsam.Values:
        try:
            return x.retract(_damped(lin, problem, lam).optimize(ordering))
        except RuntimeError as exc:  # indeterminant system
            raise DegenerateProblemError(
                f"the linear system is singular ({exc}); some variables are not observed"
            ) from exc

    def model_decrease(x: gtsam.Values, lin: gtsam.GaussianFactorGraph) -> float:
        """``0.5 ||b||^2 - 0.5 ||A d - b||^2`` for the undamped Gauss-Newton step ``d``."""
        try:
            d = _damped(lin, problem, 1e-12).optimize(ordering)
        except RuntimeError:
            return float("inf")
        zero = gtsam.VectorValues()
        for k in problem.dims:
            zero.insert(int(k), np.zeros(problem.dims[k]))
        return float(lin.error(zero) - lin.error(d))

    # a robust loss's reweighted quadratic model over-predicts near its optimum: no stall check there
    robust = any(getattr(b, "robust", None) is not None for b in problem.batches)
    res = _levenberg_marquardt(
        values,
        lambda x: error(problem, x),
        lambda x, _: linearize(problem, x),
        step,
        params,
        progress,
        lambda x: x,
        model_decrease,
        on_iterate,
        check_small_decrease=not robust,
    )
    res.backend = "gtsam"
    return res


def _explain_nonfinite_start(problem: Problem, values: gtsam.Values) -> None:
    """A DegenerateProblemError naming the factors whose residual is not finite at the start
    (e.g. landmarks whose initial position is off the DEM tiles), instead of a bare NaN error.
    Called only once the start is known to be non-finite (no cost on the normal path)."""
    from factors.dem_height import DemBatch
    from factors.keys import describe

    for b in problem.batches:
        r, _ = b.residuals(values, False)
        bad = ~np.all(np.isfinite(np.asarray(r).reshape(len(b), -1)), axis=1)
        if not bad.any():
            continue
        n = int(bad.sum())
        if isinstance(b, DemBatch):  # one landmark per row
            first = describe(int(np.asarray(b.keys)[bad][0]))
            raise DegenerateProblemError(
                f"{n} landmark(s) start off the DEM tiles (first: {first}); their rays "
                "do not meet the terrain covered by the DEM (wild observations or the "
                "wrong DEM)"
            )
        raise DegenerateProblemError(
            f"{n} collinearity residual(s) are not finite at the initial values; "
            "check the observations and the camera model"
        )


def _levenberg_marquardt(
    x0: object,
    cost: Callable[[object], float],
    system_at: Callable[[object, bool], object],
    step: Callable[[object, object, float], object],
    params: SolverParams,
    progress: Callable[[int, float, float], None] | None,
    to_values: Callable[[object], gtsam.Values],
    model_decrease: Callable[[object, object], float],
    on_iterate: Callable[[Any], None] | None = None,
    check_small_decrease: bool = True,
) -> SolveResult:
    """The LM loop shared by both backends, with ``gtsam.LevenbergMarquardtOptimizer``'s rules:
    lambda divided by ``lambda_factor`` after an accepted step, multiplied after a rejected one;
    stop when the decrease is below the absolute or relative tolerance or lambda exceeds its bound.
    Unlike GTSAM, reaching lambda's bound is not taken as convergence: ``model_decrease(x,
    system)`` (the undamped Gauss-Newton model's predicted decrease at ``x``) must then be below
    the tolerances too, else the status is ``"stalled"`` (see :class:`SolveResult`); and with
    ``check_small_decrease`` (least squares: the model is exact to second order) a small accepted
    decrease is convergence only if the model predicts at most :data:`STALL_FACTOR` times the
    tolerance at the new point.

    ``system_at(x, second_order)``: the second flag turns true (and stays so) once an accepted
    step decreased the cost by less than ``params.second_order_below`` relative, if
    ``params.dem_second_order`` -- a hybrid Gauss-Newton/Newton switch in the manner of
    Fletcher and Xu (1987): the neglected term matters only near the minimum."""
    t_start = time.perf_counter()
    x = x0
    err = cost(x)
    if not np.isfinite(err):
        raise _NonFiniteStart(f"initial error is not finite ({err})")
    history = [err]
    lam = params.lambda_initial
    status = "iteration_limit"
    predicted: float | None = None
    it = 0
    lin_time = 0.0
    second = False
    for it in range(1, params.max_iterations + 1):
        t0 = time.perf_counter()
        system = system_at(x, second)
        lin_time += time.perf_counter() - t0
        while True:
            trial = step(x, system, lam)
            new_err = cost(trial)
            if np.isfinite(new_err) and new_err < err:
                lam = max(lam / params.lambda_factor, 1e-20)
                break
            lam *= params.lambda_factor
            if lam > params.lambda_upper:
                new_err, trial = err, x
                break
        decrease = err - new_err
        x = trial
        history.append(new_err)
        if progress:
            progress(it, new_err, lam)
        if on_iterate:
            on_iterate(x)
        log.debug("LM iteration %d: error %.9g (decrease %.3g), lambda %.1e", it, new_err, decrease, lam)
        if lam > params.lambda_upper:
            predicted = float(model_decrease(x, system))
            ok = predicted <= max(params.absolute_error_tol, params.relative_error_tol * err)
            status = "converged" if ok else "stalled"
            break
        if decrease <= params.absolute_error_tol or decrease <= params.relative_error_tol * err:
            # a small decrease is convergence only if the undamped model agrees: after rejected
            # trials (e.g. steps that would take a landmark off the DEM) a heavily damped step
            # decreases little far from the optimum
            ok = True
            if check_small_decrease:
                predicted = float(model_decrease(x, system_at(x, second)))
                ok = predicted <= STALL_FACTOR * max(params.absolute_error_tol, params.relative_error_tol * new_err)
            status = "converged" if ok else "stalled"
            err = new_err
            break
        second = second or (params.dem_second_order and decrease < params.second_order_below * err)
        err = new_err
    if status != "converged":
        log.info(
            "Levenberg-Marquardt ended %s after %d iterations (cost %.9g%s)",
            status.replace("_", " "),
            it,
            err,
            "" if predicted is None else f", the model still predicts a decrease of {predicted:.3g}",
        )
    return SolveResult(
        to_values(x),
        it,
        status == "converged",
        err,
        history,
        time.perf_counter() - t_start,
        lin_time,
        it,
        status=status,
        predicted_decrease=predicted,
    )


@dataclass
class _SchurSystem:
    """Undamped normal equations of the flat problem at one linearisation point."""

    blocks: Array  # (L, 3, 3) landmark blocks H_ll
    hlc: Array  # (L, 3, n_c) landmark-to-navigation coupling
    hcc: Array  # (n_c, n_c)
    g: Array  # J^T r


def _schur_system(flat, x: Array, n_l: int, second_order: bool = False) -> _SchurSystem:
    blk, hlc, hcc, g, _ = flat.normal_equations(x, second_order=second_order)
    return _SchurSystem(blk, hlc, hcc, g)


def _schur_step(sys: _SchurSystem, lam: float, n_l: int) -> Array:
    """Solve ``(H + lam I) d = -g`` by the Schur complement on the 3x3 landmark blocks."""
    blk = sys.blocks.copy()
    blk[:, [0, 1, 2], [0, 1, 2]] += lam
    inv = np.linalg.inv(blk)
    nl3, n_c = sys.hlc.shape[0], sys.hcc.shape[0]
    gl, gc = sys.g[:n_l].reshape(nl3, 3), sys.g[n_l:]
    ig = inv @ sys.hlc  # (L, 3, n_c)
    s = sys.hcc + lam * np.eye(n_c) - sys.hlc.reshape(3 * nl3, n_c).T @ ig.reshape(3 * nl3, n_c)
    il = np.einsum("lij,lj->li", inv, gl)
    dc = np.linalg.solve(s, -gc + sys.hlc.reshape(3 * nl3, n_c).T @ il.ravel())
    dl = -il - np.einsum("lic,c->li", ig, dc)
    return np.concatenate([dl.ravel(), dc])


def _solve_schur(
    problem: Problem,
    params: SolverParams,
    initial: gtsam.Values | None,
    progress: Callable[[int, float, float], None] | None,
    on_iterate: Callable[[Any], None] | None = None,
) -> SolveResult:
    flat = problem.flat()
    n_l = 3 * len(problem.eliminate_first)

    def step(x: Array, system: _SchurSystem, lam: float) -> Array:
        try:
            return x + _schur_step(system, lam, n_l)
        except np.linalg.LinAlgError as exc:
            raise DegenerateProblemError(
                f"the linear system is singular ({exc}); some variables are not observed"
            ) from exc

    def model_decrease(x: Array, system: _SchurSystem) -> float:
        """``-g.d / 2`` for the undamped step ``d = -H^-1 g`` of the system at ``x`` (``H`` as
        the solve used it, with the DEM's second-order term once switched on)."""
        try:
            d = _schur_step(system, 1e-12, n_l)
        except np.linalg.LinAlgError:
            return float("inf")
        return float(-0.5 * system.g @ d)

    x0 = flat.from_values(initial if initial is not None else problem.initial)
    return _levenberg_marquardt(
        x0,
        flat.cost,
        lambda x, second: _schur_system(flat, x, n_l, second),
        step,
        params,
        progress,
        flat.to_values,
        model_decrease,
        on_iterate,
    )


def gauss_newton_step(flat: Any, x: Array) -> Array:
    """The undamped Gauss-Newton step ``d = -(J^T J)^-1 J^T r`` of the flat problem at ``x``
    (Schur complement on the landmark blocks; no DEM second-order term): at a stationary point
    of the cost it vanishes whatever Hessian approximation a solver used, so its size in sigma
    units verifies convergence independently of any solver's own stopping rule."""
    n_l = 3 * len(flat.problem.eliminate_first)
    return _schur_step(_schur_system(flat, x, n_l, False), 0.0, n_l)


def gtsam_lm_params(problem: Problem, params: SolverParams = SolverParams()) -> gtsam.LevenbergMarquardtParams:
    """``params`` as ``gtsam.LevenbergMarquardtParams``, with the core's ordering."""
    p = gtsam.LevenbergMarquardtParams()
    p.setMaxIterations(params.max_iterations)
    p.setlambdaInitial(params.lambda_initial)
    p.setlambdaFactor(params.lambda_factor)
    p.setlambdaUpperBound(params.lambda_upper)
    p.setRelativeErrorTol(params.relative_error_tol)
    p.setAbsoluteErrorTol(params.absolute_error_tol)
    p.setOrdering(_ordering(problem))
    return p


def solve_gtsam_lm(problem: Problem, params: SolverParams = SolverParams()) -> SolveResult:
    """Reference: the same graph given to ``gtsam.LevenbergMarquardtOptimizer`` (live callbacks)."""
    for b in problem.batches:
        b.clear()
    p = gtsam_lm_params(problem, params)
    t0 = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(problem.graph, problem.initial, p)
    values = opt.optimize()
    # GTSAM's own stopping rule (which also stops at lambda's bound); benches only
    return SolveResult(
        values,
        opt.iterations(),
        True,
        float(problem.graph.error(values)),
        [],
        time.perf_counter() - t0,
        status="converged",
    )


def information_norm_split(
    lin: gtsam.GaussianFactorGraph,
    delta: dict[int, Array],
    local_keys: "list[int] | NDArray[np.int64]",
    local_extra: "dict[int, Array] | None" = None,
) -> tuple[float, float]:
    """``e^T H e`` split exactly into ``(local part, rest)`` for variables ``local_keys`` that no
    factor shares (the landmarks: each factor touches at most one), so that ``H_LL`` is block
    diagonal.

    With ``e = (e_L, e_o)``, ``e^T H e = c^T H_LL c + e_o^T S e_o`` where ``c = e_L + H_LL^-1 H_Lo e_o``
    and ``S = H_oo - H_oL H_LL^-1 H_Lo = P_oo^-1``: the rest is the joint NEES of the other variables
    (their marginal covariance ``P_oo``), the local part the NEES of each local variable given the
    others' errors (e.g. a landmark's triangulation error were the navigation and camera exact).
    Under the model both are chi-square, with the local and the other dimensions as degrees of
    freedom. ``local_extra`` (key -> covariance) adds an error of a local variable the graph does
    not hold, independent of everything else: its local part becomes ``c^T (H_LL^-1 + X)^-1 c``
    (and the total, which is then no longer ``e^T H e``, that part plus the rest). Raises
    ``ValueError`` if a factor touches two local variables."""
    local = {int(k) for k in local_keys}
    h_ll: dict[int, Array] = {}
    g: dict[int, Array] = {}
    total = 0.0
    for i in range(lin.size()):
        f = lin.at(i)
        a, _ = f.jacobian()
        keys = [int(k) for k in f.keys()]
        blocks = [np.asarray(delta[k], float) for k in keys]
        total += float(np.sum((a @ np.concatenate(blocks)) ** 2))
        mine = [j for j, k in enumerate(keys) if k in local]
        if not mine:
            continue
        if len(mine) > 1:
            raise ValueError(
                f"information_norm_split: factor {i} touches {len(mine)} local variables "
                f"{[keys[j] for j in mine]}; H_LL would not be block diagonal"
            )
        cols = np.cumsum([0] + [b.size for b in blocks])
        j = mine[0]
        a_l = a[:, cols[j] : cols[j + 1]]
        a_o_e = sum((a[:, cols[m] : cols[m + 1]] @ blocks[m] for m in range(len(keys)) if m != j), np.zeros(a.shape[0]))
        k = keys[j]
        h_ll[k] = h_ll.get(k, 0.0) + a_l.T @ a_l
        g[k] = g.get(k, 0.0) + a_l.T @ a_o_e
    part = 0.0
    plain = 0.0
    extra = local_extra or {}
    for k, h in h_ll.items():
        c = np.asarray(delta[k], float) + np.linalg.solve(h, g[k])
        own = float(c @ h @ c)
        plain += own
        part += float(c @ np.linalg.solve(np.linalg.inv(h) + extra[k], c)) if k in extra else own
    return part, total - plain


def check_converged(result: SolveResult, what: str = "the solve", accept: bool = False) -> None:
    """Raise :class:`ConvergenceError` if the solver stopped without converging (unless ``accept``:
    then only a warning is logged; the caller flags the result)."""
    if result.converged:
        return
    why = (
        "it stalled (lambda at its bound, or damped steps decreasing the cost by almost nothing) while "
        f"the Gauss-Newton model still predicts a decrease of {result.predicted_decrease:.3g} -- e.g. steps "
        "that would take a landmark off the DEM tiles"
        if result.status == "stalled"
        else f"the iteration limit ({result.iterations}) was reached"
    )
    msg = f"{what} did not converge: {why} (cost {result.final_error:.6g})"
    if accept:
        log.warning("%s; accepted: its covariances are not those of an optimum", msg)
        return
    raise ConvergenceError(msg + "; raise --max-iterations, or pass --accept-unconverged to keep a flagged result")
