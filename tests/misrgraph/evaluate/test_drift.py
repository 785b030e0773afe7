"""The drift monitor: the filter's likelihood against the Gaussian density of the whole series
in closed form, the process levels learned back, a 0.1 px step found within one recalibration,
the false-alarm rate over series without change against the configured rate, and each camera's
series given the others in closed form and against a Monte Carlo of shared errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from misrgraph.errors import InputError
from misrgraph.evaluate.drift import (
    SEASON_DAYS,
    TrendLevels,
    conditional_series,
    cusum_threshold,
    fit_process_levels,
    kalman_filter,
    monitor_cameras,
    monitor_series,
)

#: A calibration every 30 days for five years, each with a 1-sigma of 0.02 px.
T = np.arange(60) * 30.0
SIGMA = np.full(T.size, 0.02)
#: The true process: a level wandering 0.005 px per sqrt(year), a slope wandering slowly.
TRUE = TrendLevels(q_level=0.005**2 / 365.25, q_slope=1e-6**2)


def _series(rng: np.random.Generator, levels: TrendLevels, step: float = 0.0, at: int = 40, season: float = 0.01):
    level, slope = 0.0, 1e-5
    out = np.zeros(T.size)
    for k in range(T.size):
        if k:
            dt = T[k] - T[k - 1]
            slope += rng.normal(0, math.sqrt(levels.q_slope * dt))
            level += slope * dt + rng.normal(0, math.sqrt(levels.q_level * dt))
        out[k] = level + (step if k >= at else 0.0) + season * math.cos(2 * math.pi * T[k] / SEASON_DAYS)
    return out + rng.normal(0, SIGMA)


def _integrated_cov(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    return lo**2 * hi / 2 - lo**3 / 6


def test_filter_likelihood_is_the_gaussian_density_of_the_series(rng) -> None:
    """With a proper prior (variance 10 on level and slope), the innovations' log-likelihood after
    the first two equals log N(y) - log N(y[:2]) from the joint covariance in closed form."""
    t = np.array([0.0, 20.0, 45.0, 50.0, 90.0, 130.0, 131.0])
    s = rng.uniform(0.5, 1.5, t.size)
    y = rng.normal(0, 2, t.size)
    lv = TrendLevels(q_level=0.02, q_slope=1e-4)
    p0 = 10.0
    res = kalman_filter(t, y, s, lv, seasonal=False, prior_variance=p0)
    dt = t - t[0]
    a, b = np.meshgrid(dt, dt, indexing="ij")
    cov = p0 * (1 + np.outer(dt, dt)) + lv.q_level * np.minimum(a, b) + lv.q_slope * _integrated_cov(a, b)
    cov += np.diag(s**2)
    want = multivariate_normal(np.zeros(t.size), cov).logpdf(y) - multivariate_normal(np.zeros(2), cov[:2, :2]).logpdf(
        y[:2]
    )
    assert res.log_likelihood == pytest.approx(want, rel=1e-9, abs=1e-9)


def test_start_spreads_are_learned_from_many_series(rng) -> None:
    """Series whose slopes and annual terms are drawn around zero with known spreads (a slope of
    5e-5 px/day, an annual coefficient of 0.01 px, each 1-sigma): the pooled fit gives both spreads
    back within a factor 3 (their variances), and a filter started with them predicts the series
    more tightly than one started diffuse, with standardised innovations of unit variance."""
    t = np.arange(20) * 90.0
    series = []
    for _ in range(40):
        slope = rng.normal(0, 5e-5)
        a, b = rng.normal(0, 0.01, 2)
        w = 2 * math.pi * t / SEASON_DAYS
        y = slope * t + a * np.cos(w) + b * np.sin(w) + rng.normal(0, 0.02, t.size)
        series.append((t, y, np.full(t.size, 0.02)))
    got = fit_process_levels(series)
    assert 2.5e-9 / 3 < got.slope_var < 7.5e-9, got
    assert 1e-4 / 3 < got.season_var < 3e-4, got
    diffuse = fit_process_levels(series, learn_start=False)
    assert not math.isfinite(diffuse.slope_var) and not math.isfinite(diffuse.season_var)
    # on the same data, the learned start's standardised innovations have unit variance, and its
    # prediction of the fifth calibration (the first the diffuse start predicts) is tighter
    p_learned = [kalman_filter(*s, got) for s in series]
    p_diffuse = [kalman_filter(*s, diffuse) for s in series]
    z2_learned = np.concatenate([r.z[4:] for r in p_learned]) ** 2
    assert abs(z2_learned.mean() - 1) < 0.1, z2_learned.mean()
    assert np.mean([r.S[4] for r in p_learned]) < np.mean([r.S[4] for r in p_diffuse])


def test_process_levels_are_learned_from_a_series(rng) -> None:
    """On a long series (20 years of monthly calibrations) the learned level intensity is within a
    factor 3 of the truth's."""
    t = np.arange(240) * 30.0
    truth = TrendLevels(q_level=0.01**2 / 30.0, q_slope=1e-12)
    level = np.cumsum(rng.normal(0, math.sqrt(truth.q_level * 30.0), t.size))
    y = level + rng.normal(0, 0.02, t.size)
    got = fit_process_levels([(t, y, np.full(t.size, 0.02))], seasonal=False)
    assert truth.q_level / 3 < got.q_level < 3 * truth.q_level, got


@pytest.fixture(scope="module")
def learned() -> TrendLevels:
    """The levels learned from training series of the world without change (27 other draws, as
    many as a campaign's cameras and parameters: the series the monitor pools its levels over)."""
    rng = np.random.default_rng(99)
    return fit_process_levels([(T, _series(rng, TRUE), SIGMA) for _ in range(27)])


