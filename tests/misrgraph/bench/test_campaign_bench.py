"""``bench campaign`` and the campaign's kill trials, at reduced size (the standard studies --
16 passes for the scaling, 10 trials of each kind -- are ``misrgraph bench campaign``)."""

from __future__ import annotations

import math

import pytest

from misrgraph.bench.campaign import run_bench_campaign, run_campaign_kill_trials


def test_bench_campaign_times_the_same_passes_on_one_and_two_workers(tmp_path) -> None:
    r = run_bench_campaign(paths=1, months=2.0, workdir=tmp_path)
    one, two = r["workers"]["1"], r["workers"]["2"]
    assert one["passes"] == two["passes"] == r["passes"] == 4
    assert len(one["peak_rss_mb_per_worker"]) == 1 and len(two["peak_rss_mb_per_worker"]) == 2
    # the ratio is what the rates say (no timing asserted: the machine is shared)
    assert math.isclose(r["scaling_1_to_2"], two["passes_per_minute"] / one["passes_per_minute"])
    assert r["full_plan"]["passes"] == 233 * 4


@pytest.mark.slow
def test_killed_campaigns_resume_to_identical_results(tmp_path) -> None:
    r = run_campaign_kill_trials(trials=1, kinds=("client", "worker"), seed=3, workdir=tmp_path, paths=1, months=1.0)
    assert len(r["trials"]) == 2
    assert r["failures"] == [], r["failures"]
    for t in r["trials"]:
        assert t["identical"] and t["duplicates"] == 0 and t["counted"] == t["planned"] == 2
