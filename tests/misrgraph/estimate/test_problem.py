"""The one problem representation: the flat form's rows point at their own factors, merged
problems keep those positions, and every marginal path (GTSAM linearisation, flat normal
equations, sparse solve for a few keys) gives the same covariances as ``gtsam.Marginals``."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from misrgraph.estimate.graph import GraphConfig, build_pass_graph, merge_problems
from misrgraph.estimate.problem import flat_marginals, marginal_covariances
from misrgraph.estimate.solver import solve


@pytest.fixture(scope="module")
def solved(small_pass):
    sc, p = small_pass
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=True))
    return pg, solve(pg.problem)


def _gtsam_marginals(problem, values) -> gtsam.Marginals:
    """``gtsam.Marginals`` of a problem at ``values``: the factor batches' caches filled there
    while GTSAM linearises and eliminates, cleared after (queries need neither)."""
    for b in problem.batches:
        b.evaluate(values, True)
    try:
        return gtsam.Marginals(problem.graph, values)
    finally:
        for b in problem.batches:
            b.clear()


def test_each_flat_row_points_at_its_factor(solved):
    pg, _ = solved
    prob = pg.problem
    flat = prob.flat()
    pos = flat.row_positions()
    assert pos["collinearity"].size == flat.m_coll and pos["dem"].size == flat.m_dem > 0
    lm_of_obs = flat.coll.slot_keys[0]
    for row in range(0, flat.m_coll, 97):
        f = prob.graph.at(int(pos["collinearity"][row]))
        assert isinstance(f, gtsam.CustomFactor) and int(lm_of_obs[row // 2]) in [int(k) for k in f.keys()]
    for i in range(0, flat.m_dem, 13):
        assert [int(k) for k in prob.graph.at(int(pos["dem"][i])).keys()] == [int(flat.dem.keys[i])]


def test_merged_problems_keep_the_positions(small_pass):
    sc, p = small_pass
    a = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(), pass_index=0).problem
    shared = {int(k) for k in a.initial.keys()}
    b = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(), pass_index=1, shared=shared).problem
    m = merge_problems([a, b])
    assert len(m.batch_positions) == len(m.batches) == len(a.batches) + len(b.batches)
    sources = [(a, j) for j in range(len(a.batches))] + [(b, j) for j in range(len(b.batches))]
    for mpos, (src, j) in zip(m.batch_positions, sources):
        pos = src.batch_positions[j]
        assert mpos.size == pos.size
        for i in (0, pos.size // 2, pos.size - 1):
            assert list(m.graph.at(int(mpos[i])).keys()) == list(src.graph.at(int(pos[i])).keys())


def test_every_marginal_path_agrees_with_gtsam(solved):
    pg, res = solved
    prob = pg.problem
    lin_path = marginal_covariances(prob, res.values)
    flat_path = flat_marginals(prob.flat(), prob.flat().from_values(res.values))
    joint_keys = pg.knot_keys(1)[:4] + pg.ephemeris_keys()
    sparse_path = marginal_covariances(prob, res.values, joint_keys=joint_keys)
    ref_joint = _gtsam_marginals(prob, res.values).jointMarginalCovariance(gtsam.KeyVector(joint_keys)).fullMatrix()
    np.testing.assert_allclose(sparse_path.joint, ref_joint, rtol=1e-6, atol=1e-9 * np.max(np.abs(ref_joint)))
    np.testing.assert_allclose(
        lin_path.joint_of(joint_keys), ref_joint, rtol=1e-6, atol=1e-9 * np.max(np.abs(ref_joint))
    )
    for k in list(prob.dims)[::11]:
        np.testing.assert_allclose(flat_path[k], lin_path[k], rtol=1e-8, atol=1e-12 * np.max(np.abs(lin_path[k])))


def test_landmark_cross_covariance_agrees_with_gtsam(solved):
    """Two landmarks co-vary through the other variables only: ``G_i joint G_j^T`` from the
    marginals' landmark response is GTSAM's joint marginal of the pair, on both marginal paths;
    joint-only marginals refuse the question."""
    from misrgraph.errors import InputError

    pg, res = solved
    prob = pg.problem
    keys = [int(k) for k in pg.landmark_keys[[0, len(pg.landmark_keys) // 2, -1]]]
    ref = _gtsam_marginals(prob, res.values).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    for marg in (
        marginal_covariances(prob, res.values),
        flat_marginals(prob.flat(), prob.flat().from_values(res.values)),
    ):
        g = marg.landmark_response_of(keys)
        for i in range(3):
            for j in range(3):
                block = marg[keys[i]] if i == j else g[i] @ marg.joint @ g[j].T
                want = ref[3 * i : 3 * i + 3, 3 * j : 3 * j + 3]
                np.testing.assert_allclose(block, want, rtol=1e-6, atol=1e-8 * np.max(np.abs(np.diag(ref))))
    with pytest.raises(InputError, match="marginals"):
        marginal_covariances(prob, res.values, joint_keys=pg.ephemeris_keys()).landmark_response_of(keys[:1])
    with pytest.raises(InputError, match="keys"):
        marginal_covariances(prob, res.values).landmark_response_of([int(pg.ephemeris_keys()[0])])


def test_a_month_s_camera_marginals_agree_with_gtsam(small_month_dir, monkeypatch):
    """A calibration problem (GCP landmarks shared by several passes, the cameras by all), solved
    on GTSAM's elimination with the core's COLAMD ordering: the cameras' joint covariance equals
    ``gtsam.Marginals`` both ways, by nested elimination (the passes apart, the GCPs seen by
    several passes and the cameras as the separator) and, with that route switched off, by the
    sparse factorisation of the whole reduced system."""
    import misrgraph.estimate.problem as problem_mod
    from misrgraph.estimate.calibrate import CalibrateConfig, _build
    from misrgraph.estimate.solver import SolverParams
    from misrgraph.sim.simulate import load_scenario

    sc = load_scenario(small_month_dir)
    passes = [sc.load_pass(i) for i in range(10)]
    prob, _ = _build(passes, sc.camera_model, sc.gcps, CalibrateConfig().graph_config(), None, None)
    shared = {int(k) for k in prob.eliminate_first}
    assert len(shared) < sum(len(p.landmarks) for p in passes)  # landmarks are shared between passes
    res = solve(prob, SolverParams(backend="gtsam"))
    assert res.converged and res.backend == "gtsam"
    keys = [int(k) for k in prob.eliminate_last]
    assert len(keys) == 9
    routes = []
    nested = problem_mod._joint_by_separator
    monkeypatch.setattr(problem_mod, "_joint_by_separator", lambda *a: routes.append(nested(*a)) or routes[-1])
    by_separator = marginal_covariances(prob, res.values, joint_keys=keys)
    monkeypatch.setattr(problem_mod, "MAX_SEPARATOR", 0)
    whole = marginal_covariances(prob, res.values, joint_keys=keys)
    assert routes[0] is not None and routes[1] is None  # the nested route, then the whole system
    ref = _gtsam_marginals(prob, res.values).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    for sparse_path in (by_separator, whole):
        np.testing.assert_allclose(sparse_path.joint, ref, rtol=1e-6, atol=1e-9 * np.max(np.abs(ref)))


def test_variance_factor_closed_form():
    """Two unit-sigma priors on one 2-vector at a and b: the optimum is their mean, 2E = |a-b|^2/2
    on 4 rows - 2 unknowns = 2 dof."""
    from factors.priors import vector_prior
    from misrgraph.estimate.problem import Problem, variance_factor
    from misrgraph.estimate.solver import solve

    a, b = np.array([1.0, -2.0]), np.array([4.0, 2.0])
    g = gtsam.NonlinearFactorGraph()
    g.add(vector_prior(7, a, [1.0, 1.0]))
    g.add(vector_prior(7, b, [1.0, 1.0]))
    v = gtsam.Values()
    v.insert(7, np.zeros(2))
    prob = Problem(g, v, [], [], {7: 2})
    res = solve(prob)
    vf = variance_factor(prob, res.final_error)
    assert (vf["rows"], vf["unknowns"], vf["dof"]) == (4, 2, 2)
    assert vf["chi2"] == pytest.approx(np.sum((a - b) ** 2) / 2, rel=1e-9)
    assert vf["sigma0"] == pytest.approx(np.sqrt(np.sum((a - b) ** 2) / 4), rel=1e-9)


def test_variance_factor_is_one_where_the_weights_are_right(small_pass):
    """On a simulated pass whose noise is drawn with the weights' sigmas, with the injected
    blunders left out (by the simulator's record of them), 2E lies in the central 99.9 % of its
    chi-square distribution; with the blunders in, it lies far above."""
    from scipy import stats

    from misrgraph.estimate.problem import variance_factor

    sc, p = small_pass
    blunder = sc.load_truth(0).blunder
    assert blunder.any()
    clean = build_pass_graph(
        p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=True), exclude_observations=blunder
    )
    vf = variance_factor(clean.problem, solve(clean.problem).final_error)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], vf["dof"])
    assert vf["dof"] > 1000 and lo < vf["chi2"] < hi, vf
    dirty = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(use_dem=True))
    vd = variance_factor(dirty.problem, solve(dirty.problem).final_error)
    assert vd["chi2"] > hi and vd["p_value"] < 1e-6


def test_hessian_marginals_are_the_inverse_of_jtj_plus_the_dem_curvature(small_pass):
    """flat_marginals(second_order=True) against a dense inverse of J^T J (from the sparse
    Jacobian) plus the DEM curvature per landmark, kept where it leaves >= 0.5 of the block's
    information in every direction; and the floor is what it says."""
    sc, p = small_pass
    pg = build_pass_graph(
        p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(), exclude_observations=sc.load_truth(0).blunder
    )
    flat = pg.problem.flat()
    x = flat.from_values(solve(pg.problem).values)
    j = flat.jacobian(x).toarray()
    h = j.T @ j
    li, corr = flat.dem_curvature(x)
    add = np.zeros((len(pg.problem.eliminate_first), 3, 3))
    np.add.at(add, li, corr)
    kept = 0
    for i in np.unique(li):
        old = h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]
        new = old + add[i]
        if np.linalg.eigvalsh(new)[0] > 0 and np.linalg.eigvals(np.linalg.solve(old, new)).real.min() >= 0.5:
            h[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = new
            kept += 1
    assert kept > 0.5 * np.unique(li).size
    cov = np.linalg.inv(h)
    m = flat_marginals(flat, x, second_order=True)
    for k in list(pg.problem.eliminate_first[:20]) + pg.problem.other_keys[:20]:
        o, d = flat.offset[k], pg.problem.dims[k]
        np.testing.assert_allclose(
            m[k], cov[o : o + d, o : o + d], rtol=1e-6, atol=1e-9 * np.abs(cov[o : o + d, o : o + d]).max()
        )
    gn = flat_marginals(flat, x)
    k0 = pg.problem.eliminate_first[0]
    assert not np.allclose(m[k0], gn[k0])


def _two_passes(small_pass, robust: str = "none"):
    sc, p = small_pass
    cfg = GraphConfig(robust=robust)
    a = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, cfg, pass_index=0).problem
    shared = {int(k) for k in a.initial.keys()}
    b = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, cfg, pass_index=1, shared=shared).problem
    return a, b


def test_merge_flat_is_the_merged_problem_in_flat_form(small_pass):
    """Two passes sharing their landmarks: one collinearity and one DEM batch, the same variables,
    the same cost and the same optimum as merge_problems solved by GTSAM's elimination."""
    from misrgraph.estimate.graph import merge_flat
    from misrgraph.estimate.solver import SolverParams

    a, b = _two_passes(small_pass)
    ref, m = merge_problems([a, b]), merge_flat([a, b])
    assert [type(bt).__name__ for bt in m.batches] == ["CollinearityBatch", "DemBatch"]
    assert m.eliminate_first == ref.eliminate_first and m.dims == ref.dims and m.eliminate_last == ref.eliminate_last
    assert int(m.graph.size()) == int(ref.graph.size())
    flat = m.flat()
    assert flat.m_coll == sum(
        2 * len(bt) for p in (a, b) for bt in p.batches if type(bt).__name__ == "CollinearityBatch"
    )
    assert flat.cost(flat.initial()) == pytest.approx(ref.graph.error(ref.initial), rel=1e-12)
    assert m.graph.error(m.initial) == pytest.approx(ref.graph.error(ref.initial), rel=1e-12)
    tight = SolverParams(relative_error_tol=1e-12, absolute_error_tol=1e-12)
    rs = solve(m, tight.replace(backend="schur"))
    rg = solve(ref, tight.replace(backend="gtsam"))
    assert rs.backend == "schur" and rg.backend == "gtsam"
    assert rs.final_error == pytest.approx(rg.final_error, rel=1e-7)
    cov = flat_marginals(flat, flat.from_values(rs.values))
    worst = max(
        np.max(np.abs(rs.values.atVector(k) - rg.values.atVector(k)) / np.sqrt(np.diag(cov[k]))) for k in m.dims
    )
    assert worst < 0.01


def test_merge_flat_refuses_what_the_flat_form_does_not_cover(small_pass):
    from misrgraph.estimate.graph import merge_flat
    from misrgraph.estimate.problem import NotFlat

    a, b = _two_passes(small_pass, robust="huber")
    with pytest.raises(NotFlat, match="robust"):
        merge_flat([a, b])


def test_gauss_newton_step_is_gtsams_linear_solution(solved):
    """At the start the undamped step of the Schur path equals GTSAM's elimination of the
    linearised graph; at a tightly converged optimum it vanishes (in sigma units), while the
    default criterion (relative decrease 1e-5) leaves it measurable."""
    from misrgraph.estimate.solver import SolverParams, gauss_newton_step, linearize

    pg, loose = solved
    prob = pg.problem
    flat = prob.flat()
    d = gauss_newton_step(flat, flat.initial())
    lin = linearize(prob, prob.initial)
    for bt in prob.batches:
        bt.clear()
    sol = lin.optimize()
    ref = np.concatenate([np.asarray(sol.at(k)) for k in flat.keys])
    assert np.allclose(d, ref, rtol=1e-6, atol=1e-9 * np.max(np.abs(ref)))
    res = solve(prob, SolverParams(relative_error_tol=1e-14, absolute_error_tol=1e-14))
    x = flat.from_values(res.values)
    cov = flat_marginals(flat, x)
    sig = np.concatenate([np.sqrt(np.diag(cov[k])) for k in flat.keys])
    assert np.max(np.abs(gauss_newton_step(flat, x)) / sig) < 1e-3
    x_loose = flat.from_values(loose.values)
    assert np.max(np.abs(gauss_newton_step(flat, x_loose)) / sig) > np.max(np.abs(gauss_newton_step(flat, x)) / sig)


def _gcps_in_scenes(sc, p, per_scene: int, shared_sigma_m: float = 20.0):
    """The pass's GCP database with its GCPs grouped ``per_scene`` to a source scene."""
    import dataclasses

    from misrgraph.io.passes import KIND_GCP

    rows = np.unique(p.landmarks.gcp_index[p.landmarks.kind == KIND_GCP])
    scene = np.full(len(sc.gcps), -1, np.int64)
    scene[rows] = np.arange(rows.size) // per_scene
    return dataclasses.replace(sc.gcps, scene=scene, scene_sigma_m=np.full(len(sc.gcps), shared_sigma_m)), rows


def test_gcp_scene_offsets_in_every_marginal_path(small_pass):
    """All the pass's GCPs in one source scene: the flat normal equations (landmark-offset
    coupling in H_lc) equal J^T J of the sparse Jacobian, the flat marginals equal
    ``gtsam.Marginals``, and the mean of the GCPs is known less well than with independent priors of
    the same sigma."""
    from factors import keys as K

    sc, p = small_pass
    db, rows = _gcps_in_scenes(sc, p, per_scene=10**6)
    assert rows.size >= 2
    pg = build_pass_graph(p, sc.camera_model, sc.dem, db, GraphConfig(), exclude_observations=sc.load_truth(0).blunder)
    scene = K.gcp_scene_key(0)
    assert scene in pg.problem.dims and scene in pg.problem.eliminate_last
    res = solve(pg.problem)
    flat = pg.problem.flat()
    x = flat.from_values(res.values)
    j = flat.jacobian(x)
    h = (j.T @ j).toarray()
    blk, hlc, hcc, g, _ = flat.normal_equations(x)
    n_l = 3 * blk.shape[0]
    scale = np.abs(h).max()
    np.testing.assert_allclose(hlc.reshape(n_l, -1), h[:n_l, n_l:], atol=1e-9 * scale)
    np.testing.assert_allclose(hcc, h[n_l:, n_l:], atol=1e-9 * scale)
    # at the optimum g is a cancellation of large terms: compare within rounding of their sum
    r = flat.residual(x)
    rounding = 1e-9 * (abs(j).T @ np.abs(r))
    assert np.all(np.abs(g - j.T @ r) <= rounding), np.max(np.abs(g - j.T @ r) / rounding)
    m = flat_marginals(flat, x)
    ref = _gtsam_marginals(pg.problem, res.values)
    for k in [K.gcp_key(int(r)) for r in rows] + [scene]:
        np.testing.assert_allclose(m[k], ref.marginalCovariance(k), rtol=1e-6)
    # the scene's common error: the mean of its GCPs is known less well than with independent
    # priors (their differences better: the joint prior is not smaller in every direction)
    keys = [K.gcp_key(int(r)) for r in rows]
    pg0 = build_pass_graph(
        p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(), exclude_observations=sc.load_truth(0).blunder
    )
    avg = np.kron(np.full((1, rows.size), 1.0 / rows.size), np.eye(3))
    var_mean = []
    for q, r_ in ((pg, res), (pg0, solve(pg0.problem))):
        joint = _gtsam_marginals(q.problem, r_.values).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
        var_mean.append(np.trace(avg @ joint @ avg.T))
    assert var_mean[0] > 1.05 * var_mean[1]


def test_a_scene_of_one_gcp_is_its_plain_prior(small_pass):
    """One GCP per scene: the offset and the own error add up to the catalogue's sigma, so the
    solution and every landmark's marginal are those of the plain GCP prior."""
    sc, p = small_pass
    db, rows = _gcps_in_scenes(sc, p, per_scene=1)
    ex = sc.load_truth(0).blunder
    out = []
    for gcps in (db, sc.gcps):
        pg = build_pass_graph(p, sc.camera_model, sc.dem, gcps, GraphConfig(), exclude_observations=ex)
        res = solve(pg.problem)
        flat = pg.problem.flat()
        out.append((pg, res, flat_marginals(flat, flat.from_values(res.values))))
    (pga, ra, ma), (pgb, rb, mb) = out
    assert len(pga.problem.dims) == len(pgb.problem.dims) + rows.size
    for k in pgb.problem.eliminate_first:
        np.testing.assert_allclose(ra.values.atVector(k), rb.values.atVector(k), atol=1e-3)
        # the two solves stop at the same tolerance, not at the same point: 1e-5 of the block
        np.testing.assert_allclose(ma[k], mb[k], rtol=1e-5, atol=1e-5 * np.abs(mb[k]).max())


def test_dem_sigma_scale_multiplies_the_stated_dem_sigma(small_pass):
    """``dem_sigma_scale`` scales the DEM's stated 1 sigma at each landmark and not the local
    surface fit's residual: a factor's sigma is ``sqrt((k stated)^2 + rms^2)``, checked against
    :func:`fit_local_surface` at the landmarks (``sigma^2 = stated^2 + rms^2``), and the batch
    keeps ``k stated`` as its stated part; a non-positive factor is refused."""
    from factors.dem_height import DemBatch
    from misrgraph.errors import InputError
    from misrgraph.model.dem import fit_local_surface
    from misrgraph.model.frames import ecef_to_geodetic

    sc, p = small_pass
    graphs = [build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(dem_sigma_scale=f)) for f in (1.0, 2.0)]
    batches = [next(b for b in g.problem.batches if isinstance(b, DemBatch)) for g in graphs]
    np.testing.assert_array_equal(batches[0].keys, batches[1].keys)
    lat, lon, _ = ecef_to_geodetic(np.stack([graphs[0].problem.initial.atVector(int(k)) for k in batches[0].keys]))
    s = fit_local_surface(sc.dem, lat, lon)
    rms2 = s.sigma**2 - s.stated**2
    assert np.all(rms2 > 0)
    for f, b in zip((1.0, 2.0), batches):
        np.testing.assert_allclose(b.sigma_m, np.sqrt((f * s.stated) ** 2 + rms2), rtol=1e-12)
        np.testing.assert_allclose(b.stated_m, f * s.stated, rtol=1e-12)
    assert np.all(batches[1].sigma_m < 2.0 * batches[0].sigma_m)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputError, match="dem_sigma_scale"):
            GraphConfig(dem_sigma_scale=bad)


