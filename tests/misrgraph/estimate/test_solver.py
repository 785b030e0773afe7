from __future__ import annotations

import gtsam
import numpy as np
import pytest

from misrgraph.errors import DegenerateProblemError
from misrgraph.estimate.graph import GraphConfig, build_pass_graph
from misrgraph.estimate.problem import FlatProblem, marginal_covariances
from misrgraph.estimate.solver import SolverParams, solve, solve_gtsam_lm
from misrgraph.io.passes import Observations, OrbitPass

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
    z = [
        np.max(np.abs(ours.values.atVector(k) - ref.values.atVector(k)) / np.sqrt(np.diag(m[k])))
        for k in pg.problem.dims
    ]
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
            np.testing.assert_allclose(
                mine[k], ref.marginalCovariance(k), rtol=1e-6, atol=1e-12 * np.max(np.abs(mine[k]))
            )
    finally:
        for b in prob.batches:
            b.clear()


def test_information_norm_split_is_the_rest_jointly_plus_the_landmarks_given_it(noisy_graph):
    """``e^T H e`` split into the landmarks given the other variables and those others jointly,
    for an arbitrary error ``e``: the total against the linear graph's own error
    (``||A e||^2 = E(e) + E(-e) - 2 E(0)``), the rest against ``e_o^T P_oo^-1 e_o`` with ``P_oo`` the
    joint marginal of the non-landmark variables from the Schur marginals. A factor that touches
    two local variables is refused."""
    from misrgraph.estimate.problem import linearize
    from misrgraph.estimate.solver import information_norm_split

    prob = noisy_graph.problem
    res = solve(prob)
    marg = marginal_covariances(prob, res.values)
    rng = np.random.default_rng(7)
    e = {k: np.linalg.cholesky(marg[k]) @ rng.standard_normal(d) for k, d in prob.dims.items()}
    lin = linearize(prob, res.values)
    lm = [int(k) for k in noisy_graph.landmark_keys]
    part, rest = information_norm_split(lin, e, lm)

    def lin_error(sign: float) -> float:
        vv = gtsam.VectorValues()
        for k, v in e.items():
            vv.insert(k, sign * v)
        return lin.error(vv)

    total = lin_error(1.0) + lin_error(-1.0) - 2.0 * lin_error(0.0)
    others = [k for k in prob.dims if k not in set(lm)]
    e_o = np.concatenate([e[k] for k in others])
    ref_rest = float(e_o @ np.linalg.solve(marg.joint_of(others), e_o))
    assert part + rest == pytest.approx(total, rel=1e-8)
    assert rest == pytest.approx(ref_rest, rel=1e-6)
    assert 0 < part < total
    # an extra error of the landmarks the graph does not hold: zero changes nothing; a variance
    # along one axis of every landmark lowers their part alone, the more the larger it is, and
    # never to zero (the other two axes keep theirs)
    zero = information_norm_split(lin, e, lm, {k: np.zeros((3, 3)) for k in lm})
    assert zero == pytest.approx((part, rest), rel=1e-12)
    axis = np.diag([1.0, 0.0, 0.0])
    some, rest2 = information_norm_split(lin, e, lm, {k: 1e2 * axis for k in lm})
    huge, rest3 = information_norm_split(lin, e, lm, {k: 1e12 * axis for k in lm})
    assert rest2 == rest3 == rest and 0 < huge < some < part
    with pytest.raises(ValueError, match="two|local variables"):
        information_norm_split(lin, e, list(prob.dims))


def test_error_decreases_monotonically(noisy_graph):
    res = solve(noisy_graph.problem)
    h = np.array(res.history)
    assert np.all(np.diff(h) <= 1e-9 * h[0])
    assert res.iterations < 40


def test_degenerate_inputs_are_diagnosed(small_pass):
    sc, p = small_pass
    o = p.observations
    none = OrbitPass(
        p.pass_id,
        p.path,
        p.orbit,
        p.ephemeris,
        p.attitude,
        p.t0,
        p.line_time,
        p.landmarks,
        o.subset(np.zeros(len(o), bool)),
        p.temperature_c,
    )
    with pytest.raises(DegenerateProblemError, match="no tie-point or GCP observations"):
        build_pass_graph(none, sc.camera_model, sc.dem, sc.gcps)
    one = OrbitPass(
        p.pass_id,
        p.path,
        p.orbit,
        p.ephemeris,
        p.attitude,
        p.t0,
        p.line_time,
        p.landmarks,
        o.subset(o.camera == 4),
        p.temperature_c,
    )
    with pytest.raises(DegenerateProblemError, match="single camera"):
        build_pass_graph(one, sc.camera_model, sc.dem, sc.gcps)
    assert isinstance(o, Observations)


