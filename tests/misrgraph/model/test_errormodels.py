from __future__ import annotations

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.model.errormodels import (
    ATTITUDE_RATE_FACTOR,
    JITTER_PERIODS_S,
    AttitudeErrorModel,
    EphemerisErrorModel,
    ephemeris_prior_covariance,
    interval_counts,
    knots_to_remove,
    projected_band_covariance,
    spline_design,
    uniform_knots,
    unresolved_band_sigma,
    unresolved_process_sigma,
)


def test_ephemeris_closed_form_and_jacobian(rng):
    m = EphemerisErrorModel(np.array([0.0, 100.0, 300.0]), rng.normal(size=(2, 6)))
    t = np.array([0.0, 50.0, 99.0, 100.0, 250.0, 300.0])
    e = m.evaluate(t)
    a, b = m.params[:, :3], m.params[:, 3:]
    expect = np.stack([a[0] * 0 + b[0], a[0] * 50 + b[0], a[0] * 99 + b[0], b[1], a[1] * 150 + b[1], a[1] * 200 + b[1]])
    np.testing.assert_allclose(e, expect)
    seg, d = m.design(t)
    h = 1e-6
    for j in range(6):
        p2 = m.params.copy()
        p2[seg[2], j] += h
        num = (EphemerisErrorModel(m.boundaries, p2).evaluate(t[2:3]) - e[2:3]) / h
        np.testing.assert_allclose(d[2, :, j], num[0], atol=1e-6)


def test_ephemeris_validation():
    with pytest.raises(InputError, match="params"):
        EphemerisErrorModel(np.array([0.0, 1.0]), np.zeros((2, 6)))
    with pytest.raises(InputError, match="boundaries"):
        EphemerisErrorModel(np.array([1.0, 0.0]), np.zeros((1, 6)))


@pytest.fixture
def spline(rng):
    kt = [uniform_knots(0, 600, s) for s in (120, 60, 120)]
    return AttitudeErrorModel(kt, [rng.normal(size=(k.size, 2)) * [1e-4, 1e-6] for k in kt])


def test_spline_continuity_of_value_and_rate_at_knots(spline):
    for a in range(3):
        for tk in spline.knot_times[a][1:-1]:
            eps = 1e-7
            lo, hi = spline.evaluate([tk - eps])[0, a], spline.evaluate([tk + eps])[0, a]
            assert lo == pytest.approx(hi, abs=1e-12)
            rlo, rhi = spline.rate([tk - eps])[0, a], spline.rate([tk + eps])[0, a]
            assert rlo == pytest.approx(rhi, abs=1e-12)
        # knot value and rate are interpolated exactly
        np.testing.assert_allclose(spline.evaluate(spline.knot_times[a])[:, a], spline.knots[a][:, 0], atol=1e-15)
        np.testing.assert_allclose(
            spline.rate(spline.knot_times[a])[:, a], spline.knots[a][:, 1], rtol=1e-9, atol=1e-15
        )


def test_spline_rate_is_derivative(spline, rng):
    """Inside the knots and where the end segments are extended (both sides)."""
    lo = min(k[0] for k in spline.knot_times)
    hi = max(k[-1] for k in spline.knot_times)
    t = np.r_[rng.uniform(1, 599, 20), lo - 3.0, hi + 3.0]
    h = 1e-4
    num = (spline.evaluate(t + h) - spline.evaluate(t - h)) / (2 * h)
    np.testing.assert_allclose(spline.rate(t), num, rtol=1e-6, atol=1e-13)


def test_spline_jacobian_wrt_knots(spline, rng):
    t = rng.uniform(0, 600, 15)
    for a in range(3):
        i, w = spline.bracket(a, t)
        base = spline.evaluate(t)[:, a]
        for col, (off, comp) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
            for n in range(t.size):
                kn = [k.copy() for k in spline.knots]
                kn[a][i[n] + off, comp] += 1e-3
                num = (AttitudeErrorModel(spline.knot_times, kn).evaluate(t[n : n + 1])[0, a] - base[n]) / 1e-3
                assert w[n, col] == pytest.approx(num, rel=1e-6, abs=1e-9)


