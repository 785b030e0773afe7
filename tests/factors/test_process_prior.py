"""The attitude process prior between knots: its transition against the Matern-3/2 covariance
function in closed form (damping 1) and, for any damping, against the stochastic differential
equation's own covariance (Van Loan's matrix exponential); the knots' joint distribution through
GTSAM's own marginals; the default damping against its derivation from the error spectrum."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from scipy.linalg import expm

from factors.geometry import hermite_weights
from factors.priors import linear_factor, process_covariance, process_prior_factors, process_transition

LAM, SIG = 0.0146, 3e-5


def _kernel(tau: float) -> tuple[float, float, float]:
    """C(tau), C'(tau), C''(tau) of sigma^2 (1 + lam tau) exp(-lam tau), tau >= 0, by hand."""
    e = np.exp(-LAM * tau)
    return (SIG**2 * (1 + LAM * tau) * e, -(SIG**2) * LAM**2 * tau * e, -(SIG**2) * LAM**2 * (1 - LAM * tau) * e)


def _chain_marginals(keys: list[int], times: np.ndarray, zeta: float) -> gtsam.Marginals:
    """GTSAM's marginals of a graph holding only the process prior's chain on ``keys``."""
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    for k in keys:
        v.insert(k, np.zeros(2))
    for f in process_prior_factors(keys, times, SIG, LAM, zeta):
        g.add(f)
    return gtsam.Marginals(g, v)


@pytest.mark.parametrize("dt", [2.0, 60.0, 120.0, 1600.0])
def test_transition_is_the_matern_covariance(dt):
    phi, q = process_transition(dt, SIG, LAM)
    f = np.array([[0.0, 1.0], [-(LAM**2), -2 * LAM]])
    np.testing.assert_allclose(phi, expm(f * dt), rtol=1e-10, atol=1e-14)
    # cross-covariance E[x(t+dt) x(t)^T] = Phi P = [[C, -C'], [C', -C'']]
    c, c1, c2 = _kernel(dt)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    np.testing.assert_allclose(phi @ p, [[c, -c1], [c1, -c2]], rtol=1e-9, atol=1e-22)
    assert np.all(np.linalg.eigvalsh(q) > 0)


def test_chain_gives_every_knot_the_stationary_marginal():
    times = np.array([0.0, 60.0, 120.0, 500.0, 2100.0, 2160.0])
    keys = list(range(10, 10 + times.size))
    m = _chain_marginals(keys, times, 1.0)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    for k in keys:
        np.testing.assert_allclose(m.marginalCovariance(k), p, rtol=1e-7, atol=1e-20)
    c, c1, c2 = _kernel(times[3] - times[2])
    kv = gtsam.KeyVector([keys[2], keys[3]])
    joint = m.jointMarginalCovariance(kv).fullMatrix()
    np.testing.assert_allclose(joint[2:, :2], [[c, -c1], [c1, -c2]], rtol=1e-6, atol=1e-20)


def test_underdamped_chain_gives_the_process_covariance():
    """Damping 0.58: every knot's GTSAM marginal is the stationary P, and the cross-covariance of
    knots 1600 s apart is the process's, sigma^2 rho(1600) in the value (closed form,
    :func:`misrgraph.model.errormodels.process_correlation`)."""
    from misrgraph.model.errormodels import process_correlation

    times = np.array([0.0, 60.0, 120.0, 1720.0])
    keys = list(range(20, 24))
    m = _chain_marginals(keys, times, 0.58)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    for k in keys:
        np.testing.assert_allclose(m.marginalCovariance(k), p, rtol=1e-7, atol=1e-20)
    joint = m.jointMarginalCovariance(gtsam.KeyVector([keys[2], keys[3]])).fullMatrix()
    assert joint[2, 0] == pytest.approx(
        SIG**2 * float(process_correlation(1600.0, LAM, 0.58)), rel=1e-5, abs=1e-6 * SIG**2
    )


@pytest.mark.parametrize("zeta", [0.58, 1.0])
def test_process_covariance_is_the_chains_joint_marginal(zeta):
    """The covariance form of the process prior against GTSAM's joint marginal of the chain of
    factors on uneven knots (every pair, value and rate); at damping 1 its value block against the
    Matern-3/2 covariance function in closed form."""
    times = np.array([0.0, 60.0, 120.0, 500.0, 560.0, 2100.0])
    keys = list(range(40, 40 + times.size))
    joint = _chain_marginals(keys, times, zeta).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    cov = process_covariance(times, SIG, LAM, zeta)
    np.testing.assert_allclose(cov, joint, rtol=1e-6, atol=1e-9 * SIG**2)
    if zeta == 1.0:
        tau = np.abs(times[:, None] - times[None, :])
        np.testing.assert_allclose(cov[0::2, 0::2], SIG**2 * (1 + LAM * tau) * np.exp(-LAM * tau), rtol=1e-9)
    with pytest.raises(ValueError, match="increasing"):
        process_covariance(times[::-1], SIG, LAM, zeta)


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


