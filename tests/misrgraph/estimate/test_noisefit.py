"""Noise levels learned from adjusted passes recover the levels a world was drawn with."""

from __future__ import annotations

import json

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.estimate.noisefit import (
    PassLevels,
    fit_noise_model,
    knot_prior_precision,
    log_marginal_likelihood,
    pooled_scale,
)
from misrgraph.model.constants import ARCSEC
from misrgraph.model.errormodels import ATTITUDE_DAMPING, ATTITUDE_RATE_FACTOR
from misrgraph.model.noise import NoiseModel


def _synthetic_pass(rng, sigma, lam, used_sigma, meas_arcsec=2.0, n=40, name="p", offset_m=50.0):
    """One pass whose knots (60 s apart) are drawn from the process with ``sigma`` (arcsec) and
    ``lam`` (1/s; one for every angle or one per angle) on every angle, measured in value with
    ``meas_arcsec`` noise, and estimated with the process prior of ``used_sigma`` (the exact
    linear-Gaussian posterior)."""
    t = 60.0 * np.arange(n)
    knots, covs = [], []
    for lam_a in np.broadcast_to(np.asarray(lam, float), (3,)):
        prior_true = knot_prior_precision(t, sigma, float(lam_a), ATTITUDE_DAMPING)
        x = np.linalg.cholesky(np.linalg.inv(prior_true)) @ rng.standard_normal(2 * n)
        data = np.zeros((2 * n, 2 * n))
        data[::2, ::2] = np.eye(n) / meas_arcsec**2
        y = x[::2] + meas_arcsec * rng.standard_normal(n)
        vec = np.zeros(2 * n)
        vec[::2] = y / meas_arcsec**2
        post = np.linalg.inv(data + knot_prior_precision(t, used_sigma, ATTITUDE_RATE_FACTOR, ATTITUDE_DAMPING))
        knots.append((post @ vec).reshape(n, 2) * ARCSEC)
        covs.append(post * ARCSEC**2)
    eph = np.zeros((1, 6))
    eph[0, 3:] = rng.normal(0.0, offset_m, 3)
    eph[0, :3] = rng.normal(0.0, [0.05, 0.01, 0.01])
    return PassLevels(
        name=name,
        knot_times=[t] * 3,
        knots=knots,
        knot_cov=covs,
        ephemeris_boundaries=np.array([0.0, 60.0 * n]),
        ephemeris=eph,
        ephemeris_cov=np.eye(6)[None] * 1e-8,
        classes={"tie-point An": {"kind": "tie", "factor": 1.5, "redundancy": 800.0}},
        used={"tie_sigma_scale": 2.0, "attitude_sigma_arcsec": (used_sigma,) * 3},
    )


def test_marginal_likelihood_is_the_gaussian_density_of_the_data():
    """Eq. (1) against the density of y = x + e with x ~ N(0, L^-1), e ~ N(0, R): the difference
    of the two log densities between two priors is the same."""
    rng = np.random.default_rng(0)
    t = 60.0 * np.arange(6)
    r = 4.0
    y = rng.normal(0.0, 10.0, 6)
    d_info = np.zeros((12, 12))
    d_info[::2, ::2] = np.eye(6) / r
    d_vec = np.zeros(12)
    d_vec[::2] = y / r

    def direct(sig):
        c = np.linalg.inv(knot_prior_precision(t, sig, 0.01, 0.6))[::2, ::2] + r * np.eye(6)
        return -0.5 * (np.linalg.slogdet(c)[1] + y @ np.linalg.solve(c, y))

    def eq1(sig):
        return log_marginal_likelihood(d_info, d_vec, knot_prior_precision(t, sig, 0.01, 0.6))

    assert eq1(20.0) - eq1(5.0) == pytest.approx(direct(20.0) - direct(5.0), rel=1e-9)
    # the relative form (what the fit maximises) is eq. (1) less its value at the prior used
    from misrgraph.estimate.noisefit import relative_log_marginal_likelihood

    prior0 = knot_prior_precision(t, 5.0, 0.01, 0.6)
    x0 = np.linalg.solve(d_info + prior0, d_vec)
    rel = relative_log_marginal_likelihood(d_info, d_vec, x0, prior0, knot_prior_precision(t, 20.0, 0.01, 0.6))
    assert rel == pytest.approx(eq1(20.0) - eq1(5.0), rel=1e-9)