def test_constant_and_linear_error_are_reproduced():
    kt = [np.array([0.0, 60, 120, 180])] * 3
    # a straight line E = c + r t is a cubic with zero c2, c3
    kn = [np.stack([2e-5 + 1e-7 * k, np.full(4, 1e-7)], -1) for k in kt]
    m = AttitudeErrorModel(kt, kn)
    t = np.linspace(0, 180, 37)
    np.testing.assert_allclose(m.evaluate(t)[:, 1], 2e-5 + 1e-7 * t, atol=1e-18)


def test_interval_counts_and_knot_removal_eq28_29():
    kt = np.array([0.0, 60, 120, 180, 240, 300])
    # interval 0: 30 obs over 5 cameras; interval 1: 3 obs (eq. 28 fails with T1=10);
    # interval 2: 40 obs but only 2 cameras (eq. 29 fails with T2=3); interval 3: nothing; 4: fine
    t = np.r_[np.full(30, 10.0), np.full(3, 70.0), np.full(40, 130.0), np.full(25, 250.0)]
    cam = np.r_[np.arange(30) % 5, [0, 1, 2], np.arange(40) % 2, np.arange(25) % 9]
    c = interval_counts(kt, t, cam)
    assert c.shape == (5, 9)
    np.testing.assert_array_equal(c.sum(1), [30, 3, 40, 0, 25])
    removed = knots_to_remove(c, threshold1=10, threshold2=3)
    np.testing.assert_array_equal(removed, [1, 2, 3])
    # the first knot is kept even when its interval is empty
    c0 = c.copy()
    c0[0] = 0
    assert 0 not in knots_to_remove(c0, 10, 3)


def test_support_rule_judges_both_segments_of_a_knot():
    # interval counts: 0: 30, 1: 0, 2: 0, 3: 25, 4: 0 (all with >= 3 cameras where non-zero)
    c = np.zeros((5, 9), int)
    c[0, :5] = 6
    c[3, :5] = 5
    # literal rule: knots 1, 2, 4 fail (their own interval is empty); 4 is the last interval's knot
    np.testing.assert_array_equal(knots_to_remove(c, 1, 1, "interval"), [1, 2, 4])
    # support rule: knot 1 sees intervals 0+1 (data), knot 2 sees 1+2 (empty), knot 3 sees 2+3,
    # knot 4 sees 3+4 -> only knot 2 goes, so the merged segment [t_1, t_3) holds no data
    np.testing.assert_array_equal(knots_to_remove(c, 1, 1, "support"), [2])
    with pytest.raises(InputError, match="rule"):
        knots_to_remove(c, 1, 1, "both")


def test_spline_spans_neighbours_after_removal(spline):
    m = spline.without([np.array([], int), np.array([3, 4]), np.array([])])
    kt = m.knot_times[1]
    assert 180.0 not in kt and 240.0 not in kt
    i, w = m.bracket(1, np.array([200.0]))
    assert kt[i[0]] == 120.0 and kt[i[0] + 1] == 300.0


def test_spline_design_is_the_spline(spline, rng):
    """``B @ knots`` is :meth:`AttitudeErrorModel.evaluate`, inside the knots and where the end
    segments are extended."""
    for a in range(3):
        kt = spline.knot_times[a]
        t = rng.uniform(kt[0] - 50.0, kt[-1] + 50.0, 200)
        np.testing.assert_allclose(
            spline_design(kt, t) @ spline.knots[a].ravel(), spline.evaluate(t)[:, a], rtol=1e-12, atol=1e-18
        )


def _jitter_draws(kt, n, seed):
    """The simulator's own jitter (a random sum of 12 sinusoids, ``smooth_process``), 1 sigma 1,
    sampled every second over the knots, and its least-squares spline fit's knots."""
    from misrgraph.sim.simulate import smooth_process

    gen = np.random.default_rng(seed)
    t = np.arange(kt[0], kt[-1] + 0.5, 1.0)
    b = spline_design(kt, t)
    e = np.array([smooth_process(gen, 1.0, n_terms=12, periods_s=JITTER_PERIODS_S)(t)[0] for _ in range(n)])
    k = np.linalg.solve(b.T @ b, b.T @ e.T).T
    return e, k, b


