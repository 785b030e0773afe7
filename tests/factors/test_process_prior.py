"""The attitude process prior between knots: its transition against the Matern-3/2 covariance
function in closed form, and the knots' joint distribution through GTSAM's own marginals."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.linalg import expm

from factors.geometry import hermite_weights
from factors.priors import linear_factor, matern32_transition, process_prior_factors

LAM, SIG = 0.0146, 3e-5


def _kernel(tau: float) -> tuple[float, float, float]:
    """C(tau), C'(tau), C''(tau) of sigma^2 (1 + lam tau) exp(-lam tau), tau >= 0, by hand."""
    e = np.exp(-LAM * tau)
    return (SIG**2 * (1 + LAM * tau) * e, -SIG**2 * LAM**2 * tau * e, -SIG**2 * LAM**2 * (1 - LAM * tau) * e)


@pytest.mark.parametrize("dt", [2.0, 60.0, 120.0, 1600.0])
def test_transition_is_the_matern_covariance(dt):
    phi, q = matern32_transition(dt, SIG, LAM)
    f = np.array([[0.0, 1.0], [-LAM**2, -2 * LAM]])
    np.testing.assert_allclose(phi, expm(f * dt), rtol=1e-10, atol=1e-14)
    # cross-covariance E[x(t+dt) x(t)^T] = Phi P = [[C, -C'], [C', -C'']]
    c, c1, c2 = _kernel(dt)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    np.testing.assert_allclose(phi @ p, [[c, -c1], [c1, -c2]], rtol=1e-9, atol=1e-22)
    assert np.all(np.linalg.eigvalsh(q) > 0)


def test_chain_gives_every_knot_the_stationary_marginal():
    times = np.array([0.0, 60.0, 120.0, 500.0, 2100.0, 2160.0])
    keys = list(range(10, 10 + times.size))
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    for k in keys:
        v.insert(k, np.zeros(2))
    for f in process_prior_factors(keys, times, SIG, LAM):
        g.add(f)
    m = gtsam.Marginals(g, v)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    for k in keys:
        np.testing.assert_allclose(m.marginalCovariance(k), p, rtol=1e-7, atol=1e-20)
    c, c1, c2 = _kernel(times[3] - times[2])
    kv = gtsam.KeyVector([keys[2], keys[3]])
    joint = m.jointMarginalCovariance(kv).fullMatrix()
    np.testing.assert_allclose(joint[2:, :2], [[c, -c1], [c1, -c2]], rtol=1e-6, atol=1e-20)


def test_linear_factor_error_is_its_mahalanobis_norm(rng):
    q = np.array([[4.0, 1.0], [1.0, 2.0]])
    a0, a1, b = rng.normal(size=(2, 2)), rng.normal(size=(2, 2)), rng.normal(size=2)
    f = linear_factor([1, 2], [a0, a1], b, q)
    x0, x1 = rng.normal(size=2), rng.normal(size=2)
    v = gtsam.Values()
    v.insert(1, x0)
    v.insert(2, x1)
    r = a0 @ x0 + a1 @ x1 - b
    assert f.error(v) == pytest.approx(0.5 * r @ np.linalg.solve(q, r), rel=1e-12)


@pytest.mark.parametrize("dt, bound", [(60.0, 1.0001), (120.0, 1.003)])
def test_hermite_interpolation_stays_at_the_prior(dt, bound):
    """Between knots the spline of the process prior's knots has sigma <= bound x sigma (the
    interpolant is not the conditional mean: 0.3 % above at 120 s); an independent value and
    rate prior per knot gives ~4x over a 1600 s gap (what eqs. 28-29's knot removal produced)."""
    phi, _ = matern32_transition(dt, SIG, LAM)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    s = np.block([[p, p @ phi.T], [phi @ p, p]])
    w = hermite_weights(np.linspace(0, 1, 201), dt)
    ratio = np.sqrt(np.einsum("ni,ij,nj->n", w, s, w).max()) / SIG
    assert 1.0 <= ratio <= bound
    w = hermite_weights(np.linspace(0, 1, 201), 1600.0)
    indep = np.sqrt(np.einsum("ni,ij,nj->n", w, np.kron(np.eye(2), p), w).max()) / SIG
    assert indep > 4.0
