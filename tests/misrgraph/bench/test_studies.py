"""``misrgraph bench``: the commands run and their figures are consistent (never timed assertions)."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bench_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bench")


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
