"""``misrgraph bench ...``: speed measured as ratios against a baseline run in the same process.

Never used by the tests for timing assertions (machines are shared and noisy); the tests only
check that the commands run and report consistent figures.
"""

from __future__ import annotations

import logging
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.graph import GraphConfig, build_pass_graph
from misrgraph.simulate import ScenarioConfig, load_scenario, run_simulate
from misrgraph.solver import SolverParams, linearize, solve, solve_gtsam_lm

__all__ = ["run_bench_solver", "standard_pass"]

log = logging.getLogger(__name__)


def standard_pass(tie_points: int, seed: int, workdir: Path, duration_s: float = 2700.0):
    """Simulate (or reuse) the standard pass scenario with ``tie_points`` tie points."""
    out = workdir / f"pass_{tie_points}_{seed}_{int(duration_s)}"
    if not (out / "scenario.json").exists():
        run_simulate(ScenarioConfig(scenario="pass", seed=seed, n_tie_points=tie_points, n_check_points=0,
                                    duration_s=duration_s), out)
    sc = load_scenario(out)
    return sc, sc.load_pass(0)


def _time(fn: Callable[[], Any], repeat: int = 3) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return float(best)


def run_bench_solver(tie_points: int = 1000, seed: int = 0, workdir: str | Path | None = None,
                     skip_gtsam: bool = False) -> dict[str, Any]:
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
        "core": {"seconds": core.seconds, "final_cost": core.final_error, "iterations": core.iterations,
                 "seconds_per_linearize": core.linearize_seconds / max(core.n_linearize, 1),
                 "seconds_per_iteration": core.seconds / max(core.iterations, 1)},
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
        out["gtsam_lm"] = {"seconds": ref.seconds, "final_cost": ref.final_error, "iterations": ref.iterations,
                           "seconds_per_iteration": ref.seconds / max(ref.iterations, 1)}
        out["ratio_gtsam_lm_over_core"] = ref.seconds / core.seconds
        out["relative_cost_difference"] = abs(ref.final_error - core.final_error) / ref.final_error
    if tmp is not None:
        tmp.cleanup()
    return out
