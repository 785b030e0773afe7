"""``run_adjust``: the estimate does not depend on the truth a simulated pass file carries, and a
scenario of several passes needs the pass named."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from misrgraph.errors import InputError
from misrgraph.io.gcp import read_gcp_database, save_gcp_database
from misrgraph.io.passes import OrbitPass
from misrgraph.io.truth import has_truth
from misrgraph.runs.adjust import run_adjust


def test_the_estimate_is_the_same_with_the_truth_removed(small_pass_dir, tmp_path):
    """The same pass with every truth group removed (pass, GCP database, true camera model) gives
    the same estimates (to 1e-9: the linear algebra's summation order may vary between runs);
    only the scores disappear. Together with tests/test_layout.py (no ``truth`` anywhere in
    misrgraph/estimate) this shows the estimator never reads it."""
    blind = tmp_path / "blind"
    shutil.copytree(small_pass_dir, blind)
    for f in (blind / "passes").glob("*.h5"):
        OrbitPass.load(f).save(f)
        assert not has_truth(f, "orbit_pass")
    save_gcp_database(read_gcp_database(blind / "gcp.h5"), blind / "gcp.h5")
    assert not has_truth(blind / "gcp.h5", "gcp_database")
    (blind / "camera_truth.h5").unlink()
    with_truth = run_adjust(small_pass_dir)
    without = run_adjust(blind)
    for key in ("iterations", "observations", "landmarks", "dropped_tie_points", "knots"):
        assert without[key] == with_truth[key], key
    assert without["final_cost"] == pytest.approx(with_truth["final_cost"], rel=1e-9)
    for key in ("params", "sigma"):
        np.testing.assert_allclose(without["ephemeris"][key], with_truth["ephemeris"][key], rtol=1e-9, atol=1e-12)
    a, b = without["rejected_observations"], with_truth["rejected_observations"]
    assert a["count"] == b["count"] > 0
    assert [r["index"] for r in a["largest"]] == [r["index"] for r in b["largest"]]
    np.testing.assert_allclose(
        [r["normalised_residual"] for r in a["largest"]], [r["normalised_residual"] for r in b["largest"]], rtol=1e-9
    )
    for key in ("nees", "checkpoint_geolocation_m", "attitude_rms_arcsec"):
        assert key in with_truth and key not in without


def test_a_scenario_of_several_passes_needs_the_pass_named(path_dir):
    with pytest.raises(InputError, match="PASS_FILE.*pass files.*--pass"):
        run_adjust(path_dir)
    first = sorted((path_dir / "passes").glob("*.h5"))[0]
    s = run_adjust(path_dir, pass_file=first)
    assert s["pass_id"] == first.stem and np.isfinite(s["final_cost"])


def test_an_unconverged_adjustment_fails_unless_accepted(small_pass_dir, tmp_path):
    """One iteration is not enough: exit 1 with a one-line reason; with --accept-unconverged the
    result is written and flagged (summary, diagnostics and RESULT.h5)."""
    import subprocess
    import sys

    import h5py

    from misrgraph.errors import ConvergenceError
    from misrgraph.estimate.adjust import AdjustConfig

    with pytest.raises(ConvergenceError, match="did not converge"):
        run_adjust(small_pass_dir, cfg=AdjustConfig(max_iterations=1))
    out = tmp_path / "r.h5"
    s = run_adjust(small_pass_dir, out=out, cfg=AdjustConfig(max_iterations=1, accept_unconverged=True))
    assert s["solver_status"] == "iteration_limit"
    assert "not those of an optimum" in s["diagnostics"][0]
    with h5py.File(out) as f:
        assert f.attrs["solver_status"] == "iteration_limit"
    r = subprocess.run(
        [sys.executable, "-m", "misrgraph", "adjust", str(small_pass_dir), "--max-iterations", "1"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 1 and len(lines) == 1 and "did not converge" in lines[0], r.stderr
    assert run_adjust(small_pass_dir)["solver_status"] == "converged"


def test_drop_rejected_tie_points_drops_every_tie_point_with_a_rejected_ray(small_pass_dir):
    """``adjust --drop-rejected-tie-points``: every tie point with a rejected observation (robust
    screen or data snooping; the pass has 2 % tie-point blunders) leaves the solution whole, and
    only those; without the flag only the tie points whose rays were mostly rejected go."""
    import json

    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.estimate.adjust import AdjustConfig, adjust_pass
    from misrgraph.io.passes import KIND_TIE
    from misrgraph.sim.simulate import load_scenario

    sc = load_scenario(small_pass_dir)
    op = sc.load_pass(0)
    cam = sc.camera_model.at_temperature(op.temperature_c)
    res = adjust_pass(op, cam, sc.dem, sc.gcps, AdjustConfig(drop_rejected_tie_points=True))
    lm = op.observations.landmark[res.rejected]
    with_rejection = set(lm[op.landmarks.kind[lm] == KIND_TIE].tolist())
    assert len(with_rejection) >= 3
    assert set(res.dropped_landmarks.tolist()) == with_rejection
    assert not set(res.pass_graph.landmark_rows.tolist()) & with_rejection
    out = CliRunner().invoke(app, ["adjust", str(small_pass_dir), "--drop-rejected-tie-points", "--json"])
    assert out.exit_code == 0, out.output
    flagged = json.loads(out.stdout[out.stdout.index("{") :])
    assert flagged["dropped_tie_points"] == len(with_rejection)
    assert run_adjust(small_pass_dir)["dropped_tie_points"] < len(with_rejection)


def test_adjust_cli_jitter_options(small_pass_dir):
    """``--jitter-arcsec``/``--jitter-periods-s`` reach the adjustment: the summary's unresolved
    attitude is the stated jitter's part the knots cannot follow on that band in quadrature with
    the pre-flight process's (:func:`unresolved_process_sigma`), none at 0, and a bad band is
    refused naming the option."""
    import json

    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.model.errormodels import (
        ATTITUDE_DAMPING,
        ATTITUDE_RATE_FACTOR,
        uniform_knots,
        unresolved_band_sigma,
        unresolved_process_sigma,
    )
    from misrgraph.model.noise import NoiseModel

    def unresolved(*args):
        out = CliRunner().invoke(app, ["adjust", str(small_pass_dir), "--json", *args])
        assert out.exit_code == 0, out.output
        s = json.loads(out.stdout[out.stdout.index("{") :])
        return {v["unresolved_sigma_arcsec"] for v in s["attitude_sigma"].values()}

    (default,) = unresolved()
    (two,) = unresolved("--jitter-arcsec", "2", "--jitter-periods-s", "30,300")
    assert unresolved("--jitter-arcsec", "0") == {0.0}
    kt = uniform_knots(0.0, 600.0, 60.0)  # the share depends on the knot spacing, not the pass
    process2 = np.mean(
        [
            unresolved_process_sigma(kt, s, ATTITUDE_RATE_FACTOR, ATTITUDE_DAMPING) ** 2
            for s in NoiseModel().attitude.value_sigma_arcsec
        ]
    )
    assert default == pytest.approx(np.sqrt(unresolved_band_sigma(kt, 1.0) ** 2 + process2), rel=0.02)
    assert two == pytest.approx(np.sqrt((2 * unresolved_band_sigma(kt, 1.0, (30.0, 300.0))) ** 2 + process2), rel=0.02)
    assert two < 2 * default  # slower jitter: the knots take up more of it
    for bad in ("120,8", "8"):
        out = CliRunner().invoke(app, ["adjust", str(small_pass_dir), "--jitter-periods-s", bad])
        assert out.exit_code == 2 and "attitude_jitter_periods_s" in out.output, out.output
    out = CliRunner().invoke(app, ["adjust", str(small_pass_dir), "--jitter-periods-s", "a,b"])
    assert out.exit_code == 2 and "--jitter-periods-s" in out.output, out.output


def test_adjust_cli_once_per_rev_option(small_pass_dir):
    """``--ephemeris-once-per-rev-m`` reaches the adjustment (the summary's ephemeris sigma grows),
    ``--ephemeris-segments 2`` gives two segments, and a negative amplitude or three segments with
    the term are refused naming the setting."""
    import json

    from typer.testing import CliRunner

    from misrgraph.commands.cli import app

    def eph_sigma(*args):
        out = CliRunner().invoke(app, ["adjust", str(small_pass_dir), "--json", *args])
        assert out.exit_code == 0, out.output
        return np.array(json.loads(out.stdout[out.stdout.index("{") :])["ephemeris"]["sigma"])

    base, wide = eph_sigma(), eph_sigma("--ephemeris-once-per-rev-m", "30")
    assert np.all(wide >= base * (1 - 1e-9)) and np.any(wide > 1.05 * base)
    two = eph_sigma("--ephemeris-once-per-rev-m", "30", "--ephemeris-segments", "2")
    assert base.shape == (1, 6) and two.shape == (2, 6)
    out = CliRunner().invoke(app, ["adjust", str(small_pass_dir), "--ephemeris-once-per-rev-m", "-1"])
    assert out.exit_code == 2 and "ephemeris_once_per_rev_m" in out.output, out.output
    out = CliRunner().invoke(
        app, ["adjust", str(small_pass_dir), "--ephemeris-once-per-rev-m", "30", "--ephemeris-segments", "3"]
    )
    assert out.exit_code == 2 and "ephemeris_segments" in out.output, out.output


def test_tie_height_pools_the_matched_passes_estimates(imagery_pass_dir, tmp_path):
    """``misrgraph tie-height RESULT.h5 ...``: the pooled value is the row-weighted mean of the
    results' own unclipped estimates, so the same matched pass twice gives that pass's estimate
    with zero scatter (the statistics are tested in ``test_tieheight.py``); a result of simulated
    observations is skipped and said to be; fewer than two estimates, or a missing file, is
    refused with exit 2 naming it; the printed command fixes the value."""
    import json

    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.runs.adjust import run_tie_height_pool

    matched = tmp_path / "matched.h5"
    s = run_adjust(imagery_pass_dir, observations="matched", out=matched)
    th = s["tie_height"]
    assert th["source"] == "estimated"
    copy = tmp_path / "matched_copy.h5"
    shutil.copy(matched, copy)
    simulated = tmp_path / "simulated.h5"
    run_adjust(imagery_pass_dir, out=simulated)
    res = run_tie_height_pool([matched, copy, simulated])
    assert res["passes"] == 2 and list(res["skipped"]) == [str(simulated)] and "off" in res["skipped"][str(simulated)]
    assert res["unclipped_variance_m2"] == pytest.approx(th["unclipped_variance_m2"])
    assert res["standard_error_m2"] == pytest.approx(0.0, abs=1e-9)
    assert res["dem_factors"] == 2 * th["dem_factors"]
    assert res["sigma_m"] == pytest.approx(np.sqrt(max(th["unclipped_variance_m2"], 0.0)))
    runner = CliRunner()
    out = runner.invoke(app, ["tie-height", str(matched), str(copy), str(simulated)])
    assert out.exit_code == 0, out.output
    assert f"--tie-height-sigma-m {res['sigma_m']:.1f}" in out.stdout and "skipped" in out.stdout
    js = runner.invoke(app, ["tie-height", str(matched), str(copy), "--json"])
    assert json.loads(js.stdout)["passes"] == 2
    bad = runner.invoke(app, ["tie-height", str(matched), str(simulated)])
    assert bad.exit_code == 2 and "results" in bad.output and "Traceback" not in bad.output
    missing = runner.invoke(app, ["tie-height", str(matched), str(tmp_path / "nope.h5")])
    assert missing.exit_code == 2 and "nope.h5" in missing.output
