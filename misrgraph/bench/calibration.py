"""``misrgraph bench calibration``: the month calibration's linear algebra, the current method
against the one it replaced, on the same linearised problem in the same process.

A month of GCP passes is one problem whose GCP landmarks are shared by several passes and whose
camera corrections are shared by all. Two steps dominate its solve:

* **the Levenberg-Marquardt step** (GTSAM's elimination of the damped linear graph): the
  landmarks-first ordering (the classic Schur order, right for one pass of tie points) against
  GTSAM's COLAMD with the cameras last (:func:`misrgraph.estimate.solver._ordering`);
* **the cameras' joint covariance** (:func:`misrgraph.estimate.problem.schur_marginals` with
  ``joint_keys``): SuperLU's default unsymmetric LU of the reduced system ``S`` against the
  factorisation of its symmetric permutation without pivoting (``S`` is symmetric positive
  definite).

Each pair is timed (best of ``repeat``) and compared: the largest difference of the steps
relative to the largest step component, and of the covariances relative to the largest entry.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

import gtsam
import numpy as np
import scipy.sparse.linalg as spla

from misrgraph.bench.work import bench_workdir
from misrgraph.errors import InputError

__all__ = ["run_bench_calibration", "MONTH_SIZES"]

log = logging.getLogger(__name__)

#: the month scenarios: ``standard`` is the simulator's default month (120 GCPs, 30 days), as the
#: demo and ``test_standard_month_meets_the_eighth_pixel_requirement`` calibrate; ``reduced`` the
#: 16-day month of 24 GCPs the suite's NEES study uses
MONTH_SIZES: dict[str, dict[str, Any]] = {"standard": {}, "reduced": {"n_gcps": 24, "month_days": 16}}


def _best(fn: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    best, out = np.inf, None
    for _ in range(max(int(repeat), 1)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return float(best), out


def run_bench_calibration(
    size: str = "standard", seed: int = 3, workdir: str | Path | None = None, repeat: int = 3, lam: float = 1e-3
) -> dict[str, Any]:
    """The two comparisons of the module docstring on a simulated month of ``size`` (a key of
    :data:`MONTH_SIZES`), linearised at its start (the supplied camera model), LM damping ``lam``.

    Returns the problem's size and, per comparison, the seconds of each method, their ratio
    (former / current) and the relative difference of their results."""
    from misrgraph.estimate.calibrate import CalibrateConfig, _build
    from misrgraph.estimate.problem import SPD_SPLU_OPTIONS, _blocks_from_linear, _offsets, linearize, schur_reduce
    from misrgraph.estimate.solver import _damped, _ordering
    from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

    if size not in MONTH_SIZES:
        raise InputError("size", size, " or ".join(MONTH_SIZES))
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise InputError("repeat", repeat, "a positive integer")
    with bench_workdir(workdir) as wd:
        out = Path(wd) / f"month_{size}_{seed}"
        if not (out / "scenario.json").exists():
            log.info("simulating the %s month (seed %d)", size, seed)
            run_simulate(ScenarioConfig(scenario="month", seed=seed, truth="model", **MONTH_SIZES[size]), out)
        sc = load_scenario(out)
        passes = [sc.load_pass(i) for i in range(len(sc.pass_files))]
        prob, _ = _build(passes, sc.camera_model, sc.gcps, CalibrateConfig().graph_config(), None, None)
    lin = linearize(prob, prob.initial)
    damped = _damped(lin, prob, lam)
    keys = list(prob.dims)

    def step(ordering: gtsam.Ordering) -> np.ndarray:
        d = damped.optimize(ordering)
        return np.concatenate([d.at(int(k)) for k in keys])

    t_former_order, former_order = _best(
        lambda: gtsam.Ordering([int(k) for k in prob.eliminate_first] + prob.other_keys), repeat
    )
    t_current_order, current_order = _best(lambda: _ordering(prob), repeat)
    t_former, d_former = _best(lambda: step(former_order), repeat)
    t_current, d_current = _best(lambda: step(current_order), repeat)
    res: dict[str, Any] = {
        "size": size,
        "seed": int(seed),
        "passes": len(passes),
        "variables": len(keys),
        "landmarks": len(prob.eliminate_first),
        "cameras": len(prob.eliminate_last),
        "factors": int(prob.graph.size()),
        "step": {
            "former": "landmarks first",
            "current": "COLAMD, cameras last",
            "former_s": t_former,
            "current_s": t_current,
            "ratio": t_former / t_current,
            "ordering_s": {"former": t_former_order, "current": t_current_order},
            "relative_difference": float(np.max(np.abs(d_former - d_current)) / np.max(np.abs(d_former))),
        },
    }
    h_ll, h_lc, h_cc = _blocks_from_linear(prob, lin)
    _, _, s = schur_reduce(h_ll, h_lc, h_cc)
    off, _ = _offsets(prob.other_keys, prob.dims)
    idx = np.concatenate([np.arange(off[int(k)], off[int(k)] + prob.dims[int(k)]) for k in prob.eliminate_last])
    rhs = np.zeros((s.shape[0], idx.size))
    rhs[idx, np.arange(idx.size)] = 1.0

    def joint(**kw: Any) -> np.ndarray:
        return spla.splu(s, **kw).solve(rhs)[idx]

    t_lu, c_lu = _best(lambda: joint(), repeat)
    t_sym, c_sym = _best(lambda: joint(**SPD_SPLU_OPTIONS), repeat)
    res["camera_covariance"] = {
        "former": "SuperLU, unsymmetric LU",
        "current": "SuperLU, symmetric mode without pivoting",
        "reduced_system": {"size": int(s.shape[0]), "nonzeros": int(s.nnz)},
        "former_s": t_lu,
        "current_s": t_sym,
        "ratio": t_lu / t_sym,
        "relative_difference": float(np.max(np.abs(c_lu - c_sym)) / np.max(np.abs(c_lu))),
    }
    return res
