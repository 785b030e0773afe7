"""``misrgraph bench sba`` and ``bench incremental`` at reduced size: the figures are consistent
with the verified optimum they are measured against (never timed assertions)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.bench.accuracy import SIGMA_LEVELS, VERIFIED_STEP_SIGMA, run_bench_incremental, run_bench_sba
from misrgraph.commands.cli import app


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bench_accuracy")


@pytest.fixture(scope="module")
def sba(bench_dir):
    return run_bench_sba(
        tie_points=100,
        workdir=bench_dir,
        skip=("gtsam_lm", "scipy_trf_unscaled"),
        budget_s=20.0,
        check_points=20,
        duration_s=900.0,
    )


def test_bench_sba_measures_every_solver_against_a_verified_optimum(sba):
    ref = sba["reference"]
    assert ref["verified"] and ref["gauss_newton_step_max_sigma"] <= VERIFIED_STEP_SIGMA
    levels = [f"{v:g}" for v in SIGMA_LEVELS]
    assert sba["sigma_levels"] == levels == ["1", "0.3", "0.1", "0.03"]
    ran = {n: r for n, r in sba["solvers"].items() if "skipped" not in r}
    assert {"misrgraph", "misrgraph_gauss_newton", "scipy_trf", "scipy_trust_krylov"} <= set(ran)
    for name, r in ran.items():
        st = r["stop"]
        # the optimum is the lowest cost anyone reached, polished: nobody ends below it
        assert st["cost"] >= ref["cost"] * (1 - 1e-12), name
        times = [r["seconds_to_sigma"][lv] for lv in levels]
        hit = [t for t in times if t is not None]
        assert hit == sorted(hit) and times[: len(hit)] == hit, name  # tighter levels later, never before a looser one
        for lv in levels:
            if st["max_sigma"] <= float(lv):
                assert r["seconds_to_sigma"][lv] is not None and r["seconds_to_sigma"][lv] <= st["seconds"], (name, lv)
            mh = r["seconds_to_mahalanobis"][lv]
            if mh is not None and r["seconds_to_sigma"][lv] is not None:
                # the whole-state norm bounds each knot's distance: it is reached no sooner
                assert mh >= r["seconds_to_sigma"][lv], (name, lv)
        assert st["checkpoint_rms_m"] > 0 and st["coregistration_px"] > 0
    core = ran["misrgraph"]["stop"]
    assert core["ended"] == "converged" and core["max_sigma"] < 1e-3
    # products from the core's end point are those of the optimum
    assert core["checkpoint_rms_m"] == pytest.approx(ref["checkpoint_rms_m"], rel=1e-3)
    t_core = ran["misrgraph"]["seconds_to_sigma"]["0.1"]
    for name, ratio in sba["ratio_to_core_at_0.1_sigma"].items():
        t = ran[name]["seconds_to_sigma"]["0.1"]
        if t is not None:
            assert ratio == pytest.approx(t / t_core)
        elif name in sba["ratios_that_are_lower_bounds"]:  # cut by its budget
            assert ratio == pytest.approx(ran[name]["stop"]["seconds"] / t_core)
            assert ran[name]["stop"]["ended"].startswith("time budget")
        else:  # stopped by its own rule short of 0.1 sigma
            assert ratio is None and name in sba["never_within_0.1_sigma"]
    assert sba["marginals"]["seconds"] > 0


def test_bench_sba_cli_json_and_a_bad_solver_name(bench_dir):
    runner = CliRunner()
    out = runner.invoke(
        app,
        [
            "bench",
            "sba",
            "--tie-points",
            "100",
            "--check-points",
            "0",
            "--workdir",
            str(bench_dir),
            "--skip",
            "gtsam_lm,scipy_trf_unscaled,scipy_trust_krylov,ceres,ceres_batched,misrgraph_gauss_newton",
            "--budget",
            "20",
            "--json",
        ],
    )
    assert out.exit_code == 0, out.output
    res = json.loads(out.stdout)
    assert set(res["solvers"]) == {"misrgraph", "scipy_trf"}
    assert set(res["solvers"]["misrgraph"]["stop"]) >= {"seconds", "max_sigma", "checkpoint_rms_m", "coregistration_px"}
    assert res["solvers"]["misrgraph"]["stop"]["checkpoint_rms_m"] is None  # no check points in that pass
    bad = runner.invoke(app, ["bench", "sba", "--skip", "cerez"])
    assert bad.exit_code != 0 and "cerez" in bad.output and "skip" in bad.output


def test_bench_incremental_per_pass_at_equal_accuracy(bench_dir):
    # passes are summarised after one newer pass, so passes 1 and 2 are settled by the end
    res = run_bench_incremental(passes=4, tie_points=40, workdir=bench_dir, linearization_tol=0.005, settle_after=1)
    rows = res["per_pass"]
    assert [r["pass"] for r in rows] == [1, 2, 3, 4] and res["linearization_tol"] == 0.005 and res["settle_after"] == 1
    for r in rows:
        assert r["update_seconds"] > 0 and r["batch_seconds"] > 0
        assert r["optimum_gauss_newton_step_sigma"] <= VERIFIED_STEP_SIGMA
        assert r["max_difference_sigma"] < 0.05  # the acceptance level of issue 20
        assert r["linearization_error_sigma"] <= 0.005
    assert res["max_difference_sigma_worst"] == max(r["max_difference_sigma"] for r in rows)
    assert res["update_last_over_update_10"] is None and list(res["at"]) == ["4"]
    assert res["at"]["4"]["update_over_batch"] == pytest.approx(rows[-1]["update_seconds"] / rows[-1]["batch_seconds"])
    assert np.isfinite(res["at"]["4"]["update_over_batch"])
