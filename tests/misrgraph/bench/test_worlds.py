"""``bench worlds`` at the suite's size: the three ways scored, the oracle holding the world's levels."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.bench.worlds import WORLDS, oracle_noise_model
from misrgraph.commands.cli import app
from misrgraph.model.errormodels import ATTITUDE_RATE_FACTOR
from misrgraph.sim.simulate import ScenarioConfig


def test_oracle_holds_the_worlds_levels():
    """The oracle of a world is read from the simulator's own settings, field by field; the base
    world's attitude rate factor equals the pre-flight one (both from the 200-2000 s band)."""
    cfg = ScenarioConfig.from_dict(
        {**WORLDS["navigation x3"], **WORLDS["tie stated x0.5"], "attitude_periods_s": (200.0, 2000.0)}
    )
    m = oracle_noise_model(cfg)
    assert m.observations.tie_sigma_scale == 2.0 and m.observations.gcp_pixel_sigma_scale == 1.0
    assert m.ephemeris.offset_sigma_m == 3 * ScenarioConfig().nav_sigma_m
    assert m.ephemeris.drift_sigma_mps == pytest.approx((0.15, 0.03, 0.03))
    assert m.ephemeris.once_per_rev_m == ScenarioConfig().once_per_rev_m
    rate = [r / v for r, v in zip(m.attitude.rate_sigma_arcsec_per_s, m.attitude.value_sigma_arcsec)]
    assert rate == pytest.approx([ATTITUDE_RATE_FACTOR] * 3, rel=0.02)
    assert m.attitude.knot_spacing_s == (60.0, 60.0, 60.0)
    assert len(WORLDS) >= 12
    # a world whose attitude error is faster gets the knots the noise fit's rule gives its levels:
    # on them the spline misses no more of the process than of the jitter, on twice the spacing more
    from misrgraph.model.errormodels import unresolved_process_sigma

    fast = oracle_noise_model(ScenarioConfig.from_dict(WORLDS["attitude band 30-300 s"]))
    a = fast.attitude
    for h, v, r in zip(a.knot_spacing_s, a.value_sigma_arcsec, a.rate_sigma_arcsec_per_s):
        assert h < 60.0
        missed = [unresolved_process_sigma(np.arange(0.0, 1200.5, x), v, r / v, a.damping) for x in (h, 2 * h)]
        assert missed[0] <= fast.jitter.sigma_arcsec * 1.01 < missed[1], (h, missed)


def test_bench_worlds_cli_scores_three_ways(tmp_path):
    """One tiny world whose tie file states half its sigma, one fitted and one scored pass: every
    way is scored, the learned tie scale is near the true 2 (the oracle's), and the learned way's
    check points are predicted no worse than the fixed way's."""
    r = CliRunner().invoke(
        app,
        [
            "bench",
            "worlds",
            "--worlds",
            "tie stated x0.5",
            "--passes",
            "1",
            "--fit-passes",
            "1",
            "--size",
            "tiny",
            "--workdir",
            str(tmp_path),
            "--json",
        ],
    )
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    w = res["worlds"]["tie stated x0.5"]
    assert set(w["ways"]) == {"fixed", "learned", "oracle"}
    for way in w["ways"].values():
        assert {"landmarks", "knots", "checkpoint_ratio", "checkpoint_rms_m"} <= set(way)
    assert w["true_levels"]["observations"]["tie_sigma_scale"] == 2.0
    assert w["learned_levels"]["observations.tie_sigma_scale"]["value"] == pytest.approx(2.0, rel=0.15)
    assert set(w["acceptance"]) >= {"landmarks_0.8_1.25", "knots_0.7_1.4"}
    # the stated sigma is rejected (far from 1): the learned scale entered the model
    assert w["learned_levels"]["observations.tie_sigma_scale"]["applied"] is True
    # the time ratio is the per-pass learned over fixed adjustment seconds
    pp = w["per_pass"]
    want = pp["learned"][0]["seconds"] / pp["fixed"][0]["seconds"]
    assert w["cost_ratio"]["mean"] == pytest.approx(want) and want > 0
    assert "provenance" in res
    bad = CliRunner().invoke(app, ["bench", "worlds", "--worlds", "mars", "--size", "tiny"])
    assert bad.exit_code == 2 and "worlds" in bad.output
    bad = CliRunner().invoke(app, ["bench", "worlds", "--workers", "0", "--size", "tiny"])
    assert bad.exit_code == 2 and "workers" in bad.output
    # another knot prior on the same simulated passes: its own fit beside the default's
    noise = next(tmp_path.glob("world*_tiny_noise.json"))
    before = noise.read_text()
    r = CliRunner().invoke(
        app,
        ["bench", "worlds", "--worlds", "tie stated x0.5", "--passes", "1", "--fit-passes", "1", "--size", "tiny"]
        + ["--workdir", str(tmp_path), "--knot-prior", "process+jitter", "--json"],
    )
    assert r.exit_code == 0, r.output
    other = json.loads(r.output)
    assert other["knot_prior"] == "process+jitter" and noise.read_text() == before
    assert len(list(tmp_path.glob("world*_tiny_noise-process+jitter.json"))) == 1
    assert len(list(tmp_path.glob("world*/fit_result-process+jitter.h5"))) == 1
    knots = [x["worlds"]["tie stated x0.5"]["per_pass"]["fixed"][0]["knots"] for x in (res, other)]
    assert knots[0] != pytest.approx(knots[1], rel=1e-3)  # the knots are held by another prior
    bad = CliRunner().invoke(app, ["bench", "worlds", "--knot-prior", "spline", "--size", "tiny"])
    assert bad.exit_code == 2 and "knot_prior" in bad.output