def test_flat_problem_matches_the_graph_and_its_jacobian(noisy_graph):
    from misrgraph.estimate.problem import FlatProblem
    from misrgraph.estimate.solver import error

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
    from misrgraph.estimate._kernels import HAVE_NUMBA
    from misrgraph.estimate.problem import FlatProblem

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
    # the same Gauss-Newton steps: the Schur backend's second-order DEM term off
    b = solve(prob, TIGHT.replace(backend="schur", dem_second_order=False))
    assert b.final_error == pytest.approx(a.final_error, rel=1e-8)
    m = marginal_covariances(prob, a.values)
    worst = max(
        float(np.max(np.abs(a.values.atVector(k) - b.values.atVector(k)) / np.sqrt(np.diag(m[k])))) for k in prob.dims
    )
    assert worst < 1e-3


def test_second_order_dem_term_is_the_exact_hessian_of_the_dem_cost(noisy_graph, small_pass):
    from factors.dem_height import dem_residual
    from misrgraph.model.frames import ecef_to_geodetic

    dem = small_pass[0].dem
    flat = FlatProblem(noisy_graph.problem)
    x = flat.initial()
    gn = flat.normal_equations(x)[0]
    full = flat.normal_equations(x, second_order=True)[0]
    changed = np.flatnonzero(np.any(np.abs(full - gn) > 0, axis=(1, 2)))
    assert changed.size > 0.5 * len(flat.dem)  # applied wherever the block stays positive definite
    # the surface is C1, piecewise cubic between postings (~90 m): keep landmarks more than 3 m
    # from a posting line, so that both difference stencils stay inside one cubic piece
    lat, lon, _ = ecef_to_geodetic(x[flat._dem_cols])
    t = dem.tile_of(lat, lon)
    fr = (lat - dem.lat0[t]) / dem.posting_deg % 1.0
    fc = (lon - dem.lon0[t]) / dem.posting_deg % 1.0
    away = np.minimum(np.minimum(fr, 1 - fr), np.minimum(fc, 1 - fc)) * 90.0 * np.cos(np.radians(lat)) > 3.0
    # independent: second differences of the DEM part of the cost, 0.5 (r / sigma)^2, per landmark
    rows = np.flatnonzero(np.isin(flat._dem_lm, changed) & away)[:30]
    assert rows.size == 30
    p = x[flat._dem_cols[rows]]
    sig = flat.dem.sigma_m[rows]

    def cost(q):
        return 0.5 * (dem_residual(q, flat.dem.surface, False)[0] / sig) ** 2

    _, jd = dem_residual(p, flat.dem.surface, True)
    jd = jd[:, 0, :] / sig[:, None]
    s = 0.5  # m; the surface is piecewise cubic over ~90 m cells
    num = np.empty((rows.size, 3, 3))
    for a in range(3):
        for b in range(3):
            ea, eb = np.eye(3)[a] * s, np.eye(3)[b] * s
            num[:, a, b] = (cost(p + ea + eb) - cost(p + ea - eb) - cost(p - ea + eb) + cost(p - ea - eb)) / (4 * s * s)
    mine = full[flat._dem_lm[rows]] - gn[flat._dem_lm[rows]] + np.einsum("ni,nj->nij", jd, jd)
    np.testing.assert_allclose(mine, num, rtol=1e-3, atol=1e-3 * np.abs(num).max())


def test_second_order_dem_term_reaches_a_stationary_point(noisy_graph):
    prob = noisy_graph.problem
    gn = solve(prob, TIGHT.replace(backend="schur", dem_second_order=False))
    so = solve(prob, TIGHT.replace(backend="schur"))
    assert so.converged
    assert so.final_error <= gn.final_error * (1 + 1e-12)
    # first-order optimality from the sparse Jacobian (not the normal-equation code): the
    # Gauss-Newton decrement g^T (J^T J)^-1 g, the cost decrease a further step would promise
    import scipy.sparse.linalg as spla

    flat = FlatProblem(prob)
    x = flat.from_values(so.values)
    j, r = flat.jacobian(x), flat.residual(x)
    g = j.T @ r
    dec = float(g @ spla.spsolve((j.T @ j).tocsc(), g))
    assert dec < 1e-6 * so.final_error


def test_backend_choices_that_cannot_apply_are_errors(noisy_graph, small_pass):
    """An explicit backend is used or refused, never silently replaced; 'auto' says what ran."""
    from misrgraph.errors import InputError
    from misrgraph.estimate.graph import build_pass_graph

    sc, p = small_pass
    robust = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=True, robust="cauchy"))
    with pytest.raises(InputError, match=r"backend.*Schur backend cannot solve it.*robust"):
        solve(robust.problem, TIGHT.replace(backend="schur"))
    with pytest.raises(InputError, match="dem_second_order"):
        solve(robust.problem, TIGHT.replace(dem_second_order=True))
    with pytest.raises(InputError, match="dem_second_order"):
        SolverParams(backend="gtsam", dem_second_order=True)
    assert solve(robust.problem, SolverParams(max_iterations=3)).backend == "gtsam"
    assert solve(noisy_graph.problem, SolverParams(max_iterations=3)).backend == "schur"
    assert solve(noisy_graph.problem, SolverParams(backend="gtsam", max_iterations=3)).backend == "gtsam"