@pytest.mark.parametrize("zeta", [0.2, 0.58, 1.0, 1.7])
@pytest.mark.parametrize("dt", [2.0, 60.0, 200.0])
def test_transition_is_the_sde_covariance(zeta, dt):
    """Phi = expm(F dt) and Q = int_0^dt e^{Fs} L q L^T e^{F^T s} ds, the latter by Van Loan's
    block exponential, with the white-noise intensity q = 4 zeta lam^3 sigma^2 that makes
    diag(sigma^2, (lam sigma)^2) stationary: an independent route to the same (Phi, Q); and the
    critically damped case matches the closed form. (Van Loan's block grows as exp(-F dt): past a
    few hundred seconds it loses the digits; the chain test below covers long spacings.)"""
    f = np.array([[0.0, 1.0], [-(LAM**2), -2 * zeta * LAM]])
    qc = np.array([[0.0, 0.0], [0.0, 4 * zeta * LAM**3 * SIG**2]])
    m = expm(np.block([[-f, qc], [np.zeros((2, 2)), f.T]]) * dt)
    phi_ref = m[2:, 2:].T
    q_ref = phi_ref @ m[:2, 2:]
    phi, q = process_transition(dt, SIG, LAM, zeta)
    np.testing.assert_allclose(phi, phi_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(q, q_ref, rtol=1e-6, atol=1e-9 * SIG**2 * LAM**2)
    assert np.all(np.linalg.eigvalsh(q) > 0)
    if zeta == 1.0:
        np.testing.assert_allclose(phi, expm(f * dt), rtol=1e-10, atol=1e-14)


def test_bad_transition_inputs_are_refused():
    with pytest.raises(ValueError, match="zeta"):
        process_transition(60.0, SIG, LAM, 0.0)


def test_default_damping_is_the_fit_to_the_attitude_spectrum():
    """ATTITUDE_DAMPING is the least-squares fit of the process correlation to that of periods
    log-uniform in 200-2000 s over 0-600 s; the band's correlation against a direct average of
    cosines over the periods (numerical), and the process correlation against the transition
    (rho(dt) = Phi[0, 0] + Phi[0, 1] C'(0) / C(0) = Phi[0, 0], the rate being uncorrelated with
    the value at equal times)."""
    from misrgraph.model.errormodels import (
        ATTITUDE_DAMPING,
        ATTITUDE_RATE_FACTOR,
        band_correlation,
        fit_damping,
        process_correlation,
    )

    tau = np.array([0.0, 30.0, 60.0, 120.0, 300.0, 600.0])
    periods = np.exp(np.linspace(np.log(200.0), np.log(2000.0), 20001))
    direct = np.mean(np.cos(2 * np.pi * tau[:, None] / periods[None, :]), axis=1)
    np.testing.assert_allclose(band_correlation(tau), direct, atol=2e-4)
    for z in (0.3, 1.0, 1.5):
        rho = [process_transition(t, 1.0, ATTITUDE_RATE_FACTOR, z)[0][0, 0] for t in tau[1:]]
        np.testing.assert_allclose(process_correlation(tau[1:], ATTITUDE_RATE_FACTOR, z), rho, rtol=1e-9, atol=1e-12)
    assert fit_damping(600.0) == ATTITUDE_DAMPING
    # the fit is better than the critically damped process by a wide margin
    t = np.arange(0.0, 601.0)
    err = {
        z: np.sum((process_correlation(t, ATTITUDE_RATE_FACTOR, z) - band_correlation(t)) ** 2)
        for z in (ATTITUDE_DAMPING, 1.0)
    }
    assert err[ATTITUDE_DAMPING] < 0.5 * err[1.0]


@pytest.mark.parametrize("zeta", [0.58, 1.0])
@pytest.mark.parametrize("dt, bound", [(60.0, 1.0001), (120.0, 1.003)])
def test_hermite_interpolation_stays_at_the_prior(dt, bound, zeta):
    """Between knots the spline of the process prior's knots has sigma <= bound x sigma (the
    interpolant is not the conditional mean: 0.3 % above at 120 s); an independent value and
    rate prior per knot gives ~4x over a 1600 s gap (what eqs. 28-29's knot removal produced)."""
    phi, _ = process_transition(dt, SIG, LAM, zeta)
    p = np.diag([SIG**2, (LAM * SIG) ** 2])
    s = np.block([[p, p @ phi.T], [phi @ p, p]])
    w = hermite_weights(np.linspace(0, 1, 201), dt)
    ratio = np.sqrt(np.einsum("ni,ij,nj->n", w, s, w).max()) / SIG
    assert 1.0 <= ratio <= bound
    w = hermite_weights(np.linspace(0, 1, 201), 1600.0)
    indep = np.sqrt(np.einsum("ni,ij,nj->n", w, np.kron(np.eye(2), p), w).max()) / SIG
    assert indep > 4.0
