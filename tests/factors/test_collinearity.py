from __future__ import annotations

import gtsam
import numpy as np
import pytest

from factors import keys as K
from factors.collinearity import FactorShapeError, collinearity_residual
from misrgraph.estimate.graph import GraphConfig, build_pass_graph
from misrgraph.model.constants import CAMERAS

NO_REMOVAL = GraphConfig(threshold1=0, threshold2=0, use_dem=False)


@pytest.fixture(scope="module")
def graph(exact_pass):
    sc, p = exact_pass
    return build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, NO_REMOVAL)


def _truth_values(sc, p, pg) -> gtsam.Values:
    v = gtsam.Values()
    truth = sc.load_truth(0)
    for key, row in zip(pg.landmark_keys, pg.landmark_rows):
        v.insert(int(key), truth.landmark_ecef[row])
    tr = truth.attitude_error
    for a in range(3):
        np.testing.assert_allclose(tr.knot_times[a], pg.attitude_model.knot_times[a])
        for j, k in enumerate(pg.knot_keys(a)):
            v.insert(k, tr.knots[a][j])
    for s, k in enumerate(pg.ephemeris_keys()):
        v.insert(k, truth.ephemeris_error.params[s])
    t, m = truth.camera_model, sc.camera_model
    for c, k in pg.camera_keys.items():
        v.insert(k, np.array([t.delta[c] - m.delta[c], t.beta[c] - m.beta[c], t.epsilon[c] - m.epsilon[c]]))
    return v


def test_zero_residual_at_truth_noise_free(exact_pass, graph):
    sc, p = exact_pass
    v = _truth_values(sc, p, graph)
    r, _ = graph.collinearity.residuals(v)
    assert np.unique(graph.collinearity.const.k).size > 1  # several cameras/bands
    assert np.max(np.abs(r)) < 1e-6  # pixels


def _random_args(pg, rng):
    b = pg.collinearity
    n = len(b)
    land = np.stack([np.zeros(3)] * n)
    v = gtsam.Values(pg.problem.initial)
    land, theta, knots, cam, om = b._gather(v, slice(0, n))
    land = land + rng.normal(size=land.shape) * 200.0
    theta = rng.normal(size=theta.shape) * [0.05, 0.01, 0.01, 50, 50, 50]
    knots = rng.normal(size=knots.shape) * np.array([1e-4, 1e-6, 1e-4, 1e-6])
    cam = cam + rng.normal(size=cam.shape) * np.r_[[1e-3] * 3, 1e-4, [1e-6, 1e-6, 1e-9, 1e-12, 1e-15, 1e-18]]
    om = om + rng.normal(size=om.shape) * 1e-3
    return dict(landmark=land, theta=theta, knots=knots, camera=cam, omega=om)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jacobians_match_numerical_derivatives_all_cameras(graph, seed):
    rng = np.random.default_rng(seed)
    args = _random_args(graph, rng)
    c = graph.collinearity.const
    assert set(np.unique(graph.collinearity.slot_keys[0] >= 0)) == {True}
    _, jac = collinearity_residual(**args, c=c)
    # central-difference steps on each parameter's own scale (m, m/s, rad, m, pixel^-i)
    steps = {
        "landmark": [1e-2] * 3,
        "theta": [1e-5] * 3 + [1e-2] * 3,
        "camera": [1e-8] * 3 + [1e-8] + [1e-9, 1e-11, 1e-13, 1e-15, 1e-17, 1e-19],
        "omega": [1e-8] * 3,
    }
    for name, hs in steps.items():
        x = args[name]
        for i, h in enumerate(hs):
            xp, xm = x.copy(), x.copy()
            xp[..., i] += h
            xm[..., i] -= h
            rp, _ = collinearity_residual(**{**args, name: xp}, c=c, jacobians=False)
            rm, _ = collinearity_residual(**{**args, name: xm}, c=c, jacobians=False)
            num = (rp - rm) / (2 * h)
            ana = jac[name][..., i]
            scale = np.max(np.abs(ana)) + 1e-300
            assert np.max(np.abs(num - ana)) / scale < 1e-6, (name, i)
    x = args["knots"]
    for a in range(3):
        for i in range(4):
            h = 1e-7 if i % 2 == 0 else 1e-9
            xp, xm = x.copy(), x.copy()
            xp[:, a, i] += h
            xm[:, a, i] -= h
            num = (
                collinearity_residual(**{**args, "knots": xp}, c=c, jacobians=False)[0]
                - collinearity_residual(**{**args, "knots": xm}, c=c, jacobians=False)[0]
            ) / (2 * h)
            ana = jac["knots"][:, :, a, i]
            assert np.max(np.abs(num - ana)) / np.max(np.abs(ana)) < 1e-6, (a, i)
    k = graph.collinearity.const.k
    assert np.all(np.isfinite(k)) and np.unique(k).size > 1  # each observation carries its own camera's k
    assert len(np.unique(graph.collinearity.order)) == len(graph.collinearity)