def test_attitude_level_is_recovered_from_a_prior_half_as_wide():
    """Knots drawn with 30 arcsec, adjusted with a 15 arcsec prior, fitted from 3 passes, 90 times
    (30 repetitions x 3 angles): the estimates centre on 30 (their mean within 5 %), and their
    reported 1 sigma is honest: the standardised errors have a mean within +-0.5 and a spread
    from 0.8 to 1.25, and +-1 sigma covers the truth between 55 and 80 % of the time."""
    rng = np.random.default_rng(1)
    z, values = [], []
    for rep in range(30):
        passes = [_synthetic_pass(rng, 30.0, ATTITUDE_RATE_FACTOR, 15.0, name=f"{rep}.{i}") for i in range(3)]
        fit = fit_noise_model(passes)
        for ang in ("roll", "pitch", "yaw"):
            lv = fit.levels[f"attitude.value_sigma_arcsec.{ang}"]
            assert lv["sigma"] is not None and lv["passes"] == 3 and lv["previous"] == 15.0
            z.append((lv["value"] - 30.0) / lv["sigma"])
            values.append(lv["value"])
    z = np.array(z)
    assert abs(np.mean(values) / 30.0 - 1.0) < 0.05, np.mean(values)
    assert abs(z.mean()) < 0.5 and 0.8 < z.std() < 1.25, (z.mean(), z.std())
    assert 0.55 <= np.mean(np.abs(z) < 1.0) <= 0.8, np.mean(np.abs(z) < 1.0)


def test_observation_scale_multiplies_the_level_used():
    """A class adjusted with its sigma scaled by 2 whose sigma0 came out at 1.5 learns 3."""
    rng = np.random.default_rng(3)
    fit = fit_noise_model([_synthetic_pass(rng, 10.0, ATTITUDE_RATE_FACTOR, 10.0)])
    lv = fit.levels["observations.tie_sigma_scale"]
    assert lv["value"] == pytest.approx(3.0) and lv["sigma"] == pytest.approx(3.0 / np.sqrt(1600.0))
    assert fit.model.observations.tie_sigma_scale == pytest.approx(3.0)
    assert "observations" in fit.learned_sections and "jitter" not in fit.learned_sections


def test_gcp_positions_scale_pools_the_passes_prior_components():
    """Two passes' GCP-position variance components (sigma0 2.2 over redundancy 10, 1.8 over 30,
    adjusted with the catalogue's sigma as stated) give the scale of eq. (2): the square root of
    the passes' mean sigma0^2, with the standard error of their scatter or of the redundancy,
    whichever is larger; the fitted model carries it, the other scales untouched."""
    rng = np.random.default_rng(4)
    passes = []
    for s0, r in ((2.2, 10.0), (1.8, 30.0)):
        p = _synthetic_pass(rng, 10.0, ATTITUDE_RATE_FACTOR, 10.0)
        p.classes = {"GCP positions": {"kind": "gcp_position", "factor": s0, "redundancy": r}}
        p.used = {**p.used, "gcp_sigma_scale": 1.0}
        passes.append(p)
    fit = fit_noise_model(passes)
    lv = fit.levels["observations.gcp_sigma_scale"]
    k = np.sqrt((2.2**2 + 1.8**2) / 2)
    se = np.sqrt(np.var([2.2**2, 1.8**2], ddof=1) / 2) / (2 * k)
    assert lv["value"] == pytest.approx(k) and lv["sigma"] == pytest.approx(
        max(se, np.sqrt((2.2**2 * 10 + 1.8**2 * 30) / 40) / np.sqrt(80))
    )
    assert fit.model.observations.gcp_sigma_scale == pytest.approx(k)
    assert fit.model.observations.tie_sigma_scale == 1.0