def test_dem_smoothing_reads_the_low_passed_dem_with_the_raw_sigma(small_pass):
    """``dem_smoothing_postings``: the height factors read the DEM low-passed by
    :meth:`DemTiles.smoothed` (heights and slopes at the landmarks equal that DEM's local surface,
    and differ from the raw DEM's), while their sigma is the raw DEM's stated one; a negative or
    larger-than-2-postings sigma is refused by name."""
    from factors.dem_height import DemBatch
    from misrgraph.errors import InputError
    from misrgraph.model.dem import fit_local_surface
    from misrgraph.model.frames import ecef_to_geodetic

    sc, p = small_pass
    raw, smooth = [
        next(
            b
            for b in build_pass_graph(
                p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(dem_smoothing_postings=f)
            ).problem.batches
            if isinstance(b, DemBatch)
        )
        for f in (0.0, 1.0)
    ]
    np.testing.assert_array_equal(raw.keys, smooth.keys)
    cfg = GraphConfig(dem_smoothing_postings=1.0)
    pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, cfg)
    lat, lon, _ = ecef_to_geodetic(np.stack([pg.problem.initial.atVector(int(k)) for k in smooth.keys]))
    # sigma: the raw DEM's at the (initial) landmarks, times the scale
    np.testing.assert_allclose(
        smooth.sigma_m, fit_local_surface(sc.dem, lat, lon).sigma * cfg.dem_sigma_scale, rtol=1e-12
    )
    h, dlat, dlon = smooth.surface(lat, lon)
    ref = fit_local_surface(sc.dem.smoothed(1.0), lat, lon)
    np.testing.assert_allclose(h, ref.height, atol=1e-9)
    np.testing.assert_allclose(dlat, ref.dh_dlat, rtol=1e-9, atol=1e-9)
    assert np.max(np.abs(h - raw.surface(lat, lon)[0])) > 0.1  # the low-pass changed the heights read
    for bad in (-0.5, 3.0, float("nan")):
        with pytest.raises(InputError, match="dem_smoothing_postings"):
            GraphConfig(dem_smoothing_postings=bad)