def test_projected_band_covariance_is_the_spread_of_the_simulators_jitter_fits():
    """The knots' share of a jitter (closed form from its band's correlation) against 800 draws of
    the simulator's jitter fitted by least squares: per knot value and rate, end knots apart, the
    mean ratio of the draws' mean square to the predicted variance is 1 within 4 standard errors
    of the draws' own scatter."""
    kt = uniform_knots(0.0, 900.0, 60.0)
    cov = projected_band_covariance(kt, 1.0)
    _, k, _ = _jitter_draws(kt, 800, 11)
    var = np.diag(cov).reshape(-1, 2)
    for part, sl in (("ends", [0, -1]), ("interior", slice(1, -1))):
        for c, name in enumerate(("value", "rate")):
            z = (k.reshape(len(k), -1, 2)[:, sl, c] ** 2 / var[sl, c]).mean(axis=1)  # per draw
            se = z.std(ddof=1) / np.sqrt(z.size)
            assert abs(z.mean() - 1) < 4 * se, (part, name, z.mean(), se)
    # the end knots take up more of it than the interior ones (half a support each)
    assert var[0, 0] > 2 * var[7, 0] and var[0, 1] > 1.5 * var[7, 1]


def test_unresolved_band_sigma_is_the_fits_residual_and_has_its_limits():
    kt = uniform_knots(0.0, 900.0, 60.0)
    e, k, b = _jitter_draws(kt, 400, 12)
    resid = np.mean((e - k @ b.T) ** 2, axis=1)
    se = resid.std(ddof=1) / np.sqrt(resid.size)
    assert abs(unresolved_band_sigma(kt, 1.0) ** 2 - resid.mean()) < 4 * se
    assert unresolved_band_sigma(kt, 2.0) == pytest.approx(2 * unresolved_band_sigma(kt, 1.0), rel=1e-12)
    # periods far above the knot spacing are all the spline's; far below, none of it
    assert unresolved_band_sigma(kt, 1.0, (2000.0, 20000.0)) < 1e-3
    assert unresolved_band_sigma(kt, 1.0, (3.0, 6.0)) > 0.999
    with pytest.raises(InputError, match="periods_s"):
        projected_band_covariance(kt, 1.0, (120.0, 8.0))
    with pytest.raises(InputError, match="sigma"):
        unresolved_band_sigma(kt, -1.0)
    with pytest.raises(InputError, match="periods_s"):
        unresolved_band_sigma(kt, 1.0, (120.0, 8.0))
    with pytest.raises(InputError, match="knot_times"):
        projected_band_covariance([0.0], 1.0)


def test_unresolved_process_sigma_is_the_residual_of_spline_fits_to_the_process():
    """What the spline misses of the slow attitude process (closed form from its correlation
    function) against 400 draws of the process stepped by its exact transition
    (:func:`factors.priors.process_transition`, stationary start, every 1 s) and fitted by least
    squares: the mean square residual within 4 standard errors of the draws' scatter, for a fast
    process (natural frequency 0.1/s) on knots every 60 s and every 15 s; the pre-flight process
    on 60 s knots leaves under 3 % of its sigma."""
    from factors.priors import process_transition

    gen = np.random.default_rng(21)
    lam, zeta, n = 0.1, 0.58, 400
    t = np.arange(0.0, 900.5, 1.0)
    phi, q = process_transition(1.0, 1.0, lam, zeta)
    lq = np.linalg.cholesky(q)
    x = gen.standard_normal((n, 2)) * [1.0, lam]
    e = np.empty((n, t.size))
    for i in range(t.size):
        e[:, i] = x[:, 0]
        x = x @ phi.T + gen.standard_normal((n, 2)) @ lq.T
    for spacing in (60.0, 15.0):
        kt = uniform_knots(0.0, 900.0, spacing)
        b = spline_design(kt, t)
        k = np.linalg.solve(b.T @ b, b.T @ e.T).T
        resid = np.mean((e - k @ b.T) ** 2, axis=1)
        se = resid.std(ddof=1) / np.sqrt(n)
        want = unresolved_process_sigma(kt, 1.0, lam, zeta) ** 2
        assert abs(want - resid.mean()) < 4 * se, (spacing, want, resid.mean(), se)
    assert unresolved_process_sigma(uniform_knots(0.0, 900.0, 60.0), 1.0, lam, zeta) > 0.4
    assert unresolved_process_sigma(uniform_knots(0.0, 900.0, 60.0), 1.0, ATTITUDE_RATE_FACTOR, zeta) < 0.03
    with pytest.raises(InputError, match="lam"):
        unresolved_process_sigma(kt, 1.0, 0.0, zeta)