def test_helpers_and_errors():
    k, s = pooled_scale([1.0, 2.0], [100.0, 300.0])
    assert k == pytest.approx(np.sqrt((100 + 1200) / 400)) and s == pytest.approx(k / np.sqrt(800))
    with pytest.raises(InputError, match="RESULTS"):
        fit_noise_model([])
    t = np.array([0.0, 60.0, 120.0])
    ind = knot_prior_precision(t, 2.0, 0.1, 0.6, "independent")
    np.testing.assert_allclose(np.diag(ind), [0.25, 25.0] * 3)
    # the process's marginal is stationary: every knot's prior variance is sigma^2, (lam sigma)^2
    cov = np.linalg.inv(knot_prior_precision(t, 2.0, 0.1, 0.6))
    np.testing.assert_allclose(np.diag(cov), [4.0, 0.04] * 3, rtol=1e-9)


@pytest.fixture(scope="module")
def world_results(tmp_path_factory):
    """Three short passes of a world whose attitude error is twice the pre-flight sigma and whose
    tie file understates its sigma by half (model truth: the knots are drawn from the process
    with the world's sigma), each adjusted with the pre-flight levels and written out."""
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    d = tmp_path_factory.mktemp("noisefit")
    truth_sigma = tuple(2.0 * s for s in NoiseModel().attitude.value_sigma_arcsec)
    from misrgraph.estimate.adjust import AdjustConfig

    adjust_cfg = AdjustConfig.from_dict(attitude_jitter_arcsec=0.0)  # the model truth has no jitter
    out = []
    for i in range(3):
        cfg = ScenarioConfig(
            truth="model",
            scenario="pass",
            seed=4242 + i,
            n_tie_points=150,
            n_check_points=10,
            n_gcps=20,
            duration_s=1200.0,
            start_lat_deg=55.0,
            attitude_sigma_arcsec=truth_sigma,
            tie_sigma_true_over_stated=2.0,
        )
        run_simulate(cfg, d / f"world{i}")
        r = d / f"result{i}.h5"
        run_adjust(d / f"world{i}", out=r, cfg=adjust_cfg)
        out.append(r)
    return out, truth_sigma


