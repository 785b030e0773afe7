"""Scoring against a truth the estimator does not share."""

from __future__ import annotations

import numpy as np
import pytest

from misrgraph.evaluate.score import true_knots
from misrgraph.io.truth import PassTruth
from misrgraph.model.errormodels import AttitudeErrorModel, EphemerisErrorModel


def _truth(att: AttitudeErrorModel) -> PassTruth:
    return PassTruth(EphemerisErrorModel.zeros(0.0, 600.0), att, np.zeros((0, 3)), np.zeros(0, bool), None)


def test_true_knots_are_the_truths_own_on_the_same_grid_and_its_projection_otherwise():
    """A spline on the estimator's grid: its knots are returned as they are. The same spline
    tabulated on a 2 s grid (a truth the estimator does not share, but inside its spline space):
    the least-squares projection recovers the original knots (to the 2 s tabulation's accuracy)."""
    rng = np.random.default_rng(3)
    kt = np.arange(0.0, 601.0, 60.0)
    coarse = AttitudeErrorModel(
        [kt] * 3, [np.c_[rng.normal(0, 1e-4, kt.size), rng.normal(0, 1e-6, kt.size)] for _ in range(3)]
    )
    np.testing.assert_array_equal(true_knots(_truth(coarse), kt, 1), coarse.knots[1])
    fine_t = np.arange(0.0, 601.0, 2.0)
    fine = AttitudeErrorModel(
        [fine_t] * 3, [np.c_[coarse.evaluate(fine_t)[:, a], coarse.rate(fine_t)[:, a]] for a in range(3)]
    )
    got = true_knots(_truth(fine), kt, 1)
    np.testing.assert_allclose(got[:, 0], coarse.knots[1][:, 0], atol=1e-9)
    np.testing.assert_allclose(got[:, 1], coarse.knots[1][:, 1], atol=1e-10)


def test_an_independent_truth_is_scored_on_what_it_defines(tmp_path):
    """Simulated with truth='independent' (attitude jitter on a 2 s grid, a once-per-revolution
    ephemeris term on 60 s segments), a pass adjusts and is scored: knots against the truth's
    projection, landmarks and check points as before; the parameter-wise ephemeris and whole-state
    NEES, which need the truth in the estimator's parameterisation, are left out and flagged."""
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

    d = tmp_path / "ind"
    run_simulate(
        ScenarioConfig(
            scenario="pass",
            truth="independent",
            seed=5,
            n_tie_points=80,
            n_check_points=10,
            duration_s=600.0,
            start_lat_deg=50.0,
        ),
        d,
    )
    t = load_scenario(d).load_truth(0)
    assert np.allclose(np.diff(t.attitude_error.knot_times[1]), 2.0)
    assert np.allclose(np.diff(t.ephemeris_error.boundaries)[:-1], 60.0)
    s = run_adjust(d)
    assert s["truth_in_estimator_parameterisation"] is False
    assert {"knots", "landmarks", "landmarks_common", "landmarks_within"} <= set(s["nees"])
    assert not {"state", "ephemeris"} & set(s["nees"])
    assert np.isfinite(s["nees"]["knots"]) and s["checkpoint_geolocation_m"]
    # the CLI prints what this truth defines (it once failed looking for the whole-state NEES)
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app

    r = CliRunner().invoke(app, ["adjust", str(d)])
    assert r.exit_code == 0, r.output
    text = " ".join(r.stdout.split())  # rich wraps at the terminal's width
    assert "NEES / dim: knots" in text and "within them" in text and "whole state" not in text
    dem = s["reliability"]["dem_sigma"]  # the DEM row, as the summary has it
    assert f"DEM heights: scale on the DEM's stated sigma {dem['sigma_scale']:.3f} ({dem['status']};" in text, text
    with pytest.raises(Exception, match="truth"):
        ScenarioConfig(truth="made-up")


