"""The tie points' shared height error: the estimator from DEM residuals against draws from its
model, the covariance term against closed forms, and the adjustment of a pass whose tie points'
non-An rays were moved together along their epipolar directions by a height error the test draws
(the estimator never sees it) against the truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.estimate.adjust import AdjustConfig, adjust_pass
from misrgraph.estimate.tieheight import inflate_along, pool_shared_height, shared_height_variance
from misrgraph.io.passes import KIND_TIE
from misrgraph.model.constants import CAMERAS

AN = CAMERAS.index("An")


def _draws(rng: np.random.Generator, s2: float, n: int = 800, reps: int = 300):
    sig = rng.choice([30.0, 60.0], n)
    q = rng.uniform(0.85, 1.0, n)
    out = [
        shared_height_variance(np.sqrt(q * sig**2 + q**2 * s2) * rng.standard_normal(n), sig, q) for _ in range(reps)
    ]
    return (
        np.array([e.unclipped_m2 for e in out]),
        np.array([e.variance_m2 for e in out]),
        np.array([e.standard_error_m2 for e in out]),
    )


@pytest.mark.parametrize("s2", [0.0, 150.0, 900.0])
def test_the_estimate_is_unbiased_and_its_standard_error_is_its_scatter(s2):
    """r_i drawn from the model, E[r^2] = q sigma^2 + q^2 s^2: over 300 draws the unclipped
    estimate's mean is within 3.5 standard errors of the mean of ``s^2``, and the stated standard
    error is the draws' scatter within 15 % (the scatter's own sampling error is 4 %). The clipped
    value is never negative and equals the unclipped one where that is positive."""
    est, clipped, se = _draws(np.random.default_rng(int(s2) + 5), s2)
    assert abs(est.mean() - s2) < 3.5 * est.std() / np.sqrt(est.size), (est.mean(), s2)
    assert np.std(est) == pytest.approx(np.median(se), rel=0.15)
    assert clipped.min() >= 0 and np.allclose(clipped[est > 0], est[est > 0])


def test_pooling_short_passes_is_unbiased_and_states_its_scatter():
    """20 short passes (60-90 DEM rows each, s^2 = 300 m^2): each pass's estimate has a standard
    error near the variance itself (draws from the model, as above). Over 200 repetitions the
    pooled (row-weighted) mean of the unclipped estimates is unbiased within 3.5 standard errors,
    its stated standard error (from the passes' scatter) is the repetitions' scatter within 15 %,
    and it is several times smaller than one pass's."""
    rng = np.random.default_rng(12)
    s2, pooled, stated, one_se = 300.0, [], [], []
    for _ in range(200):
        ests = []
        for n in rng.integers(60, 91, 20):
            sig = rng.choice([30.0, 60.0], n)
            q = rng.uniform(0.85, 1.0, n)
            ests.append(shared_height_variance(np.sqrt(q * sig**2 + q**2 * s2) * rng.standard_normal(n), sig, q))
        p = pool_shared_height([e.unclipped_m2 for e in ests], [e.n for e in ests])
        pooled.append(p.unclipped_m2)
        stated.append(p.standard_error_m2)
        one_se.append(np.std([e.unclipped_m2 for e in ests]))
    pooled = np.array(pooled)
    assert abs(pooled.mean() - s2) < 3.5 * pooled.std() / np.sqrt(pooled.size), pooled.mean()
    assert np.std(pooled) == pytest.approx(np.sqrt(np.mean(np.square(stated))), rel=0.15)
    assert np.median(one_se) > 3.0 * np.std(pooled)


def test_pooling_equal_counts_is_the_plain_mean():
    """Equal row counts: the pooled value is the plain mean and its standard error the sample
    standard deviation over sqrt(P) (closed form); a negative mean is clipped to 0."""
    u = np.array([100.0, 400.0, -50.0, 250.0])
    p = pool_shared_height(u, np.full(4, 70))
    assert p.unclipped_m2 == pytest.approx(u.mean())
    assert p.standard_error_m2 == pytest.approx(u.std(ddof=1) / 2.0)
    assert p.n == 280
    assert pool_shared_height([-10.0, -30.0], [50, 50]).variance_m2 == 0.0
    for args, field in (
        (([1.0], [5]), "unclipped_m2"),
        (([1.0, 2.0], [5]), "n"),
        (([1.0, np.nan], [5, 5]), "unclipped_m2"),
        (([1.0, 2.0], [5, 0]), "n"),
    ):
        with pytest.raises(InputError, match=field):
            pool_shared_height(*args)


def test_bad_input_names_the_field():
    r = np.ones(5)
    with pytest.raises(InputError, match="sigma_m"):
        shared_height_variance(r, np.ones(4), np.ones(5))
    with pytest.raises(InputError, match="sigma_m"):
        shared_height_variance(r, np.zeros(5), np.ones(5))
    with pytest.raises(InputError, match="redundancy"):
        shared_height_variance(r, np.ones(5), np.full(5, 1.5))
    with pytest.raises(InputError, match="residual_m"):
        shared_height_variance(np.full(5, np.nan), np.ones(5), np.ones(5))
    assert shared_height_variance([1.0], [1.0], [1.0]).variance_m2 == 0.0  # one row estimates nothing
    with pytest.raises(InputError, match="direction"):
        inflate_along(np.zeros((2, 3, 3)), np.zeros((2, 3)), 1.0)
    with pytest.raises(InputError, match="variance_m2"):
        inflate_along(np.zeros((1, 3, 3)), np.ones((1, 3)), -1.0)
    for bad in ("maybe", -1.0, True, float("inf")):
        with pytest.raises(InputError, match="tie_height_sigma_m"):
            AdjustConfig.from_dict({"tie_height_sigma_m": bad})


def test_the_covariance_term_adds_the_variance_along_the_ray_only():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((4, 3, 3))
    cov = a @ a.transpose(0, 2, 1)
    u = rng.standard_normal((4, 3)) * 7.0
    out = inflate_along(cov, u, 25.0)
    un = u / np.linalg.norm(u, axis=1, keepdims=True)
    perp = np.cross(un, rng.standard_normal((4, 3)))
    np.testing.assert_allclose(np.einsum("ni,nij,nj->n", un, out - cov, un), 25.0)
    np.testing.assert_allclose(np.einsum("ni,nij->nj", perp, out - cov), 0.0, atol=1e-12)


def _with_shared_heights(p, truth, sigma_m: float, rng: np.random.Generator):
    """The pass with every tie point's non-An rays moved to where the true geometry sees its true
    point raised by ``dh ~ N(0, sigma_m^2)`` along An's true ray (each ray keeps its own noise);
    returns the pass and ``{landmark row: (dh, unit vector up along An's ray)}``."""
    geo = truth.geometry(p)
    obs = p.observations
    line, sample = obs.line.copy(), obs.sample.copy()
    moved = {}
    tie_rows = np.flatnonzero(p.landmarks.kind == KIND_TIE)
    for row in tie_rows:
        mine = np.flatnonzero(obs.landmark == row)
        an = mine[obs.camera[mine] == AN]
        others = mine[obs.camera[mine] != AN]
        if an.size == 0 or others.size == 0:
            continue
        _, d = geo.pixel_rays(
            obs.camera[an[:1]],
            obs.band[an[:1]],
            obs.line[an[:1]],
            obs.sample[an[:1]],
            exposure=obs.exposure_index[an[:1]],
        )
        u = -d[0] / np.linalg.norm(d[0])
        dh = float(rng.normal(0.0, sigma_m))
        x = truth.landmark_ecef[row]
        at = geo.ground_to_pixel(
            obs.camera[others], obs.band[others], np.repeat(x[None], others.size, 0), continuous=True
        )
        up = geo.ground_to_pixel(
            obs.camera[others], obs.band[others], np.repeat((x + dh * u)[None], others.size, 0), continuous=True
        )
        ok = np.isfinite(at.line) & np.isfinite(up.line)
        line[others[ok]] += up.line[ok] - at.line[ok]
        sample[others[ok]] += up.sample[ok] - at.sample[ok]
        moved[int(row)] = (dh, u)
    q = dataclasses.replace(p, observations=dataclasses.replace(obs, line=line, sample=sample))
    return q, moved


def test_a_shared_height_error_is_estimated_and_makes_the_heights_honest(small_pass):
    """150 tie points whose rays share a 40 m height error each (drawn here): estimated from the
    DEM residuals within 3 standard errors of the drawn errors' mean square, and the landmarks'
    z^2 along An's ray against the truth, mean over the tie points, inside its chi-square band
    (1 dof each, 99.9 %, widened by the estimate's relative standard error); without the term
    it is far above the band."""
    from scipy import stats

    sc, p = small_pass
    truth = sc.load_truth(0)
    q, moved = _with_shared_heights(p, truth, 40.0, np.random.default_rng(2))
    cfg = AdjustConfig.from_dict(
        attitude_jitter_arcsec=0.0
    )  # the model truth has no jitter; blunders: the default screen
    res = adjust_pass(q, sc.camera_model, sc.dem, sc.gcps, cfg.replace(tie_height_sigma_m="estimate"))
    th = res.tie_height
    assert th["source"] == "estimated" and th["tie_points"] > 0
    drawn = np.mean([dh**2 for dh, _ in moved.values()])
    assert abs(th["unclipped_variance_m2"] - drawn) < 3 * th["standard_error_m2"], (th, drawn)
    off = adjust_pass(q, sc.camera_model, sc.dem, sc.gcps, cfg.replace(tie_height_sigma_m=0.0))
    assert off.tie_height["source"] == "off" and not off.landmark_extra_cov

    def z2(r) -> float:
        pg = r.pass_graph
        out = []
        for k, row in zip(pg.landmark_keys, pg.landmark_rows):
            if int(row) in moved:
                _, u = moved[int(row)]
                e = (r.values.atVector(int(k)) - truth.landmark_ecef[row]) @ u
                out.append(e**2 / (u @ r.marginals[int(k)] @ u))
        return float(np.mean(out)), len(out)

    with_term, n = z2(res)
    without, _ = z2(off)
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], n) / n
    widen = th["standard_error_m2"] / th["variance_m2"]
    assert lo * (1 - widen) < with_term < hi * (1 + widen), (with_term, lo, hi, widen)
    assert without > 3 * hi, without
