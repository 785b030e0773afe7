"""The same adjustment problem solved by the alternatives a user could pick (for ``misrgraph bench sba``).

* :func:`solve_scipy` hands :class:`misrgraph.estimate.problem.FlatProblem` (vectorised whitened residuals
  and a sparse Jacobian from the very same pure functions) to ``scipy.optimize.least_squares`` --
  what a good numpy user would write.
* :func:`solve_ceres` gives the same residuals to Ceres through ``pyceres`` with Python cost
  functions (one per landmark, as the core groups them), when ``pyceres`` is installed.

Both stop on the same criterion as the core: relative decrease of the cost below ``ftol``.
"""

from __future__ import annotations

import time
from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors.dem_height import dem_residual
from misrgraph.estimate.problem import FlatProblem
from misrgraph.errors import require_extra

__all__ = ["solve_scipy", "solve_ceres"]

Array = NDArray[np.float64]


def solve_scipy(flat: FlatProblem, ftol: float = 1e-5, max_nfev: int = 200,
                on_cost: Callable[[float], None] | None = None) -> dict[str, Any]:
    """``scipy.optimize.least_squares`` (trust region reflective, sparse Jacobian, LSMR).

    ``on_cost(cost)`` is called with the cost of every evaluated point (for time-to-cost traces;
    it may raise to stop the run).
    """
    from scipy.optimize import least_squares

    def fun(x: Array) -> Array:
        r = flat.residual(x)
        if on_cost is not None:
            on_cost(0.5 * float(r @ r))
        return r

    t0 = time.perf_counter()
    res = least_squares(fun, flat.initial(), jac=flat.jacobian, method="trf", ftol=ftol, xtol=1e-15, gtol=1e-15,
                        x_scale="jac", max_nfev=max_nfev, tr_solver="lsmr")
    return {"x": res.x, "cost": float(res.cost), "iterations": int(res.njev), "seconds": time.perf_counter() - t0,
            "status": int(res.status)}


def solve_ceres(flat: FlatProblem, ftol: float = 1e-5, max_iterations: int = 100,
                on_cost: Callable[[float], None] | None = None, max_seconds: float | None = None) -> dict[str, Any]:
    """Ceres (pyceres) with Python cost functions: one per collinearity group, per DEM factor, per prior.

    ``on_cost(cost)`` is called after every iteration with the current cost; ``max_seconds``
    bounds Ceres' solver time.
    """
    pyceres = require_extra("pyceres", "bench", "the Ceres comparison of misrgraph bench sba")

    problem = flat.problem
    b = flat.coll
    x = flat.initial()
    params = {k: x[flat.offset[k]: flat.offset[k] + problem.dims[k]].copy() for k in flat.keys}

    class Collinearity(pyceres.CostFunction):
        def __init__(self, f: int) -> None:
            super().__init__()
            self.f = f
            self.keys = b.layout.factor_keys[f]
            a, z = int(b.layout.obs_start[f]), int(b.layout.obs_stop[f])
            self.sig = np.repeat(b.sigma_px[a:z], 2)
            self.set_num_residuals(2 * (z - a))
            self.set_parameter_block_sizes([problem.dims[k] for k in self.keys])

        def Evaluate(self, parameters, residuals, jacobians):  # noqa: N802 - Ceres API
            v = gtsam.Values()
            for k, p in zip(self.keys, parameters):
                v.insert(int(k), np.asarray(p, dtype=float))
            r, blocks = b.factor_rows(self.f, v, jacobians is not None)
            residuals[:] = r / self.sig
            if jacobians is not None:
                for i, blk in enumerate(blocks):
                    if jacobians[i] is not None:
                        jacobians[i][:] = (blk / self.sig[:, None]).ravel()
            return True

    class Linear(pyceres.CostFunction):
        """A whitened linear prior ``sum_k A_k x_k - b`` (one or two keys), or a DEM row evaluated
        by the pure function."""

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
    for f in range(b.layout.n_factors):
        c = Collinearity(f)
        costs.append(c)
        prob.add_residual_block(c, None, [params[k] for k in c.keys])
    if flat.dem is not None:
        for i, k in enumerate(flat.dem.keys):
            c = Linear((int(k),), dem_index=i)
            costs.append(c)
            prob.add_residual_block(c, None, [params[int(k)]])
    for p in flat.priors:
        c = Linear(p.keys, p)
        costs.append(c)
        prob.add_residual_block(c, None, [params[k] for k in p.keys])
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    opts.function_tolerance = ftol
    opts.gradient_tolerance = 1e-20
    opts.parameter_tolerance = 1e-20
    opts.max_num_iterations = max_iterations
    opts.num_threads = 1
    if max_seconds is not None:
        opts.max_solver_time_in_seconds = float(max_seconds)
    if on_cost is not None:

        class Callback(pyceres.IterationCallback):
            def __call__(self, it):  # noqa: D102 - Ceres API
                on_cost(float(it.cost))
                return pyceres.CallbackReturnType.SOLVER_CONTINUE

        callback = Callback()
        opts.callbacks = [callback]
    summary = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(opts, prob, summary)
    seconds = time.perf_counter() - t0
    xs = np.zeros(flat.n)
    for k, p in params.items():
        xs[flat.offset[k]: flat.offset[k] + p.size] = p
    return {"x": xs, "cost": float(summary.final_cost), "iterations": int(summary.num_successful_steps + summary.num_unsuccessful_steps),
            "seconds": seconds, "report": summary.BriefReport()}