def test_knot_prior_damping_sets_the_process_prior(small_pass):
    """``knot_prior_damping`` is the damping of the process prior in the graph: with the knots at
    zero (no data factor touched), the graph's prior part has the information of the process's
    joint covariance, built independently from ``process_correlation`` of each knot pair's lag;
    a non-positive damping is refused by name."""
    from misrgraph.errors import InputError
    from misrgraph.model.errormodels import ATTITUDE_RATE_FACTOR, process_correlation

    sc, p = small_pass
    for zeta in (0.58, 1.0):
        pg = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, GraphConfig(knot_prior_damping=zeta))
        keys = pg.knot_keys(1)
        prior = gtsam.NonlinearFactorGraph()
        g = pg.problem.graph
        for i in range(g.size()):
            f = g.at(i)
            if (
                f is not None
                and set(f.keys()) <= set(keys)
                and isinstance(f, gtsam.LinearContainerFactor | gtsam.PriorFactorVector)
            ):
                prior.add(f)
        v = gtsam.Values()
        for k in keys:
            v.insert(k, np.zeros(2))
        m = gtsam.Marginals(prior, v)
        t = pg.attitude_model.knot_times[1]
        lag = t[2] - t[0]  # 120 s: correlation 0.48 at damping 1, 0.31 at 0.58
        joint = m.jointMarginalCovariance(gtsam.KeyVector([keys[0], keys[2]])).fullMatrix()
        var = joint[0, 0]
        assert joint[2, 0] / var == pytest.approx(float(process_correlation(lag, ATTITUDE_RATE_FACTOR, zeta)), abs=1e-6)
    for bad in (0.0, -0.5, float("inf")):
        with pytest.raises(InputError, match="knot_prior_damping"):
            GraphConfig(knot_prior_damping=bad)


