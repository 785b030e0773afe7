"""Camera calibration: recovery of the injected misalignments, honest covariance, blunders, degeneracy."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import DegenerateProblemError, InputError
from misrgraph.estimate.calibrate import CalibrateConfig, calibrate_passes, summarise
from misrgraph.evaluate.calibration import score_calibration
from misrgraph.io.camera import read_camera_file
from misrgraph.io.passes import OrbitPass
from misrgraph.model.constants import CAMERAS
from misrgraph.runs.calibrate import run_calibrate
from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate


@pytest.fixture(scope="module")
def month(small_month_dir):
    sc = load_scenario(small_month_dir)
    return sc, [sc.load_pass(i) for i in range(len(sc.pass_files))]


@pytest.mark.slow
def test_standard_month_meets_the_eighth_pixel_requirement(tmp_path):
    """The standard month (120 GCPs, 30 days, 5 % GCP blunders): every camera within 1/8 pixel."""
    out = tmp_path / "month"
    run_simulate(ScenarioConfig(truth="model", scenario="month", seed=3), out)
    s = run_calibrate(out)
    assert s["max_pointing_error_px"] <= 0.125  # the seed's requirement
    for v in s["cameras"].values():
        assert v["pointing_error_px"] < 3 * v["sigma_px"]


def test_recovers_the_misalignments_within_their_sigma(small_month_dir, tmp_path):
    out = tmp_path / "cgm.h5"
    s = run_calibrate(small_month_dir, out=out)
    assert set(s["cameras"]) == set(CAMERAS)
    for cam, v in s["cameras"].items():
        assert v["pointing_error_px"] < 3 * v["sigma_px"], cam
        assert v["pointing_error_px"] < v["pointing_error_before_px"], cam
    # the written model is a camera model the adjustment can consume
    m = read_camera_file(out)
    assert m.provenance["source"] == "misrgraph calibrate"
    corr = np.asarray(s["correlation"]["matrix"])
    n = 9 * len(CalibrateConfig().params)  # 45: delta, beta, epsilon, alpha_2, alpha_3 per camera
    assert corr.shape == (n, n) and np.allclose(np.diag(corr), 1.0)


@pytest.mark.slow
def test_nees_inside_chi2_band_over_seeds(tmp_path):
    """Five reduced months: the aggregated NEES of the 45 camera corrections lies in the 95 % band
    (the model truth's alpha_2, alpha_3 drawn from the calibration's own prior)."""
    chi2, dof = 0.0, 0
    for seed in range(5):
        out = tmp_path / f"m{seed}"
        run_simulate(ScenarioConfig(truth="model", scenario="month", seed=200 + seed, n_gcps=24, month_days=16), out)
        s = run_calibrate(out)
        chi2 += s["nees"] * s["nees_dim"]
        dof += s["nees_dim"]
    lo, hi = stats.chi2.ppf([0.025, 0.975], dof)
    assert lo < chi2 < hi, (chi2 / dof, lo / dof, hi / dof)


def test_blunders_found_and_harmless(month):
    """Every rejection is an injected blunder, most blunders are found, and the result moves by less
    than its sigma against an oracle run that never saw the blunders."""
    sc, passes = month
    res = calibrate_passes(passes, sc.camera_model, sc.gcps, CalibrateConfig())
    truths = {p.pass_id: sc.load_truth(i) for i, p in enumerate(passes)}
    injected = sum(int(t.blunder.sum()) for t in truths.values())
    true_pos = sum(
        1 for pi, o, _ in res.rejected if res.graphs and truths[_pass_of(res, passes, pi).pass_id].blunder[o]
    )
    assert true_pos == len(res.rejected)
    assert len(res.rejected) >= 0.9 * injected
    clean = []
    for p in passes:
        keep = ~truths[p.pass_id].blunder
        clean.append(
            OrbitPass(
                p.pass_id,
                p.path,
                p.orbit,
                p.ephemeris,
                p.attitude,
                p.t0,
                p.line_time,
                p.landmarks,
                p.observations.subset(keep),
                p.temperature_c,
            )
        )
    oracle = calibrate_passes(clean, sc.camera_model, sc.gcps, CalibrateConfig(robust="none"))
    sig = np.sqrt(np.diag(oracle.covariance))
    assert np.all(np.abs(res.values - oracle.values) < sig)


def _pass_of(res, passes, pi):
    with_gcp = [p for p in passes if np.any(p.landmarks.kind == 1)]
    return with_gcp[pi]


def test_undeterminable_parameters_are_reported(month):
    sc, passes = month
    cfg = CalibrateConfig(params=("delta", "beta", "epsilon", "alpha2", "alpha3", "alpha4", "alpha5"))
    res = calibrate_passes(passes[:4], sc.camera_model, sc.gcps, cfg)
    s = summarise(res, cfg, sc.camera_model)
    flagged = {p["parameter"] for p in s["poorly_determined"]}
    assert any(".alpha5" in f for f in flagged)
    # T_ic = Ry(beta) Rx(delta): at An (beta = 0) delta is a roll about the line axis (a cross-track
    # shift) and epsilon a rotation about the boresight, so GCPs across the swath separate them.
    # (Under the retired Rz(delta) Ry(beta) they were one rotation about nadir and An.delta was flagged.)
    assert "An.delta" not in flagged and "An.epsilon" not in flagged


def test_a_measured_focal_plane_prior_holds_f_and_alpha(month, nominal_camera):
    """``focal_prior_px``: f and alpha_i get the prior of a focal plane known to that many pixels
    at the swath edge -- by hand, d alpha_i = px |alpha_1| / 752^i and df = f px / 752 -- while the
    angles keep the wide pre-flight 0.1 deg; 0 keeps every parameter's wide prior. The month's
    result reports those priors, and with 4 passes the alpha_3 corrections stay inside 3 prior
    sigma (the truth has no alpha error). A negative value is refused by name."""
    from misrgraph.estimate.graph import CAMERA_PRIOR_SIGMA, calibration_prior_sigma

    params = ("delta", "beta", "epsilon", "f", "alpha2", "alpha3")
    c = 4
    a1, f = abs(nominal_camera.alpha[c, 2, 1]), nominal_camera.focal_length[c, 2]
    np.testing.assert_allclose(
        calibration_prior_sigma(nominal_camera, c, params, 0.05),
        [1.745e-3] * 3 + [f * 0.05 / 752, 0.05 * a1 / 752**2, 0.05 * a1 / 752**3],
        rtol=1e-12,
    )
    np.testing.assert_array_equal(
        calibration_prior_sigma(nominal_camera, c, params, 0.0), [CAMERA_PRIOR_SIGMA[p] for p in params]
    )
    sc, passes = month
    narrow = calibrate_passes(passes[:4], sc.camera_model, sc.gcps, CalibrateConfig(params=params, focal_prior_px=0.05))
    expect = np.concatenate([calibration_prior_sigma(sc.camera_model, k, params, 0.05) for k in range(len(CAMERAS))])
    np.testing.assert_allclose(narrow.prior_sigma, expect, rtol=1e-12)
    z = narrow.values.reshape(len(CAMERAS), -1)[:, 5] / expect.reshape(len(CAMERAS), -1)[:, 5]
    assert np.all(np.abs(z) < 3.0), z
    with pytest.raises(InputError, match="focal_prior_px"):
        CalibrateConfig(focal_prior_px=-0.1)


def test_cli_json_and_bad_params(small_month_dir):
    r = CliRunner().invoke(app, ["calibrate", str(small_month_dir), "--json", "--max-passes", "12"])
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    for key in ("cameras", "max_pointing_error_px", "rejected_observations", "iterations", "nees"):
        assert key in s
    assert set(s["cameras"]["Df"]) >= {"params", "pointing_error_px", "sigma_px"}
    assert set(s["cameras"]["Df"]["params"]["beta"]) == {"value", "sigma", "sigma_px"}
    r = CliRunner().invoke(app, ["calibrate", str(small_month_dir), "--params", "delta,gamma"])
    assert r.exit_code == 2 and "--params" in r.output
    r = CliRunner().invoke(app, ["calibrate", str(small_month_dir), "--jitter-arcsec", "-1"])
    assert r.exit_code == 2 and "attitude_jitter_arcsec" in r.output and "Traceback" not in r.output


def test_json_caps_the_rejected_list_and_the_file_holds_it_all(small_month_dir, tmp_path):
    """The summary shows at most 20 rejected observations (the largest residuals) with the count;
    the result file holds every one of them."""
    import h5py

    from misrgraph.io.results import capped_list
    from misrgraph.runs.calibrate import run_calibrate

    out = tmp_path / "cal.h5"
    s = run_calibrate(small_month_dir, out=out, max_passes=12)
    rej = s["rejected_observations"]
    assert rej["full_list"] == f"{out}:/calibration/rejected"
    with h5py.File(out, "r") as f:
        res = f["calibration/rejected/normalised_residual"][()]
    assert res.size == rej["count"] > 0
    assert [e["normalised_residual"] for e in rej["largest"]] == sorted(res, key=abs, reverse=True)[:20]
    many = capped_list(
        [{"normalised_residual": float(i), "camera": "An" if i % 2 else "Df"} for i in range(500)],
        "x.h5:/r",
        group_by=("camera",),
    )
    assert many["count"] == 500 and many["shown"] == 20 and many["largest"][0]["normalised_residual"] == 499.0
    assert many["by_camera"] == {"Df": 250, "An": 250}


def test_supplied_thermal_table_is_applied_per_pass(thermal_month_dir):
    """With the true thermal table as the supplied model, each pass is modelled at its own
    temperature, so the common corrections are zero within their covariance (chi-square, 95 %)
    and the result stays within 3 sigma of the truth at every temperature of the month."""
    sc = load_scenario(thermal_month_dir)
    truth = sc.camera_truth
    passes = [sc.load_pass(i) for i in range(len(sc.pass_files))]
    temps = [p.temperature_c for p in passes]
    cfg = CalibrateConfig()  # robust: the month has 5 % GCP blunders
    res = calibrate_passes(passes, truth.at_temperature(float(np.median(temps))), sc.gcps, cfg, table=truth)
    nees = res.values @ np.linalg.solve(res.covariance, res.values)
    lo, hi = stats.chi2.ppf([0.025, 0.975], res.values.size)
    assert lo <= nees <= hi
    s = score_calibration(summarise(res, cfg, res.camera), res, cfg, res.camera, truth)
    for v in s["cameras"].values():
        assert v["pointing_error_px"] < 3 * v["sigma_px"]


def test_thermal_truth_recovered_by_temperature_bins(thermal_month_dir, tmp_path):
    """A thermal truth: one model for all temperatures misses by many of its own sigma at the ends
    of the temperature range; three bins with the fitted line stay within 3 sigma, recover every
    camera's slopes with an honest covariance (NEES in its 95 % chi-square band), and write a
    temperature table that loads."""
    from misrgraph.io.camera import load_camera_model
    from misrgraph.model.camera import TabulatedCameraModel

    angles = ("delta", "beta", "epsilon")  # the thermal truth moves the angles (and f), not alpha
    one = run_calibrate(thermal_month_dir, cfg=CalibrateConfig(params=angles, temperature_bins=1))
    assert max(v["pointing_error_px"] / v["sigma_px"] for v in one["cameras"].values()) > 3.0
    out = tmp_path / "thermal_cgm.h5"
    three = run_calibrate(thermal_month_dir, out=out, cfg=CalibrateConfig(params=angles, temperature_bins=3))
    for v in three["cameras"].values():
        assert v["pointing_error_px"] < 3 * v["sigma_px"]
    assert three["max_pointing_error_px"] < one["max_pointing_error_px"]
    th = three["thermal"]
    assert len(th["bins_c"]) == 3 and np.all(np.diff(th["bins_c"]) > 0)
    lo, hi = stats.chi2.ppf([0.025, 0.975], th["nees_dim"]) / th["nees_dim"]
    assert lo <= th["nees"] <= hi
    assert set(th["slopes"]) == set(CAMERAS) and set(th["slopes"]["Df"]) == set(angles)
    table = load_camera_model(out)
    assert isinstance(table, TabulatedCameraModel) and len(table.models) == 2
    sc = load_scenario(thermal_month_dir)
    temps = [sc.load_pass(i).temperature_c for i in range(len(sc.pass_files))]
    np.testing.assert_allclose(table.temperatures_c, [min(temps), max(temps)])


def test_temperature_bins_need_enough_passes(month):
    sc, passes = month
    with pytest.raises(DegenerateProblemError, match="temperature bins"):
        calibrate_passes(passes[:3], sc.camera_model, sc.gcps, CalibrateConfig(temperature_bins=2))
    with pytest.raises(InputError, match="temperature_bins"):
        CalibrateConfig(temperature_bins=0)


def test_per_band_truth_recovered_per_band(band_month_dir, tmp_path):
    """All four bands observed, each with its own angle offsets: --per-band recovers every band's
    corrections with an honest covariance (NEES in its 95 % chi-square band) and stores them as
    that band's offsets, leaving the camera-level angles as supplied; one correction per camera
    cannot describe this truth."""
    from misrgraph.io.camera import load_camera_model
    from misrgraph.model.constants import BANDS

    sc = load_scenario(band_month_dir)
    p0 = sc.load_pass(0)
    assert set(np.unique(p0.observations.band)) == set(range(len(BANDS)))
    out = tmp_path / "per_band.h5"
    angles = ("delta", "beta", "epsilon")  # the band offsets are angles
    s = run_calibrate(band_month_dir, out=out, cfg=CalibrateConfig(params=angles, per_band=True))
    lo, hi = stats.chi2.ppf([0.025, 0.975], s["nees_dim"]) / s["nees_dim"]
    assert s["nees_dim"] == 9 * 4 * 3 and lo <= s["nees"] <= hi
    for v in s["cameras"].values():
        assert v["pointing_error_px"] < 3 * v["sigma_px"]
    m = load_camera_model(out)
    z = []
    for name in ("delta", "beta", "epsilon"):
        np.testing.assert_array_equal(getattr(m, name), getattr(sc.camera_model, name))  # nothing summed in
        est = getattr(m, "band_" + name) - getattr(sc.camera_model, "band_" + name)
        true = (
            getattr(sc.camera_truth, name)[:, None]
            + getattr(sc.camera_truth, "band_" + name)
            - getattr(sc.camera_model, name)[:, None]
        )
        for c, cam in enumerate(CAMERAS):
            for b, band in enumerate(BANDS):
                z.append((est[c, b] - true[c, b]) / s["cameras"][cam]["params"][f"{band}.{name}"]["sigma"])
    # 108 standard normal scores: P(max |z| > 4.5) ~ 7e-4
    assert np.max(np.abs(z)) < 4.5
    one = run_calibrate(band_month_dir, cfg=CalibrateConfig(params=angles))
    lo1, hi1 = stats.chi2.ppf([0.025, 0.975], one["nees_dim"]) / one["nees_dim"]
    assert one["nees"] > hi1


def test_camera_variance_components_recover_a_wrong_stated_sigma(month):
    """An's and Bf's observations (the most redundant cameras) stated at half the sigma their
    noise was drawn with. The first round is biased, as any variance-component estimate from
    wrong weights is (the misweighted cameras pull the navigation). At the fixed point the two
    are rescaled by 2 and every other camera by 1, each within three standard errors of a sigma0
    from r redundant rows (``sigma0 / sqrt(2 r)``) plus 0.1, and every camera's sigma0 is then 1."""
    import dataclasses

    sc, passes = month
    wrong = [CAMERAS.index("An"), CAMERAS.index("Bf")]
    halved = [
        dataclasses.replace(
            p,
            observations=dataclasses.replace(
                p.observations,
                sigma_px=np.where(np.isin(p.observations.camera, wrong), 0.5, 1.0) * p.observations.sigma_px,
            ),
        )
        for p in passes
    ]
    res = calibrate_passes(halved, sc.camera_model, sc.gcps, CalibrateConfig(variance_component_rounds=6))
    rounds, scale = res.variance_components["rounds"], res.variance_components["sigma_scale"]
    last = rounds[-1]
    assert len(rounds) >= 2 and set(last) == set(CAMERAS)
    for name, v in last.items():
        assert abs(v["sigma0"] - 1.0) < 3 / np.sqrt(2 * v["redundancy"]) + 0.05, (name, v)
        expect = 2.0 if CAMERAS.index(name) in wrong else 1.0
        assert abs(scale[name] - expect) < 3 * expect / np.sqrt(2 * v["redundancy"]) + 0.1, (name, scale[name], v)
    s = summarise(res, CalibrateConfig(variance_component_rounds=6), sc.camera_model)
    assert s["variance_components"]["sigma_scale"] == scale
    with pytest.raises(InputError, match="variance_component_rounds"):
        CalibrateConfig(variance_component_rounds=-1)


