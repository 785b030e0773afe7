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
    coarse = AttitudeErrorModel([kt] * 3, [np.c_[rng.normal(0, 1e-4, kt.size), rng.normal(0, 1e-6, kt.size)]
                                           for _ in range(3)])
    np.testing.assert_array_equal(true_knots(_truth(coarse), kt, 1), coarse.knots[1])
    fine_t = np.arange(0.0, 601.0, 2.0)
    fine = AttitudeErrorModel([fine_t] * 3, [np.c_[coarse.evaluate(fine_t)[:, a], coarse.rate(fine_t)[:, a]] for a in range(3)])
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
    run_simulate(ScenarioConfig(scenario="pass", truth="independent", seed=5, n_tie_points=80, n_check_points=10,
                                duration_s=600.0, start_lat_deg=50.0), d)
    t = load_scenario(d).load_truth(0)
    assert np.allclose(np.diff(t.attitude_error.knot_times[1]), 2.0)
    assert np.allclose(np.diff(t.ephemeris_error.boundaries)[:-1], 60.0)
    s = run_adjust(d)
    assert s["truth_in_estimator_parameterisation"] is False
    assert {"knots", "landmarks"} <= set(s["nees"]) and not {"state", "ephemeris"} & set(s["nees"])
    assert np.isfinite(s["nees"]["knots"]) and s["checkpoint_geolocation_m"]
    with pytest.raises(Exception, match="truth"):
        ScenarioConfig(truth="made-up")
