"""The same adjustment problem solved by the alternatives a user could pick (for ``misrgraph bench sba``).

* :func:`solve_scipy` hands :class:`misrgraph.estimate.problem.FlatProblem` (vectorised whitened residuals
  and a sparse Jacobian from the very same pure functions) to ``scipy.optimize.least_squares`` --
  what a good numpy user would write.
* :func:`solve_scipy_newton` is a second-order peer: ``scipy.optimize.minimize`` (trust-krylov)
  with Hessian-vector products of ``J^T J`` plus the DEM curvature the core also uses.
* :func:`solve_ceres` gives the same pure residual functions to Ceres through ``pyceres``, one
  cost function per landmark (as a Ceres bundle adjuster is written; landmarks Schur-eliminated)
  or per batch of landmarks (one vectorised call per batch; sparse Cholesky), numpy arrays in,
  when ``pyceres`` is installed.

Both stop on the same criterion as the core: relative decrease of the cost below ``ftol``.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from factors.collinearity import collinearity_residual
from factors.dem_height import dem_residual
from misrgraph.errors import InputError, require_extra
from misrgraph.estimate.problem import FlatProblem

__all__ = ["solve_scipy", "solve_scipy_newton", "solve_ceres"]

Array = NDArray[np.float64]


def solve_scipy(
    flat: FlatProblem,
    ftol: float = 1e-5,
    max_nfev: int = 200,
    on_cost: Callable[[float], None] | None = None,
    x_scale: str | float = "jac",
    on_point: Callable[[Array, float], None] | None = None,
) -> dict[str, Any]:
    """``scipy.optimize.least_squares`` (trust region reflective, sparse Jacobian, LSMR).

    ``on_cost(cost)`` is called with the cost of every evaluated point, ``on_point(x, cost)``
    with the point too (for time-to-cost and time-to-accuracy traces; either may raise to stop
    the run). ``x_scale``: scipy's variable scaling (``"jac"``: by the Jacobian's column norms).
    Exact trust-region solves (``tr_solver="exact"``) need the dense Jacobian and are not offered.
    """
    from scipy.optimize import least_squares

    def fun(x: Array) -> Array:
        r = flat.residual(x)
        cost = 0.5 * float(r @ r)
        if on_cost is not None:
            on_cost(cost)
        if on_point is not None:
            on_point(x, cost)
        return r

    t0 = time.perf_counter()
    res = least_squares(
        fun,
        flat.initial(),
        jac=flat.jacobian,
        method="trf",
        ftol=ftol,
        xtol=1e-15,
        gtol=1e-15,
        x_scale=x_scale,
        max_nfev=max_nfev,
        tr_solver="lsmr",
    )
    return {
        "x": res.x,
        "cost": float(res.cost),
        "iterations": int(res.njev),
        "seconds": time.perf_counter() - t0,
        "status": int(res.status),
    }


def solve_scipy_newton(
    flat: FlatProblem,
    gtol: float = 1e-8,
    max_iterations: int = 200,
    on_point: Callable[[Array, float], None] | None = None,
) -> dict[str, Any]:
    """A second-order peer: ``scipy.optimize.minimize(method="trust-krylov")`` on the cost
    ``0.5 ||r(x)||^2`` with its gradient ``J^T r`` and Hessian-vector products of ``J^T J`` plus
    the DEM factors' second-order term (the same curvature the core adds near convergence,
    :meth:`~misrgraph.estimate.problem.FlatProblem.dem_curvature`), from the same vectorised
    residual and sparse Jacobian. ``on_point(x, cost)`` is called at every evaluated point."""
    import scipy.sparse as sp
    from scipy.optimize import minimize

    # Jacobi scaling (the Krylov iterations are unpreconditioned): y = s * x with s the column
    # norms of the whitened Jacobian at the start, as least_squares' x_scale="jac"
    x0 = flat.initial()
    s = np.sqrt(np.asarray(flat.jacobian(x0).power(2).sum(axis=0)).ravel())
    s[s == 0] = 1.0
    state: dict[str, Any] = {}

    def fun(y: Array) -> tuple[float, Array]:
        if not np.all(np.isfinite(y)):
            # the Krylov subproblem can propose a non-finite step: an infinite cost makes the
            # trust region reject it and shrink (the residual would fail on it, e.g. in the DEM lookup)
            return float("inf"), np.zeros_like(y)
        x = y / s
        r = flat.residual(x)
        jac = flat.jacobian(x)
        cost = 0.5 * float(r @ r)
        h = None
        if flat.dem is not None and len(flat.dem):
            li, corr = flat.dem_curvature(x)
            cols = flat._dem_cols
            h = sp.csr_matrix(
                (corr.ravel(), (np.repeat(cols, 3, axis=1).ravel(), np.tile(cols, (1, 3)).ravel())),
                shape=(flat.n, flat.n),
            )
        state.update(y=y.copy(), jac=jac, dem=h)
        if on_point is not None:
            on_point(x, cost)
        return cost, (jac.T @ r) / s

    def hessp(y: Array, v: Array) -> Array:
        if "y" not in state or not np.array_equal(state["y"], y):
            fun(y)
        u = v / s
        out = state["jac"].T @ (state["jac"] @ u)
        return (out if state["dem"] is None else out + state["dem"] @ u) / s

    t0 = time.perf_counter()
    res = minimize(
        fun, x0 * s, jac=True, hessp=hessp, method="trust-krylov", options={"gtol": gtol, "maxiter": max_iterations}
    )
    res.x = res.x / s
    return {
        "x": res.x,
        "cost": float(res.fun),
        "iterations": int(res.nit),
        "seconds": time.perf_counter() - t0,
        "status": int(res.status),
    }


class _CostRows:
    """The residual rows of a run of consecutive collinearity factors (landmarks) for one Ceres
    cost function: their observations (the pure
    :func:`~factors.collinearity.collinearity_residual` on those observations, numpy arrays in,
    no ``gtsam.Values``) and the DEM rows of their landmarks in ``dem_of`` (landmark key -> DEM
    row), whitened; parameter blocks in first-seen key order of the factors (landmark first)."""

    def __init__(self, flat: FlatProblem, factors: range, dem_of: dict[int, int]) -> None:
        b = flat.coll
        lay = b.layout
        self.a, self.z = int(lay.obs_start[factors.start]), int(lay.obs_stop[factors.stop - 1])
        self.keys = list(dict.fromkeys(int(k) for f in factors for k in lay.factor_keys[f]))
        self.dims = [int(flat.problem.dims[k]) for k in self.keys]
        self.n_cols = int(sum(self.dims))
        pos = dict(zip(self.keys, np.concatenate([[0], np.cumsum(self.dims)[:-1]]).astype(int)))
        sl = slice(self.a, self.z)
        # local columns of each slot per observation, (n, d) or -1
        self.cols = []
        for s, d in enumerate(b.slot_dims):
            ks = b.slot_keys[s][sl]
            start = np.array([pos.get(int(k), -1) if k >= 0 else -1 for k in ks], np.int64)
            self.cols.append(np.where(start[:, None] >= 0, start[:, None] + np.arange(d), -1))
        self.const = b.const.take(sl)
        self.cam0 = b.camera_supplied[sl]
        self.w = 1.0 / b.sigma_px[sl].ravel()
        self.batch = b
        lms = [int(k) for k in dict.fromkeys(b.slot_keys[0][sl].tolist()) if int(k) in dem_of]
        self.dem_index = np.array([dem_of[k] for k in lms], np.int64)
        self.dem_cols = np.array([pos[k] for k in lms], np.int64)[:, None] + np.arange(3)
        self.flat = flat
        self.n_res = 2 * (self.z - self.a) + self.dem_index.size

    def evaluate(self, xl: Array, jacobian: bool) -> tuple[Array, Array | None]:
        """Whitened residual ``(n_res,)`` and Jacobian ``(n_res, n_cols)`` at the local vector ``xl``."""
        b, n = self.batch, self.z - self.a
        cols = [np.where(c >= 0, xl[np.maximum(c, 0)], 0.0) for c in self.cols]
        knots = np.stack([np.concatenate([cols[2 + 2 * a], cols[3 + 2 * a]], -1) for a in range(3)], 1)
        cam = self.cam0.copy()
        if np.any(self.cols[8] >= 0):  # absent camera slots gather 0 (as the flat problem's)
            cam[:, list(b.camera_select)] += cols[8] * b.camera_scale
        om = np.broadcast_to(b.omega_supplied, (n, 3)) + cols[9]
        r, j = collinearity_residual(cols[0], cols[1], knots, cam, om, self.const, jacobians=jacobian)
        res = r.ravel() * self.w
        jm = None
        if jacobian:
            assert j is not None
            jm = np.zeros((self.n_res, self.n_cols))
            rows = np.arange(2 * n).reshape(n, 2)
            for c, blk in zip(self.cols, b._blocks(j)):
                used = c[:, 0] >= 0
                np.add.at(jm, (rows[used][:, :, None], c[used][:, None, :]), blk[used])
            jm[: 2 * n] *= self.w[:, None]
        if self.dem_index.size:
            dem = self.flat.dem
            rd, jd = dem_residual(xl[self.dem_cols], dem.surface, jacobian)
            s = dem.sigma_m[self.dem_index]
            res = np.concatenate([res, rd / s])
            if jm is not None and jd is not None:
                jm[2 * n + np.arange(s.size)[:, None], self.dem_cols] = jd[:, 0, :] / s[:, None]
        return res, jm


def solve_ceres(
    flat: FlatProblem,
    ftol: float = 1e-5,
    max_iterations: int = 100,
    on_cost: Callable[[float], None] | None = None,
    max_seconds: float | None = None,
    on_point: Callable[[Array, float], None] | None = None,
    linear_solver: str = "DENSE_SCHUR",
    group: int = 1,
) -> dict[str, Any]:
    """Ceres (pyceres) on the same vectorised residuals: one cost function per ``group``
    consecutive landmarks (their collinearity observations and DEM rows, evaluated by the pure
    functions on numpy arrays in one call, :class:`_CostRows`) and one per linear prior;
    ``linear_solver`` (a ``pyceres.LinearSolverType`` name), one thread. With ``group`` 1 the
    landmarks are Schur-eliminated (``DENSE_SCHUR``); a cost function over several landmarks
    couples them, and Schur elimination needs them independent (Ceres would eliminate only an
    independent subset), so ``group`` > 1 is refused with a Schur solver and wants
    ``SPARSE_NORMAL_CHOLESKY`` (SuiteSparse's supernodal Cholesky of the normal equations).

    ``on_cost(cost)`` / ``on_point(x, cost)`` are called after every iteration with the current
    cost (and point); ``max_seconds`` bounds Ceres' solver time. pyceres does not expose Ceres'
    ``EvaluationCallback``, so a cost function cannot see the whole point and the residuals are
    evaluated cost function by cost function (one Python call per group per evaluation).
    """
    if not (isinstance(group, int) and group >= 1):
        raise InputError("group", group, "a whole number of landmarks per cost function >= 1")
    if group > 1 and linear_solver.endswith("SCHUR"):
        raise InputError(
            "linear_solver",
            linear_solver,
            "a non-Schur solver (e.g. SPARSE_NORMAL_CHOLESKY) when group > 1: "
            "a cost function over several landmarks couples them, and Schur elimination needs them independent",
        )
    pyceres = require_extra("pyceres", "bench", "the Ceres comparison of misrgraph bench sba")

    problem = flat.problem
    b = flat.coll
    x = flat.initial()
    params = {k: x[flat.offset[k] : flat.offset[k] + problem.dims[k]].copy() for k in flat.keys}
    dem_of = {int(k): i for i, k in enumerate(flat.dem.keys)} if flat.dem is not None else {}

    class Landmarks(pyceres.CostFunction):
        def __init__(self, factors: range) -> None:
            super().__init__()
            lay = b.layout
            lms = {int(k) for k in b.slot_keys[0][lay.obs_start[factors.start] : lay.obs_stop[factors.stop - 1]]}
            self.rows = _CostRows(flat, factors, {lm: dem_of.pop(lm) for lm in lms if lm in dem_of})
            self.keys = self.rows.keys
            self.set_num_residuals(self.rows.n_res)
            self.set_parameter_block_sizes(self.rows.dims)

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            xl = np.concatenate([np.asarray(p, dtype=float) for p in parameters])
            r, jm = self.rows.evaluate(xl, jacobians is not None)
            if not np.all(np.isfinite(r)):
                return False
            residuals[:] = r
            if jacobians is not None:
                assert jm is not None
                c = 0
                for i, d in enumerate(self.rows.dims):
                    if jacobians[i] is not None:
                        jacobians[i][:] = jm[:, c : c + d].ravel()
                    c += d
            return True

    class Linear(pyceres.CostFunction):
        """A whitened linear prior ``sum_k A_k x_k - b`` (one or two keys), or the DEM row of a
        landmark without collinearity observations."""

        def __init__(self, keys: tuple[int, ...], prior: Any = None, dem_index: int | None = None) -> None:
            super().__init__()
            self.keys, self.prior, self.dem_index = keys, prior, dem_index
            self.set_num_residuals(1 if dem_index is not None else prior.b.size)
            self.set_parameter_block_sizes([problem.dims[k] for k in keys])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            if self.dem_index is not None:
                p = np.asarray(parameters[0], dtype=float)
                rd, jd = dem_residual(p[None, :], flat.dem.surface, jacobians is not None)
                s = flat.dem.sigma_m[self.dem_index]
                residuals[:] = rd / s
                if jacobians is not None and jacobians[0] is not None:
                    jacobians[0][:] = (jd[0, 0] / s).ravel()
                return bool(np.all(np.isfinite(rd)))
            pr = self.prior
            residuals[:] = sum(a @ np.asarray(q, dtype=float) for a, q in zip(pr.a, parameters)) - pr.b
            if jacobians is not None:
                for i, a in enumerate(pr.a):
                    if jacobians[i] is not None:
                        jacobians[i][:] = a.ravel()
            return True

    prob = pyceres.Problem()
    costs = []  # keep the Python objects alive
    n_f = b.layout.n_factors
    for f in range(0, n_f, group):
        c = Landmarks(range(f, min(f + group, n_f)))
        costs.append(c)
        prob.add_residual_block(c, None, [params[k] for k in c.keys])
    for lm, i in dem_of.items():  # DEM rows of landmarks whose views all sit in other factors
        c = Linear((lm,), dem_index=i)
        costs.append(c)
        prob.add_residual_block(c, None, [params[lm]])
    for p in flat.priors:
        c = Linear(p.keys, p)
        costs.append(c)
        prob.add_residual_block(c, None, [params[k] for k in p.keys])
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = getattr(pyceres.LinearSolverType, linear_solver)
    opts.function_tolerance = ftol
    opts.gradient_tolerance = 1e-20
    opts.parameter_tolerance = 1e-20
    opts.max_num_iterations = max_iterations
    opts.num_threads = 1

    def current() -> Array:
        xs = np.zeros(flat.n)
        for k, p in params.items():
            xs[flat.offset[k] : flat.offset[k] + p.size] = p
        return xs

    if max_seconds is not None:
        opts.max_solver_time_in_seconds = float(max_seconds)
    if on_cost is not None or on_point is not None:
        opts.update_state_every_iteration = on_point is not None

        class Callback(pyceres.IterationCallback):
            def __call__(self, it):  # noqa: D102 - Ceres API
                if on_cost is not None:
                    on_cost(float(it.cost))
                if on_point is not None:
                    on_point(current(), float(it.cost))
                return pyceres.CallbackReturnType.SOLVER_CONTINUE

        callback = Callback()
        opts.callbacks = [callback]
    summary = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(opts, prob, summary)
    seconds = time.perf_counter() - t0
    return {
        "x": current(),
        "cost": float(summary.final_cost),
        "iterations": int(summary.num_successful_steps + summary.num_unsuccessful_steps),
        "seconds": seconds,
        "report": summary.BriefReport(),
    }