def test_all_cameras_present(graph):
    cams = set()
    for key in graph.camera_keys:
        cams.add(key)
    assert cams == set(range(len(CAMERAS)))


def test_cached_and_live_linearisations_agree(graph):
    prob = graph.problem
    v = prob.initial
    for b in prob.batches:
        b.clear()
    live = prob.graph.linearize(v)
    for b in prob.batches:
        b.evaluate(v, True)
    cached = prob.graph.linearize(v)
    for b in prob.batches:
        b.clear()
    assert live.size() == cached.size()
    for i in range(live.size()):
        a1, b1 = live.at(i).jacobian()
        a2, b2 = cached.at(i).jacobian()
        np.testing.assert_allclose(a1, a2, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(b1, b2, rtol=1e-12, atol=1e-12)


def test_h_none_path_gives_the_whitened_error(graph):
    prob = graph.problem
    b = graph.collinearity
    b.clear()
    r, _ = b.residuals(prob.initial)
    expected = 0.5 * np.sum((r / b.sigma_px) ** 2)
    got = sum(prob.graph.at(i).error(prob.initial) for i in range(b.layout.n_factors))
    assert got == pytest.approx(expected, rel=1e-10)


def test_wrong_shapes_are_rejected_before_gtsam(graph, monkeypatch):
    b = graph.collinearity
    factor = b.factors()[0]
    good = b.factor_rows

    def bad_rows(f, values, want_h):
        r, blocks = good(f, values, want_h)
        return r, [blk[:, :-1] for blk in blocks] if blocks is not None else None

    monkeypatch.setattr(b, "factor_rows", bad_rows)
    with pytest.raises(Exception) as info:
        factor.linearize(graph.problem.initial)
    assert "Jacobian" in str(info.value) or isinstance(info.value, FactorShapeError)

    def bad_residual(f, values, want_h):
        r, blocks = good(f, values, want_h)
        return r[:-1], blocks

    monkeypatch.setattr(b, "factor_rows", bad_residual)
    with pytest.raises(Exception) as info:
        factor.error(graph.problem.initial)
    assert "residual shape" in str(info.value)


def test_per_observation_grouping_gives_the_same_system(exact_pass):
    sc, p = exact_pass
    a = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, NO_REMOVAL)
    b = build_pass_graph(p, sc.camera_model, sc.dem, sc.gcps, NO_REMOVAL.replace(group_by="observation"))
    assert b.problem.graph.size() > a.problem.graph.size()
    ha = a.problem.graph.linearize(a.problem.initial).hessian()
    hb = b.problem.graph.linearize(b.problem.initial).hessian()
    np.testing.assert_allclose(ha[0], hb[0], rtol=1e-9, atol=1e-9 * np.max(np.abs(ha[0])))
    assert K.describe(int(a.landmark_keys[0]))[0] in "lg"


def test_cache_answers_only_for_the_values_it_was_computed_at(graph):
    """A live cache serves factors called with the same Values object, and only those: the error
    at any other point is computed live (the issue: a graph.error(v) during a live cache returned
    the cached point's error). Checked by planting a zero residual in the cache."""
    prob = graph.problem
    b = graph.collinearity
    n = b.layout.n_factors
    v0 = prob.initial
    r, _ = b.residuals(v0)
    live0 = sum(prob.graph.at(i).error(v0) for i in range(n))
    v1 = gtsam.Values(v0)
    k = int(graph.landmark_keys[0])
    v1.update(k, v0.atVector(k) + np.array([300.0, 0.0, 0.0]))
    live1 = sum(prob.graph.at(i).error(v1) for i in range(n))
    assert live0 > 0 and live1 != pytest.approx(live0)
    try:
        b.cache(np.zeros_like(r), None, values=v0)
        assert sum(prob.graph.at(i).error(v0) for i in range(n)) == 0.0  # the cache is used for v0...
        assert sum(prob.graph.at(i).error(v1) for i in range(n)) == pytest.approx(live1, rel=1e-12)  # ...not v1
        assert sum(prob.graph.at(i).error(gtsam.Values(v0)) for i in range(n)) == pytest.approx(live0, rel=1e-12)
    finally:
        b.clear()


def test_solver_linearize_uses_the_cache(graph, monkeypatch):
    """The vectorised path is really taken inside ``solver.linearize`` (no per-factor live
    evaluation), so keying the cache by the Values object costs no speed."""
    from misrgraph.estimate.solver import linearize

    b = graph.collinearity
    calls = {"live": 0}
    real = b._gather

    def counting(values, sl):
        if sl.stop - sl.start < len(b):
            calls["live"] += 1
        return real(values, sl)

    monkeypatch.setattr(b, "_gather", counting)
    lin = linearize(graph.problem, graph.problem.initial)
    assert lin.size() == graph.problem.graph.size() and calls["live"] == 0