def test_an_unconverged_calibration_fails_unless_accepted(month):
    from misrgraph.errors import ConvergenceError

    sc, passes = month
    with pytest.raises(ConvergenceError, match="did not converge.*--accept-unconverged"):
        calibrate_passes(passes[:6], sc.camera_model, sc.gcps, CalibrateConfig(max_iterations=1))
    res = calibrate_passes(
        passes[:6], sc.camera_model, sc.gcps, CalibrateConfig(max_iterations=1, accept_unconverged=True)
    )
    assert res.status == "iteration_limit"
    s = summarise(res, CalibrateConfig(), sc.camera_model)
    assert s["solver_status"] == "iteration_limit" and s["variance_factor"]["dof"] > 0


@pytest.fixture(scope="module")
def calibrated6(month):
    """A calibration of the month's first six passes: (scenario, config, result, summary)."""
    sc, passes = month
    cfg = CalibrateConfig()
    res = calibrate_passes(passes[:6], sc.camera_model, sc.gcps, cfg)
    return sc, cfg, res, summarise(res, cfg, sc.camera_model)


def test_sigma_px_agrees_with_a_monte_carlo(calibrated6):
    """Each camera's ``sigma_px`` (linear propagation of the posterior) against a 400-draw Monte
    Carlo of the calibrated model's pointing: the mean squares agree within 4 standard errors of
    the Monte Carlo's mean (from its own draws) plus 2 % for nonlinearity."""
    from misrgraph.estimate.calibrate import calibrated_models, evaluation_grid, pointing_error_px

    sc, cfg, res, s = calibrated6
    grid = evaluation_grid(res, sc.camera_model)
    est = calibrated_models(res, cfg, sc.camera_model, grid)
    chol = np.linalg.cholesky(res.covariance)
    rng = np.random.default_rng(7)
    q = []
    for _ in range(400):
        m = calibrated_models(res, cfg, sc.camera_model, grid, res.values + chol @ rng.standard_normal(res.values.size))
        q.append(
            [np.mean([pointing_error_px(m[j], est[j], c) ** 2 for j in range(grid.size)]) for c in range(len(CAMERAS))]
        )
    q = np.array(q)
    mc, se = q.mean(0), q.std(0, ddof=1) / np.sqrt(q.shape[0])
    for c, name in enumerate(CAMERAS):
        lin = s["cameras"][name]["sigma_px"] ** 2
        assert abs(lin - mc[c]) < 4 * se[c] + 0.02 * mc[c], (name, lin, mc[c], se[c])


