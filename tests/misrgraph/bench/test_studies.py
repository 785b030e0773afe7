"""``misrgraph bench``: the commands run and their figures are consistent (never timed assertions)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.bench.studies import run_bench_incremental, run_bench_sba
from misrgraph.commands.cli import app


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bench")


def test_bench_sba_reports_time_to_equal_cost(bench_dir):
    res = run_bench_sba(tie_points=120, workdir=bench_dir, skip_gtsam=True, skip_ceres=True, budget_s=20.0)
    r = res["results"]
    assert {"misrgraph", "misrgraph_gauss_newton", "misrgraph_gtsam_elimination", "scipy"} <= set(r)
    lowest = min(v["lowest_cost"] for v in r.values())
    assert res["lowest_cost"] == pytest.approx(lowest, rel=1e-15)
    assert res["target_cost"] == pytest.approx(lowest * (1 + 1e-6), rel=1e-15)
    assert r["misrgraph"]["reached"]
    for name, v in r.items():
        assert v["seconds"] >= v["marginal_seconds"] > 0
        if v["reached"]:
            assert v["final_cost"] <= res["target_cost"]
        else:
            assert f"{name}_over_misrgraph" in res["ratios_that_are_lower_bounds"]
        if name != "misrgraph":
            assert res["ratios"][f"{name}_over_misrgraph"] == pytest.approx(v["seconds"] / r["misrgraph"]["seconds"])
        levels = list(v["seconds_to_relative_level"].values())
        reached = [t for t in levels if t is not None]
        assert reached == sorted(reached)  # tighter levels are reached later
    # the second-order DEM term gets at least as low as Gauss-Newton alone
    assert r["misrgraph"]["lowest_cost"] <= r["misrgraph_gauss_newton"]["lowest_cost"] * (1 + 1e-6)


def test_bench_sba_cli(bench_dir):
    runner = CliRunner()
    out = runner.invoke(app, ["bench", "sba", "--tie-points", "120", "--workdir", str(bench_dir), "--skip-gtsam-lm",
                              "--budget", "20", "--json"])
    assert out.exit_code == 0, out.output
    assert json.loads(out.stdout)["results"]["misrgraph"]["reached"]
    bad = runner.invoke(app, ["bench", "sba", "--target-rel", "2"])
    assert bad.exit_code == 2
    assert "--target-rel" in bad.output and "2.0" in bad.output


def test_bench_incremental_ratios_and_accuracy(bench_dir):
    res = run_bench_incremental(passes=3, tie_points=40, workdir=bench_dir, linearization_tol=0.005)
    assert [r["pass"] for r in res["rows"]] == [1, 2, 3] and res["linearization_tol"] == 0.005
    for r in res["rows"]:
        assert r["ratio"] == pytest.approx(r["incremental_seconds"] / r["batch_seconds"])
        assert r["linearization_error_sigma"] <= 0.005
    acc = res["max_difference_in_sigma_vs_tight_batch"]
    assert np.isfinite(acc["batch"]) and acc["incremental"] < 0.01  # 2x the tolerance (module docstring)


def test_interval_from_the_run_to_run_scatter():
    """Student-t interval, closed form: values 1, 2, 3 -> mean 2, half width t(0.975, 2) / sqrt(3)."""
    from scipy import stats

    from misrgraph.bench.studies import _interval

    iv = _interval([1.0, 2.0, 3.0])
    half = stats.t.ppf(0.975, 2) * 1.0 / np.sqrt(3)
    assert iv["mean"] == 2.0 and iv["ci95"] == pytest.approx([2.0 - half, 2.0 + half], rel=1e-12)


def test_bench_nees_per_class_at_reduced_size(tmp_path):
    """Two reduced adjustment runs: every class (knots, ephemeris, camera, landmarks, state) is
    reported with its chi-square band and an interval from the runs; an unknown size is refused."""
    from misrgraph.bench.studies import run_bench_nees
    from misrgraph.errors import InputError

    r = run_bench_nees("adjust", runs=2, seed=1000, workdir=tmp_path)
    assert set(r["summary"]) >= {"knots", "ephemeris", "landmarks", "state", "checkpoint_rms_over_predicted",
                                 "checkpoint_rms_m"}
    for k, v in r["summary"].items():
        lo, hi = v["per_run"]["ci95"]
        assert lo <= v["per_run"]["mean"] <= hi, k
        assert ("band" in v) == (k not in ("checkpoint_rms_over_predicted", "checkpoint_rms_m")), k
        if "band" in v:
            assert v["band"][0] < 1 < v["band"][1], k
        assert v["per_run"]["mean"] == pytest.approx(np.mean([p[k] for p in r["per_run"]]))
    with pytest.raises(InputError, match="size"):
        run_bench_nees("adjust", runs=1, size="huge", workdir=tmp_path)


def test_time_ratios_only_against_a_baseline_that_reached_the_target():
    from misrgraph.bench.studies import _time_ratios

    reached = {"misrgraph": {"reached": True, "seconds": 2.0}, "scipy": {"reached": True, "seconds": 3.0},
               "gtsam_lm": {"reached": False, "seconds": 60.0}, "ceres": {"skipped": "not installed"}}
    ratios, bounds = _time_ratios(reached)
    assert ratios == {"scipy_over_misrgraph": 1.5, "gtsam_lm_over_misrgraph": 30.0}
    assert bounds == ["gtsam_lm_over_misrgraph"]
    missed = dict(reached, misrgraph={"reached": False, "seconds": 2.0})
    assert _time_ratios(missed) == ({}, [])


def test_bench_pp_at_reduced_size(bench_dir):
    """The PP honesty study on two reduced passes (the bench runs more): the cameras that see the
    block scored, intervals from the runs, the PP better than the supplied navigation in each."""
    from misrgraph.bench.studies import run_bench_pp

    res = run_bench_pp(runs=2, seed=5000, workdir=bench_dir, blocks_per_pass=1)
    per_cam = res["summary"]["per_camera"]
    assert len(res["per_run"]) == 2
    # a 10-minute pass's Df view runs ~7 minutes ahead and may miss the block; the others see it
    assert set(per_cam) >= {"Cf", "Bf", "Af", "An", "Aa", "Ba", "Ca", "Da"}
    for cam, v in per_cam.items():
        assert v["passes"] == sum(cam in r["nees"] for r in res["per_run"])
        if v["passes"] == 2:
            lo, hi = v["rms_over_predicted"]["ci95"]
            assert lo <= v["rms_over_predicted"]["mean"] <= hi
        assert v["improvement_over_supplied"]["mean"] > 2.0, cam
    # two passes cannot pin honesty down, but a sigma off by a factor of three would show
    assert 1 / 3 < res["summary"]["rms_over_predicted_all_cameras"]["mean"] < 3