def test_noise_fit_learns_a_world_it_was_not_adjusted_for(world_results, tmp_path):
    """From three passes adjusted with the pre-flight levels: the tie scale is learned within 10 %
    of the true 2, each attitude sigma within 3 of its own standard errors of the truth (twice
    the pre-flight) and nearer to it than the pre-flight; the file it writes adjusts a pass."""
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.io.noise import read_noise_model

    results, truth_sigma = world_results
    out = tmp_path / "noise.json"
    r = CliRunner().invoke(app, ["noise", "fit", *map(str, results), "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    assert res["passes"] == 3
    tie = res["levels"]["observations.tie_sigma_scale"]
    assert tie["value"] == pytest.approx(2.0, rel=0.10), tie
    pre = NoiseModel().attitude.value_sigma_arcsec
    for a, ang in enumerate(("roll", "pitch", "yaw")):
        lv = res["levels"][f"attitude.value_sigma_arcsec.{ang}"]
        assert abs(lv["value"] - truth_sigma[a]) < 3 * lv["sigma"], (ang, lv)
        assert abs(lv["value"] - truth_sigma[a]) < abs(pre[a] - truth_sigma[a]), (ang, lv)
    model, source = read_noise_model(out)
    assert source["observations"] == "learned" and source["jitter"] == "pre-flight"
    assert model.observations.tie_sigma_scale == pytest.approx(tie["value"])
    assert "jitter.sigma_arcsec" in res["not_fitted"]
    assert json.loads(out.read_text())["fit"]["levels"]["observations.tie_sigma_scale"]["value"] == tie["value"]


def test_a_level_the_passes_do_not_determine_keeps_the_base():
    """One pass holds one ephemeris segment: one drift per axis cannot say how wide the drift's
    prior is (its log's sd from the curvature is above MAX_LOG_SD), so the model keeps the base's
    drift and says so; the offset, pooled over three axes, is determined. Drawn with the base's
    50 m it keeps the base's (the passes do not reject it: |z| <= LEVEL_Z); drawn with 500 m it
    is learned."""
    from misrgraph.estimate.noisefit import LEVEL_Z, MAX_LOG_SD

    rng = np.random.default_rng(5)
    fit = fit_noise_model([_synthetic_pass(rng, 10.0, ATTITUDE_RATE_FACTOR, 10.0)])
    base = NoiseModel()
    for axis in ("along", "cross", "radial"):
        lv = fit.levels[f"ephemeris.drift_sigma_mps.{axis}"]
        assert lv["applied"] is False, lv
        assert lv["sigma"] is None or lv["sigma"] / lv["value"] > MAX_LOG_SD * 0.9
    assert fit.model.ephemeris.drift_sigma_mps == base.ephemeris.drift_sigma_mps
    off = fit.levels["ephemeris.offset_sigma_m"]
    assert off["sigma"] is not None and off["sigma"] / off["value"] < MAX_LOG_SD
    assert abs(off["z"]) <= LEVEL_Z and not off["applied"] and off["reason"] == "agrees with the base", off
    assert fit.model.ephemeris.offset_sigma_m == base.ephemeris.offset_sigma_m
    wide = fit_noise_model([_synthetic_pass(rng, 10.0, ATTITUDE_RATE_FACTOR, 10.0, offset_m=500.0)])
    off = wide.levels["ephemeris.offset_sigma_m"]
    assert off["applied"] and off["z"] > LEVEL_Z and wide.model.ephemeris.offset_sigma_m == pytest.approx(off["value"])


def test_a_level_driven_to_its_bound_is_not_applied():
    """Knots that are all zero, exactly measured, drive the attitude sigma to the optimiser's lower
    bound: that is no determination of the level (it would pin the knots), so the model keeps the
    base's sigma."""
    rng = np.random.default_rng(6)
    p = _synthetic_pass(rng, 10.0, ATTITUDE_RATE_FACTOR, 10.0, meas_arcsec=0.01)
    p.knots = [np.zeros_like(k) for k in p.knots]
    fit = fit_noise_model([p])
    lv = fit.levels["attitude.value_sigma_arcsec.roll"]
    assert lv["value"] < 0.1 and lv["applied"] is False and lv["sigma"] is None, lv
    assert fit.model.attitude.value_sigma_arcsec == NoiseModel().attitude.value_sigma_arcsec


def test_the_attitude_shape_is_learned_only_where_the_passes_reject_the_base():
    """Passes whose process is three times faster than the pre-flight one: by default the fitted
    rate enters the model (its z against the base's above SHAPE_Z) and the knots get denser, to
    the spacing on which the spline misses no more of the learned process than of the jitter
    (checked here against :func:`unresolved_process_sigma` directly). With
    ``learn_attitude_shape=False`` the learned value sigma keeps the base's rate/value ratio and
    the 60 s knots. Passes drawn with the pre-flight shape, or a slower one, keep the base's shape
    by default; ``True`` applies whatever was fitted."""
    from misrgraph.estimate.noisefit import SHAPE_Z, spacing_tolerance
    from misrgraph.model.errormodels import unresolved_process_sigma

    rng = np.random.default_rng(7)
    fast = [_synthetic_pass(rng, 20.0, 3 * ATTITUDE_RATE_FACTOR, 20.0, name=str(i)) for i in range(3)]
    base = NoiseModel()
    fit = fit_noise_model(fast)
    tol = spacing_tolerance(base)
    for a, ang in enumerate(("roll", "pitch", "yaw")):
        lv = fit.levels[f"attitude.rate_sigma_arcsec_per_s.{ang}"]
        value = fit.model.attitude.value_sigma_arcsec[a]
        assert lv["applied"] is True and lv["shape_z"] > SHAPE_Z, lv
        lam = fit.model.attitude.rate_sigma_arcsec_per_s[a] / value
        assert lam == pytest.approx(lv["value"] / fit.levels[f"attitude.value_sigma_arcsec.{ang}"]["value"])
        assert 2 * ATTITUDE_RATE_FACTOR < lam < 4.5 * ATTITUDE_RATE_FACTOR, lam
        h = fit.model.attitude.knot_spacing_s[a]
        assert h < 60.0 and fit.levels[f"attitude.knot_spacing_s.{ang}"]["value"] == h

        def missed(spacing, value=value, lam=lam):
            return unresolved_process_sigma(np.arange(0.0, 1200.5, spacing), value, lam, ATTITUDE_DAMPING)

        assert missed(h) <= tol * 1.01 and missed(60.0) > tol, (h, missed(h), missed(60.0), tol)
    kept = fit_noise_model(fast, base, learn_attitude_shape=False)
    v, r = kept.model.attitude.value_sigma_arcsec, kept.model.attitude.rate_sigma_arcsec_per_s
    np.testing.assert_allclose(np.array(r) / np.array(v), ATTITUDE_RATE_FACTOR, rtol=1e-12)
    assert kept.model.attitude.knot_spacing_s == base.attitude.knot_spacing_s
    assert kept.levels["attitude.rate_sigma_arcsec_per_s.pitch"]["applied"] is False
    for lam_true in (ATTITUDE_RATE_FACTOR, ATTITUDE_RATE_FACTOR / 3):
        same = [_synthetic_pass(rng, 20.0, lam_true, 20.0, name=str(i)) for i in range(3)]
        fit = fit_noise_model(same)
        np.testing.assert_allclose(
            np.array(fit.model.attitude.rate_sigma_arcsec_per_s) / np.array(fit.model.attitude.value_sigma_arcsec),
            ATTITUDE_RATE_FACTOR,
            rtol=1e-12,
        )
        assert fit.model.attitude.knot_spacing_s == base.attitude.knot_spacing_s
        assert all(fit.levels[f"attitude.rate_sigma_arcsec_per_s.{a}"]["shape_z"] < SHAPE_Z for a in ("roll", "pitch"))
    shaped = fit_noise_model(same, base, learn_attitude_shape=True)
    lv = shaped.levels
    att = shaped.model.attitude
    assert att.rate_sigma_arcsec_per_s[1] / att.value_sigma_arcsec[1] == pytest.approx(
        lv["attitude.rate_sigma_arcsec_per_s.pitch"]["value"] / lv["attitude.value_sigma_arcsec.pitch"]["value"]
    )


def test_a_flat_level_does_not_hide_the_determined_ones():
    """The curvature covariance of a Gaussian log-likelihood in two levels (known covariance C)
    beside a third level it does not depend on: the two get C back, the flat one an infinite
    variance (a singular curvature must not leave all three undetermined)."""
    from misrgraph.estimate.noisefit import _maximise

    c = np.array([[0.04, 0.01], [0.01, 0.09]])
    info = np.linalg.inv(c)
    mu = np.array([1.0, -0.5])

    def objective(th):
        r = th[:2] - mu
        return -0.5 * r @ info @ r + 0.0 * th[2]

    th, cov = _maximise(objective, np.zeros(3), [(-5.0, 5.0)] * 3)
    np.testing.assert_allclose(th[:2], mu, atol=1e-4)
    np.testing.assert_allclose(cov[:2, :2], c, rtol=1e-3)
    assert np.isinf(cov[2, 2])


def test_the_shape_rule_tests_the_attitude_then_each_angle():
    """The default rule (closed-form cases): no angle's shape is applied unless some angle's z is
    above SHAPE_Z; then every angle whose z is above SHAPE_FOLLOW_Z gets its own. A forced rule
    applies every determined shape (True) or none (False)."""
    from misrgraph.estimate.noisefit import SHAPE_FOLLOW_Z, SHAPE_Z, _shape_applied

    between = 0.5 * (SHAPE_Z + SHAPE_FOLLOW_Z)
    assert _shape_applied([SHAPE_Z + 2, SHAPE_Z + 5, between], None, [True] * 3) == [True, True, True]
    assert _shape_applied([between, between, between], None, [True] * 3) == [False] * 3
    assert _shape_applied([SHAPE_Z + 1, SHAPE_FOLLOW_Z - 0.1, None], None, [True] * 3) == [True, False, False]
    assert _shape_applied([-SHAPE_Z - 5, 0.0, between], None, [True] * 3) == [False] * 3
    assert _shape_applied([0.0, None, 1.0], True, [True, False, True]) == [True, False, True]
    assert _shape_applied([SHAPE_Z + 5] * 3, False, [True] * 3) == [False] * 3


def test_a_moderately_faster_angle_follows_a_clearly_faster_one():
    """Roll's process five times faster than the pre-flight one (its z far above SHAPE_Z), yaw's
    1.6 times faster on few knots (a z between the two thresholds), pitch's the pre-flight one:
    the fit applies each angle's fitted shape exactly when its own z is above SHAPE_FOLLOW_Z, and
    the one whose shape is applied and faster gets denser knots."""
    from misrgraph.estimate.noisefit import SHAPE_FOLLOW_Z, SHAPE_Z

    rng = np.random.default_rng(11)
    lam = (5 * ATTITUDE_RATE_FACTOR, ATTITUDE_RATE_FACTOR, 1.6 * ATTITUDE_RATE_FACTOR)
    passes = [_synthetic_pass(rng, 20.0, lam, 20.0, n=20, name=str(i)) for i in range(2)]
    fit = fit_noise_model(passes)
    z = {a: fit.levels[f"attitude.rate_sigma_arcsec_per_s.{a}"]["shape_z"] for a in ("roll", "pitch", "yaw")}
    assert z["roll"] > SHAPE_Z, z
    for a, ang in enumerate(("roll", "pitch", "yaw")):
        lv = fit.levels[f"attitude.rate_sigma_arcsec_per_s.{ang}"]
        assert lv["applied"] is (z[ang] > SHAPE_FOLLOW_Z), (ang, z)
        ratio = fit.model.attitude.rate_sigma_arcsec_per_s[a] / fit.model.attitude.value_sigma_arcsec[a]
        if lv["applied"]:
            assert ratio == pytest.approx(lv["value"] / fit.levels[f"attitude.value_sigma_arcsec.{ang}"]["value"])
        else:
            assert ratio == pytest.approx(ATTITUDE_RATE_FACTOR)
    assert fit.model.attitude.knot_spacing_s[0] < 60.0


def test_class_scale_inverts_the_variance_component_of_a_partly_stated_sigma():
    """class_scale in closed form: a class whose weighted variance is a share F of a stated sigma at
    scale ``used`` and 1 - F of a part no scale touches reads ``factor^2 = F (k/used)^2 + 1 - F``
    when the truth's scale is ``k``; class_scale gives ``k`` back, and its amplification is the
    numerical derivative of log k over log factor. With F = 1 it is ``used * factor``."""
    from misrgraph.estimate.reliability import class_scale

    for share in (1.0, 0.96, 0.6):
        for k_true in (0.5, 2.0):
            for used in (1.0, 1.3):
                factor = np.sqrt(share * (k_true / used) ** 2 + 1.0 - share)
                k, amp = class_scale(used, factor, share)
                assert k == pytest.approx(k_true, rel=1e-12)
                h = 1e-6
                num = (
                    np.log(class_scale(used, factor * (1 + h), share)[0])
                    - np.log(class_scale(used, factor * (1 - h), share)[0])
                ) / (np.log(1 + h) - np.log(1 - h))
                assert amp == pytest.approx(num, rel=1e-5)
    assert class_scale(1.5, 0.8)[0] == pytest.approx(1.2)
    assert class_scale(1.0, 0.5, 0.6)[0] == pytest.approx(1e-3, rel=1e-9)  # no variance left for the stated share