def test_ephemeris_prior_is_the_covariance_of_the_segments_fit_to_the_simulators_draws():
    """The joint ephemeris prior against 3000 of the simulator's own independent-truth ephemeris
    errors (``draw_ephemeris_error``: an offset, a drift and a once-per-revolution term, tabulated
    on 60 s segments) over a 45-minute pass, each fitted by least squares with the estimator's one
    and two eq. 19 segments: every entry of the covariance (in correlation units) within 4.5
    standard errors of the draws' own scatter; the offset and drift made small, so that the
    once-per-revolution term carries it (a factor 2 in its variance fails). Without the term and
    with one segment it is the plain eq. 19 prior."""
    from misrgraph.sim.simulate import ScenarioConfig, draw_ephemeris_error

    t0, t1, amp = 1000.0, 3700.0, 30.0
    cfg = ScenarioConfig(
        truth="independent", once_per_rev_m=amp, nav_sigma_m=5.0, along_drift_sigma_mps=0.002, drift_sigma_mps=0.001
    )
    gen = np.random.default_rng(11)
    t = np.arange(t0, t1 + 1e-9, 5.0)
    curves = np.array([draw_ephemeris_error(gen, cfg, t0, t1).evaluate(t) for _ in range(3000)])  # (draws, T, 3)
    for n_seg in (1, 2):
        edges = np.linspace(t0, t1, n_seg + 1)
        params = []
        for s in range(n_seg):
            m = (t >= edges[s]) & (t <= edges[s + 1])
            design = np.stack([t[m] - edges[s], np.ones(m.sum())], 1)
            coef = np.linalg.lstsq(design, curves[:, m].transpose(1, 0, 2).reshape(m.sum(), -1), rcond=None)[0]
            params.append(coef.reshape(2, len(curves), 3).transpose(1, 0, 2).reshape(len(curves), 6))  # a_xyz, b_xyz
        x = np.concatenate(params, axis=1)
        cov = ephemeris_prior_covariance(edges, [0.002, 0.001, 0.001], 5.0, amp)
        d = np.sqrt(np.diag(cov))
        prod = (x[:, :, None] * x[:, None, :]) / np.outer(d, d)
        se = prod.std(axis=0, ddof=1) / np.sqrt(len(x))
        err = np.abs(prod.mean(axis=0) - cov / np.outer(d, d))
        assert np.all(err < 4.5 * se + 1e-12), (n_seg, np.max(err / (se + 1e-12)))
        wrong = ephemeris_prior_covariance(edges, [0.002, 0.001, 0.001], 5.0, amp * np.sqrt(2))
        assert np.any(np.abs(prod.mean(axis=0) - wrong / np.outer(d, d)) > 4.5 * se)
    np.testing.assert_allclose(
        ephemeris_prior_covariance([t0, t1], [0.05, 0.01, 0.01], 50.0, 0.0),
        np.diag([0.05**2, 0.01**2, 0.01**2, 2500.0, 2500.0, 2500.0]),
        atol=1e-9,
    )
    with pytest.raises(InputError, match="ephemeris_segments"):
        ephemeris_prior_covariance(np.linspace(t0, t1, 4), [0.05, 0.01, 0.01], 50.0, amp)
    with pytest.raises(InputError, match="ephemeris_once_per_rev_m"):
        ephemeris_prior_covariance([t0, t1], [0.05, 0.01, 0.01], 50.0, -1.0)