def test_parameter_sigma_px_is_the_rotation_of_its_one_sigma_in_closed_form(calibrated6):
    """Each angle's ``sigma_px`` against the small rotation it is: moving ``delta`` by ``s`` turns
    every pointing vector ``d`` by ``s |a x d|`` about the axis ``a = T_si Ry(beta) x`` (``beta``:
    ``T_si y``; ``epsilon``: the boresight ``T_si Ry(beta) Rx(delta) z``), in IFOVs, RMS over the
    swath; and a camera's parameters together are no larger than its ``sigma_px``'s propagation
    of the whole covariance allows (their squares sum to it when uncorrelated)."""
    from factors.geometry import rot_x, rot_y
    from misrgraph.estimate.calibrate import RED, calibrated_models, evaluation_grid

    sc, cfg, res, s = calibrated6
    est = calibrated_models(res, cfg, sc.camera_model, evaluation_grid(res, sc.camera_model))[0]
    samples = np.linspace(0, 1503, 48)
    for c, name in enumerate(CAMERAS):
        d = est.direction_scs(np.full(48, c), np.full(48, RED), np.zeros(48), samples)
        ifov = est.ifov_cross_rad(c, RED, samples)
        dl, be, _ = est.angles(c)
        axes = {
            "delta": est.t_si() @ rot_y(be) @ np.array([1.0, 0.0, 0.0]),
            "beta": est.t_si() @ np.array([0.0, 1.0, 0.0]),
            "epsilon": est.t_si() @ rot_y(be) @ rot_x(dl) @ np.array([0.0, 0.0, 1.0]),
        }
        for par, axis in axes.items():
            entry = s["cameras"][name]["params"][par]
            want = entry["sigma"] * np.sqrt(np.mean((np.linalg.norm(np.cross(axis, d), axis=1) / ifov) ** 2))
            assert entry["sigma_px"] == pytest.approx(want, rel=1e-3), (name, par)
        assert s["cameras"][name]["params"]["delta"]["sigma_px"] < s["cameras"][name]["sigma_px"]