@pytest.mark.parametrize("shared", [False, True])
def test_nested_elimination_equals_the_dense_inverse(shared):
    """Two groups of variables, joint variables coupling them, and three landmarks (the third seen
    by both groups when ``shared``): the nested elimination's joint covariance is the joint block
    of the dense inverse of the whole information matrix."""
    import scipy.sparse as sp

    from misrgraph.estimate.problem import _joint_by_separator

    rng = np.random.default_rng(0)
    n_c, idx = 10, np.array([8, 9])
    a = rng.standard_normal((60, n_c + 9))
    h = a.T @ a
    group = {**{i: 1 for i in range(4)}, **{i: 2 for i in range(4, 8)}, 10: 1, 11: 1, 12: 1, 13: 2, 14: 2, 15: 2}
    for i in range(16, 19):
        group[i] = 0 if shared else 1  # 0: coupled to both groups
    landmark = {i: (i - n_c) // 3 for i in range(n_c, n_c + 9)}
    for i in range(n_c + 9):
        for j in range(n_c + 9):
            gi, gj = group.get(i), group.get(j)
            apart = gi is not None and gj is not None and gi and gj and gi != gj
            two_landmarks = i in landmark and j in landmark and landmark[i] != landmark[j]
            if apart or two_landmarks:
                h[i, j] = 0.0
    h += 20 * np.eye(n_c + 9)
    h_ll = np.stack([h[n_c + 3 * k : n_c + 3 * k + 3, n_c + 3 * k : n_c + 3 * k + 3] for k in range(3)])
    joint = _joint_by_separator(h_ll, sp.csr_matrix(h[n_c:, :n_c]), sp.csr_matrix(h[:n_c, :n_c]), idx)
    np.testing.assert_allclose(joint, np.linalg.inv(h)[np.ix_(idx, idx)], rtol=1e-10)
