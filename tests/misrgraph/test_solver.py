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


def test_flat_problem_matches_the_graph_and_its_jacobian(noisy_graph):
    from misrgraph.flat import FlatProblem
    from misrgraph.solver import error

    prob = noisy_graph.problem
    flat = FlatProblem(prob)
    x = flat.initial()
    assert flat.cost(x) == pytest.approx(error(prob, prob.initial), rel=1e-10)
    j = flat.jacobian(x).toarray()
    rng = np.random.default_rng(0)
    for c in rng.choice(flat.n, 12, replace=False):
        h = 1e-3 if c < 3 * len(prob.eliminate_first) else 1e-9
        e = np.zeros(flat.n)
        e[c] = h
        num = (flat.residual(x + e) - flat.residual(x - e)) / (2 * h)
        assert np.max(np.abs(num - j[:, c])) <= 1e-5 * max(np.max(np.abs(j[:, c])), 1e-12)
    blk, hlc, hcc, g, cost = flat.normal_equations(x)
    h = j.T @ j
    n_l = 3 * len(prob.eliminate_first)
    np.testing.assert_allclose(hcc, h[n_l:, n_l:], rtol=1e-9, atol=1e-9 * np.abs(h).max())
    np.testing.assert_allclose(hlc.reshape(n_l, -1), h[:n_l, n_l:], rtol=1e-9, atol=1e-9 * np.abs(h).max())
    np.testing.assert_allclose(g, j.T @ flat.residual(x), rtol=1e-9, atol=1e-9 * np.abs(g).max())
    assert cost == pytest.approx(flat.cost(x), rel=1e-12)


def test_numba_and_numpy_normal_equations_agree(noisy_graph):
    from misrgraph._kernels import HAVE_NUMBA
    from misrgraph.flat import FlatProblem

    flat = FlatProblem(noisy_graph.problem)
    x = flat.initial()
    a = flat.normal_equations(x, use_numba=False)
    b = flat.normal_equations(x, use_numba=True)
    assert HAVE_NUMBA  # a dependency; the numpy path is the fallback
    for u, v in zip(a[:4], b[:4]):
        np.testing.assert_allclose(u, v, rtol=1e-10, atol=1e-10 * np.abs(u).max())
    assert a[4] == pytest.approx(b[4], rel=1e-12)


def test_schur_backend_equals_gtsam_elimination(noisy_graph):
    prob = noisy_graph.problem
    a = solve(prob, TIGHT.replace(backend="gtsam"))
    b = solve(prob, TIGHT.replace(backend="schur"))
    assert b.final_error == pytest.approx(a.final_error, rel=1e-8)
    m = marginal_covariances(prob, a.values)
    worst = max(float(np.max(np.abs(a.values.atVector(k) - b.values.atVector(k)) / np.sqrt(np.diag(m[k])))) for k in prob.dims)
    assert worst < 1e-3