def test_jitter_in_the_calibrations_weights(month):
    """``attitude_jitter_arcsec``: each GCP observation's line and sample sigma carries the jitter
    the knots cannot follow, through its pointing sensitivity, exactly as the pass adjustment's
    (``graph.observation_sigma``, tested against independent derivatives in ``test_graph.py``):
    the added variance is ``unresolved^2 |d(line, sample) / d angles|^2``, the unresolved part
    the jitter's share (linear in the jitter) in quadrature with the slow process's, so doubling
    the jitter adds three times the jitter's share; the D cameras' lines feel it most. 0 leaves
    the matcher's sigma. A negative value is refused by name."""
    from misrgraph.estimate.graph import build_pass_graph
    from misrgraph.model.errormodels import unresolved_attitude

    sc, passes = month
    p = passes[0]
    with_j = build_pass_graph(
        p, sc.camera_model, None, sc.gcps, CalibrateConfig(attitude_jitter_arcsec=1.0).graph_config()
    )
    plain = build_pass_graph(p, sc.camera_model, None, sc.gcps, CalibrateConfig().graph_config())
    rows = with_j.obs_index[with_j.collinearity.order]
    stated = p.observations.sigma_px[rows]
    np.testing.assert_array_equal(plain.collinearity.sigma_px, np.stack([stated] * 2, axis=1))
    extra = with_j.collinearity.sigma_px**2 - stated[:, None] ** 2
    assert np.all(extra > 0)
    double = build_pass_graph(
        p, sc.camera_model, None, sc.gcps, CalibrateConfig(attitude_jitter_arcsec=2.0).graph_config()
    )
    kt = with_j.attitude_model.knot_times
    u1 = CalibrateConfig(attitude_jitter_arcsec=1.0).graph_config().unresolved_attitude_rad(kt)
    u2 = CalibrateConfig(attitude_jitter_arcsec=2.0).graph_config().unresolved_attitude_rad(kt)
    assert u2**2 - u1**2 == pytest.approx(3.0 * unresolved_attitude(kt, 1.0) ** 2, rel=1e-9)
    np.testing.assert_allclose(
        double.collinearity.sigma_px**2 - stated[:, None] ** 2, (u2 / u1) ** 2 * extra, rtol=1e-9
    )
    cams = p.observations.camera[rows]
    line = {
        c: float(np.sqrt(extra[cams == CAMERAS.index(c), 0].mean()))
        for c in ("Df", "An", "Da")
        if np.any(cams == CAMERAS.index(c))
    }
    assert "An" in line and all(line[c] > 4 * line["An"] for c in line if c != "An"), line
    with pytest.raises(InputError, match="attitude_jitter_arcsec"):
        CalibrateConfig(attitude_jitter_arcsec=-1.0)