def test_a_step_of_a_tenth_of_a_pixel_is_found_within_one_recalibration(learned) -> None:
    rng = np.random.default_rng(7)
    n, found, delays, onsets = 100, 0, [], []
    for _ in range(n):
        res, alarm = monitor_series(T, _series(rng, TRUE, step=0.1, at=40), SIGMA, learned, alpha=0.05)
        if alarm is not None and 40 <= alarm.index <= 41 and alarm.direction == 1:
            found += 1
            delays.append(alarm.index - 40)
            onsets.append((alarm.onset, alarm.index))
    # at least 90 % with the 95 % binomial interval's lower end above 80 %
    assert found / n >= 0.9, (found, delays)
    # the onset: the step's own calibration in most, never after the alarm
    assert np.mean([o == 40 for o, _ in onsets]) >= 0.8 and all(o <= i for o, i in onsets), onsets


def test_false_alarms_stay_within_the_configured_rate(learned) -> None:
    rng = np.random.default_rng(11)
    n = 300
    alarms = sum(monitor_series(T, _series(rng, TRUE), SIGMA, learned, alpha=0.05)[1] is not None for _ in range(n))
    rate = alarms / n
    # the configured 5 % within the run-to-run scatter (2 standard errors)
    assert rate <= 0.05 + 2 * math.sqrt(0.05 * 0.95 / n), rate


def test_threshold_and_inputs() -> None:
    assert cusum_threshold(50, 0.01) > cusum_threshold(50, 0.1) > cusum_threshold(5, 0.1)
    with pytest.raises(InputError, match="alpha"):
        cusum_threshold(10, 1.5)
    with pytest.raises(InputError, match="increasing"):
        kalman_filter([0.0, 0.0, 1.0], [1, 2, 3], [1, 1, 1], TRUE)
    with pytest.raises(InputError, match="sigma"):
        kalman_filter([0.0, 1.0], [1, 2], [1, 0], TRUE)


def test_a_camera_given_another_in_closed_form() -> None:
    """Two cameras with errors of 1-sigma 2 and 1 correlated at 0.8: camera a given b is
    ``y_a - 0.8 * 2 / 1 * y_b`` with 1-sigma ``2 sqrt(1 - 0.64)`` and gain ``1 + 1.6^2``."""
    t = np.arange(4) * 30.0
    ya, yb = np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.5, -1.0, 0.0, 2.0])
    cov = np.array([[4.0, 0.8 * 2.0], [0.8 * 2.0, 1.0]])
    series = {("a", "p"): (t, ya, np.full(4, 2.0)), ("b", "p"): (t, yb, np.full(4, 1.0))}
    got, gains = conditional_series(series, {"p": np.broadcast_to(cov, (4, 2, 2))}, ["a", "b"])
    assert got["a", "p"][1] == pytest.approx(ya - 1.6 * yb)
    assert got["a", "p"][2] == pytest.approx(np.full(4, 2.0 * math.sqrt(1 - 0.64)))
    assert got["b", "p"][1] == pytest.approx(yb - 0.4 * ya) and gains["a", "p"] == pytest.approx(1 + 1.6**2)
    with pytest.raises(InputError, match="positive definite"):
        conditional_series(series, {"p": np.broadcast_to(np.ones((2, 2)), (4, 2, 2))}, ["a", "b"])
    with pytest.raises(InputError, match="covariances"):
        conditional_series(series, {"p": np.broadcast_to(cov, (3, 2, 2))}, ["a", "b"])


def test_given_the_others_a_shared_error_is_taken_out(rng) -> None:
    """Nine cameras whose calibration errors share 90 % of their variance: the conditional series'
    errors have the 1-sigma it states (Monte Carlo, 4000 draws), a third of the cameras' own; a
    step of 2 sigma in one camera is found at once in the conditional view, naming that camera,
    in far more series than in the cameras' own (where the shared error hides it)."""
    cams = [f"c{i}" for i in range(9)]
    cov = 0.02**2 * (0.9 * np.ones((9, 9)) + 0.1 * np.eye(9))
    chol = np.linalg.cholesky(cov)
    n = 4000
    t = np.arange(n, dtype=float)
    err = (chol @ rng.standard_normal((9, n))).T
    series = {(c, "p"): (t, err[:, i], np.full(n, 0.02)) for i, c in enumerate(cams)}
    got, gains = conditional_series(series, {"p": np.broadcast_to(cov, (n, 9, 9))}, cams)
    for c in cams:
        sd = got[c, "p"][2][0]
        assert np.std(got[c, "p"][1]) == pytest.approx(sd, rel=0.05) and sd < 0.4 * 0.02
    found = {"conditional": 0, "marginal": 0}
    for _ in range(40):
        y = (chol @ rng.standard_normal((9, T.size))).T
        y[40:, 4] += 0.04
        own = {(c, "p"): (T, y[:, i], np.full(T.size, 0.02)) for i, c in enumerate(cams)}
        cond, g = conditional_series(own, {"p": np.broadcast_to(cov, (T.size, 9, 9))}, cams)
        for view, ser, gn in (("conditional", cond, g), ("marginal", own, None)):
            alarms = monitor_cameras(ser, TRUE, alpha=0.05, gains=gn)
            found[view] += bool(alarms) and alarms[0]["camera"] == "c4" and alarms[0]["index"] in (40, 41)
    assert found["conditional"] >= 36 and found["conditional"] >= found["marginal"] + 10, found
