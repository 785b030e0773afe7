from __future__ import annotations

import gtsam
import numpy as np
import pytest

from misrgraph.errors import DegenerateProblemError
from misrgraph.graph import GraphConfig, build_pass_graph
from misrgraph.passdata import Observations, OrbitPass
from misrgraph.solver import SolverParams, marginal_covariances, solve, solve_gtsam_lm

TIGHT = SolverParams(relative_error_tol=1e-12, absolute_error_tol=1e-12, max_iterations=60)


@pytest.fixture(scope="module")
def noisy_graph(small_pass):
    sc, p = small_pass
    return build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=True))


def test_core_reaches_the_gtsam_lm_optimum(small_pass):
    sc, p = small_pass
    # no DEM here: GTSAM's optimiser then sees exactly the same smooth problem
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=False))
    ours = solve(pg.problem, TIGHT)
    ref = solve_gtsam_lm(pg.problem, TIGHT)
    assert ours.converged
    assert ours.final_error == pytest.approx(ref.final_error, rel=1e-6)
    # and the same solution, to well within the posterior sigma
    m = marginal_covariances(pg.problem, ours.values)
    z = [np.max(np.abs(ours.values.atVector(k) - ref.values.atVector(k)) / np.sqrt(np.diag(m[k]))) for k in pg.problem.dims]
    assert max(z) < 1e-3


def test_marginals_equal_gtsam_marginals(noisy_graph):
    prob = noisy_graph.problem
    res = solve(prob)
    mine = marginal_covariances(prob, res.values)
    for b in prob.batches:
        b.evaluate(res.values, True)
    try:
        ref = gtsam.Marginals(prob.graph, res.values)
        keys = list(prob.dims)[::7] + noisy_graph.knot_keys(1)[:3] + noisy_graph.ephemeris_keys()
        for k in keys:
            np.testing.assert_allclose(mine[k], ref.marginalCovariance(k), rtol=1e-6, atol=1e-12 * np.max(np.abs(mine[k])))
    finally:
        for b in prob.batches:
            b.clear()


def test_error_decreases_monotonically(noisy_graph):
    res = solve(noisy_graph.problem)
    h = np.array(res.history)
    assert np.all(np.diff(h) <= 1e-9 * h[0])
    assert res.iterations < 40


def test_degenerate_inputs_are_diagnosed(small_pass):
    sc, p = small_pass
    o = p.observations
    none = OrbitPass(p.pass_id, p.path, p.orbit, p.ephemeris, p.attitude, p.t0, p.line_time, p.landmarks,
                     o.subset(np.zeros(len(o), bool)), p.temperature_c, p.truth)
    with pytest.raises(DegenerateProblemError, match="no tie-point or GCP observations"):
        build_pass_graph(none, sc.camera_model, sc.dem, sc.gcps)
    one = OrbitPass(p.pass_id, p.path, p.orbit, p.ephemeris, p.attitude, p.t0, p.line_time, p.landmarks,
                    o.subset(o.camera == 4), p.temperature_c, p.truth)
    with pytest.raises(DegenerateProblemError, match="single camera"):
        build_pass_graph(one, sc.camera_model, sc.dem, sc.gcps)
    assert isinstance(o, Observations)