def _toy_lm(step_decreases: bool, model: float | None = None, wall: float = np.inf):
    """The LM loop on cost (x - 3)^2 from 0: steps that reach the minimum, or steps that never
    decrease the cost (so lambda climbs to its bound); ``model``: the predicted decrease there
    (default: the exact Gauss-Newton model's, (x - 3)^2). Beyond ``wall`` the cost is not finite
    (a landmark stepping off the DEM)."""
    from misrgraph.estimate.solver import _levenberg_marquardt

    def cost(x):
        return float((x - 3.0) ** 2) if x <= wall else float("nan")

    step = (lambda x, sys, lam: x + (3.0 - x) / (1.0 + lam)) if step_decreases else (lambda x, sys, lam: x)
    predicted = (lambda x, sys: float((x - 3.0) ** 2)) if model is None else (lambda x, sys: model)
    return _levenberg_marquardt(0.0, cost, lambda x, second: None, step, SolverParams(), None, lambda x: x, predicted)


def test_lambda_at_its_bound_is_not_convergence_unless_the_model_agrees():
    """Closed-form LM runs: a step that keeps failing drives lambda to its bound; that ends as
    'stalled' while the Gauss-Newton model still predicts a decrease, and as 'converged' only when
    the model predicts (almost) none. A normal run converges by the decrease test."""
    stalled = _toy_lm(False, model=9.0)
    assert stalled.status == "stalled" and not stalled.converged and stalled.predicted_decrease == 9.0
    at_optimum = _toy_lm(False, model=0.0)
    assert at_optimum.status == "converged" and at_optimum.converged
    normal = _toy_lm(True)
    assert normal.status == "converged" and abs(normal.final_error) < 1e-9


def test_damped_creep_against_a_wall_is_stalled_not_converged():
    """Steps past x = 1 make the cost non-finite, so LM accepts ever more damped steps that
    decrease it by almost nothing: that passes the small-decrease test, but the Gauss-Newton model
    still predicts a decrease of ~4, so it is 'stalled' (it was reported 'converged')."""
    res = _toy_lm(True, wall=1.0)
    assert res.status == "stalled" and not res.converged
    assert res.predicted_decrease > 3.0 and res.final_error > 3.0


def test_iteration_limit_is_reported_and_refused(noisy_graph):
    from misrgraph.errors import ConvergenceError
    from misrgraph.estimate.solver import check_converged

    res = solve(noisy_graph.problem, SolverParams(max_iterations=1))
    assert res.status == "iteration_limit" and not res.converged and res.iterations == 1
    with pytest.raises(ConvergenceError, match="iteration limit.*--accept-unconverged"):
        check_converged(res, "the least-squares solve")
    check_converged(res, "the least-squares solve", accept=True)  # flagged, not raised
    full = solve(noisy_graph.problem)
    assert full.status == "converged" and full.converged


def test_ceres_cost_rows_are_the_flat_rows(noisy_graph):
    """Ceres' cost functions -- one landmark, or a run of several -- evaluate the same whitened
    rows and Jacobian blocks as the flat problem (whose Jacobian is checked against numerical
    derivatives above)."""
    from misrgraph.errors import InputError
    from misrgraph.estimate.backends import _CostRows, solve_ceres

    flat = noisy_graph.problem.flat()
    x = flat.initial()
    r_all, j_all = flat.residual(x), flat.jacobian(x).tocsr()
    lay = flat.coll.layout
    dem_of = {int(k): i for i, k in enumerate(flat.dem.keys)} if flat.dem is not None else {}
    n = lay.n_factors
    for factors in (range(0, 1), range(n // 2, n // 2 + 1), range(n - 1, n), range(3, min(n, 40))):
        rows = _CostRows(flat, factors, dem_of)
        xl = np.concatenate([x[flat.offset[k] : flat.offset[k] + d] for k, d in zip(rows.keys, rows.dims)])
        r, jm = rows.evaluate(xl, True)
        idx = list(range(2 * rows.a, 2 * rows.z)) + [flat.m_coll + int(i) for i in rows.dem_index]
        assert len(idx) == rows.n_res and (len(factors) == 1 or rows.dem_index.size > 1)
        cols = np.concatenate([np.arange(flat.offset[k], flat.offset[k] + d) for k, d in zip(rows.keys, rows.dims)])
        assert np.allclose(r, r_all[idx], rtol=1e-12, atol=1e-12)
        assert np.allclose(jm, j_all[idx][:, cols].toarray(), rtol=1e-10, atol=1e-12)
        # the rows touch no other column
        assert np.allclose(np.abs(j_all[idx]).sum(), np.abs(jm).sum(), rtol=1e-12)
    with pytest.raises(InputError, match="linear_solver.*non-Schur"):
        solve_ceres(flat, group=8)  # several landmarks per cost function cannot be Schur-eliminated