def test_predicted_checkpoint_rms_agrees_with_a_monte_carlo(small_pass_dir):
    """The check points' predicted RMS (linear propagation of the posterior and the unresolved
    attitude) against a 400-draw Monte Carlo through the same geolocation: states drawn from the
    posterior, and an independent attitude offset (1 sigma ``unresolved_attitude_rad`` per angle)
    at every view. Per camera the two mean squares agree within 4 standard errors of the Monte
    Carlo's own mean (computed from its draws), plus 2 % for the geolocation's nonlinearity."""
    import gtsam

    from misrgraph.estimate.adjust import (
        AdjustConfig,
        adjust_pass,
        corrected_geometry,
        estimated_models,
        supplied_camera_of,
    )
    from misrgraph.evaluate.score import horizontal_error, predicted_checkpoint_rms
    from misrgraph.io.passes import KIND_CHECK
    from misrgraph.model.constants import BANDS, CAMERAS
    from misrgraph.model.frames import ecef_to_geodetic
    from misrgraph.sim.simulate import load_scenario

    sc = load_scenario(small_pass_dir)
    op, truth = sc.load_pass(0), sc.load_truth(0)
    res = adjust_pass(op, sc.camera_model.at_temperature(op.temperature_c), sc.dem, sc.gcps, AdjustConfig())
    assert res.unresolved_attitude_rad > 0
    chk = np.flatnonzero(op.landmarks.kind == KIND_CHECK)
    g = truth.landmark_ecef[chk]
    h = ecef_to_geodetic(g)[2]
    true_geo = truth.geometry(op)
    lin = predicted_checkpoint_rms(op, res, g, h, true_geo)

    red = BANDS.index("red")
    views = [
        (c, p) for c, p in ((c, true_geo.ground_to_pixel(c, red, g)) for c in range(len(CAMERAS))) if p.visible.any()
    ]
    cam_of = np.concatenate([np.full(int(p.visible.sum()), c) for c, p in views])
    line, sample, expo = (
        np.concatenate([getattr(p, a)[p.visible] for _, p in views]) for a in ("line", "sample", "exposure")
    )
    height = np.concatenate([h[p.visible] for _, p in views])
    times = np.unique(true_geo.line_time(cam_of, red, line, expo))
    pg = res.pass_graph
    keys = [k for a in range(3) for k in pg.knot_keys(a)] + pg.ephemeris_keys() + list(pg.camera_keys.values())
    mean = np.concatenate([res.values.atVector(k) for k in keys])
    chol = np.linalg.cholesky(res.marginals.joint_of(keys))
    sizes = np.cumsum([res.values.atVector(k).size for k in keys])[:-1]

    def ground(att, eph, cam, extra=None):
        return corrected_geometry(op, att, eph, cam, attitude_extra=extra).pixel_to_ground(
            cam_of, red, line, sample, height=height, exposure=expo
        )

    base = ground(res.attitude, res.ephemeris, res.camera)
    rng = np.random.default_rng(20261125)
    q = []
    for _ in range(400):
        v = gtsam.Values()
        for k, seg in zip(keys, np.split(mean + chol @ rng.standard_normal(mean.size), sizes)):
            v.insert(k, seg)
        off = rng.standard_normal((times.size, 3)) * res.unresolved_attitude_rad  # one offset per view time
        e2 = (
            horizontal_error(
                ground(
                    *estimated_models(pg, v, supplied_camera_of(res)), lambda t, o=off: o[np.searchsorted(times, t)]
                ),
                base,
            )
            ** 2
        )
        q.append([e2[cam_of == c].mean() for c, _ in views])
    q = np.array(q)
    mc, se = q.mean(0), q.std(0, ddof=1) / np.sqrt(q.shape[0])
    for j, (c, _) in enumerate(views):
        assert abs(lin[CAMERAS[c]] ** 2 - mc[j]) < 4 * se[j] + 0.02 * mc[j], (
            CAMERAS[c],
            lin[CAMERAS[c]] ** 2,
            mc[j],
            se[j],
        )