def test_bench_worlds_on_two_workers_gives_the_serial_figures(tmp_path):
    """Two tiny worlds on two worker processes, then the first alone in this process on the same
    simulated passes: the worlds come back in the order asked, and the first world's per-pass
    figures (all but the seconds) and learned levels are the serial run's."""
    from misrgraph.bench.worlds import run_bench_worlds

    names = ["GCP stated x2", "tie stated x0.5"]
    both = run_bench_worlds(1, 1, names, size="tiny", workdir=tmp_path, workers=2)
    assert list(both["worlds"]) == names and both["workers"] == 2
    alone = run_bench_worlds(1, 1, names[:1], size="tiny", workdir=tmp_path)
    a, b = both["worlds"][names[0]], alone["worlds"][names[0]]

    def figures(w):
        return {
            way: [{k: v for k, v in p.items() if k != "seconds"} for p in runs] for way, runs in w["per_pass"].items()
        }

    assert figures(a) == figures(b) and figures(a)["learned"]
    assert a["learned_levels"] == b["learned_levels"]
    assert both["worlds"][names[1]]["true_levels"]["observations"]["tie_sigma_scale"] == 2.0


def test_kept_sigma_fraction_against_the_truncated_gaussian_in_closed_form():
    """Gaussian errors kept below a chi-square(2) value c: E[|x|^2 | kept] = 2 - c e^(-c/2) / (1 -
    e^(-c/2)), so the kept sigma is its half's square root; Student-t tails lose more."""
    from misrgraph.bench.worlds import kept_sigma_fraction

    for c in (9.0, 13.8155):
        want = np.sqrt((2 - c * np.exp(-c / 2) / (1 - np.exp(-c / 2))) / 2)
        assert kept_sigma_fraction(0.0, c) == pytest.approx(want, rel=3e-3)
    assert kept_sigma_fraction(5.0, 13.8155) < kept_sigma_fraction(0.0, 13.8155) - 0.03


def test_levels_recovered_compares_each_learned_level_with_the_worlds_own():
    """Two worlds made by hand: the rows, ratios, z, bounds and the coverage count, value by value;
    a band world's attitude rows are left out; the tie scale's truth is the kept observations'."""
    from misrgraph.bench.worlds import kept_sigma_fraction, levels_recovered
    from misrgraph.estimate.reliability import critical_T

    true = {
        "observations": {"tie_sigma_scale": 2.0, "gcp_pixel_sigma_scale": 1.0, "gcp_sigma_scale": 2.0},
        "dem": {"sigma_scale": 1.0},
        "attitude": {"value_sigma_arcsec": [10.0, 20.0, 30.0]},
    }
    learned = {
        "observations.gcp_sigma_scale": {"value": 1.9, "sigma": 0.02},  # -5 %: within, z -5
        "attitude.value_sigma_arcsec.pitch": {"value": 26.0, "sigma": 4.0},  # +30 %: outside, z +1.5
        "dem.sigma_scale": {"value": 1.0, "sigma": None},  # no sigma: not in the coverage count
        "observations.tie_sigma_scale": {"value": 1.0, "sigma": 0.01},  # far from either truth
    }
    r = levels_recovered(
        {
            "worlds": {
                "tie x0.5": {"learned_levels": learned, "true_levels": true},
                "attitude band 30-300 s": {"learned_levels": learned, "true_levels": true},
            }
        }
    )
    rows = {(x["world"], x["level"]): x for x in r["rows"]}
    assert len(rows) == 7 and ("attitude band 30-300 s", "attitude.value_sigma_arcsec.pitch") not in rows
    g = rows[("tie x0.5", "observations.gcp_sigma_scale")]
    assert g["ratio"] == pytest.approx(0.95) and g["z"] == pytest.approx(-5.0) and g["within"]
    assert g["true_kept"] == g["true"] == 2.0
    pitch = rows[("tie x0.5", "attitude.value_sigma_arcsec.pitch")]
    assert pitch["ratio"] == pytest.approx(1.3) and pitch["z"] == pytest.approx(1.5) and not pitch["within"]
    tie = rows[("tie x0.5", "observations.tie_sigma_scale")]
    assert tie["true"] == 2.0 and tie["true_kept"] == pytest.approx(2.0 * kept_sigma_fraction(5.0, critical_T()))
    assert (r["rows_counted"], r["within"], r["with_sigma"], r["covered"]) == (7, 4, 5, 1)
