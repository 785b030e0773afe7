"""``bench knot-prior``: the closed-form expected NEES against a Monte Carlo of the same linear
model, and the study on a tiny worlds run through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.bench.knotprior import PRIORS, expected_knot_error
from misrgraph.commands.cli import app


def _spd(rng: np.random.Generator, m: int, scale: float) -> np.ndarray:
    a = rng.standard_normal((m, m))
    return scale * (a @ a.T / m + 0.2 * np.eye(m))


def test_expected_knot_error_against_a_monte_carlo_of_the_linear_model(rng) -> None:
    """Truth x ~ N(0, C), data y = x + v with v ~ N(0, D^-1), estimate P D y under a prior L that
    is not C^-1: the mean NEES and the error covariance over 40000 draws match the closed form;
    with L = C^-1 the expected NEES is the dimension exactly."""
    m, n = 6, 40_000
    c, d, lp = _spd(rng, m, 4.0), _spd(rng, m, 1.0), _spd(rng, m, 2.0)
    nees, err = expected_knot_error(d, lp, c)
    x = rng.multivariate_normal(np.zeros(m), c, n)
    y = x + rng.multivariate_normal(np.zeros(m), np.linalg.inv(d), n)
    p = np.linalg.inv(d + lp)
    e = y @ d @ p - x  # rows: (P D y - x)^T
    draws = np.einsum("ij,jk,ik->i", e, d + lp, e)
    assert np.mean(draws) == pytest.approx(nees, abs=4 * np.std(draws) / np.sqrt(n))
    assert abs(nees / m - 1.0) > 0.1  # the case is not the honest one
    se = np.sqrt(2.0 * np.outer(np.diag(err), np.diag(err)) / n)  # a bound on each entry's standard error
    assert np.all(np.abs(e.T @ e / n - err) <= 4 * se)
    exact, _ = expected_knot_error(d, np.linalg.inv(c), c)
    assert exact == pytest.approx(m, rel=1e-10)


def test_knot_prior_study_on_a_tiny_worlds_run(tmp_path) -> None:
    """A tiny 'jitter x2' world (one fitted pass): the exact prior's NEES is 1, a jitter component
    lowers the damped process's NEES (the world has twice the jitter the process's tail holds),
    and a workdir without a worlds run is refused naming the option."""
    from misrgraph.bench.worlds import WORLD_SIZES, WORLDS, world_files
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.runs.noise import run_noise_fit
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    # what 'bench worlds --size tiny --fit-passes 1' leaves of the world's fit in its workdir
    w = list(WORLDS).index("jitter x2")
    pass_dir, fit_result, noise_file = world_files(tmp_path, "jitter x2", "tiny")
    d = pass_dir(20000 + 100 * w)
    over = {**WORLD_SIZES["tiny"], "scenario": "pass", "start_lat_deg": 50.0, **WORLDS["jitter x2"]}
    run_simulate(ScenarioConfig.from_dict({**over, "seed": 20000 + 100 * w}), d)
    run_adjust(d, out=d / fit_result)
    run_noise_fit([d / fit_result], out=noise_file)
    r = CliRunner().invoke(app, ["bench", "knot-prior", "--workdir", str(tmp_path), "--size", "tiny", "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    w = res["worlds"]["jitter x2"]
    assert list(res["worlds"]) == ["jitter x2"] and w["passes"] == 1 and w["blocks"] == 3
    assert set(w["priors"]) == set(PRIORS)
    assert w["priors"]["exact"]["nees"] == pytest.approx(1.0, rel=1e-9)
    assert w["priors"]["process + jitter"]["nees"] < w["priors"]["process"]["nees"]
    assert w["priors"]["exact"]["value_rms_arcsec"] <= w["priors"]["process"]["value_rms_arcsec"] + 1e-9
    assert res["provenance"]["bench"] == "knot-prior"
    empty = tmp_path / "empty"
    empty.mkdir()
    bad = CliRunner().invoke(app, ["bench", "knot-prior", "--workdir", str(empty)])
    assert bad.exit_code == 2 and "workdir" in bad.output
