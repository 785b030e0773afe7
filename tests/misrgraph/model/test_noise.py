"""The noise model: one home for every level the estimator assumes, a file a user edits, and the
levels reaching the graph and the summaries."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.adjust import AdjustConfig
from misrgraph.estimate.calibrate import CalibrateConfig
from misrgraph.estimate.graph import GraphConfig
from misrgraph.io.noise import read_noise_model, save_noise_model
from misrgraph.model.noise import LEVELS, NoiseModel

runner = CliRunner()


def test_the_pre_flight_model_is_what_the_estimator_assumes_without_one():
    """Given the defaults, an adjustment and a calibration are configured exactly as without."""
    assert AdjustConfig().with_noise(NoiseModel()) == AdjustConfig()
    assert CalibrateConfig(noise=NoiseModel()).graph_config() == CalibrateConfig().graph_config()
    g = GraphConfig()
    for k, v in NoiseModel().navigation_fields().items():
        assert getattr(g, k) == v, k


def test_every_level_is_listed_with_its_source():
    m = NoiseModel()
    listed = set(LEVELS)
    fields = {
        (s, f)
        for s in ("attitude", "jitter", "ephemeris", "camera", "dem", "observations")
        for f in getattr(m, s).to_dict()
    }
    assert listed == fields
    assert all(unit and source for unit, source in LEVELS.values())


def test_file_round_trip_and_partial_files(tmp_path):
    m = NoiseModel.from_dict(
        {"attitude": {"value_sigma_arcsec": [20, 30, 25], "damping": 0.9}, "ephemeris": {"offset_sigma_m": 150.0}}
    )
    save_noise_model(m, tmp_path / "n.json", source={"ephemeris": "learned"})
    back, source = read_noise_model(tmp_path / "n.json")
    assert back == m and source["ephemeris"] == "learned" and source["attitude"] == "pre-flight"
    # a section left out takes the pre-flight levels
    (tmp_path / "p.json").write_text(
        json.dumps({"kind": "misrgraph noise model", "version": 1, "jitter": {"sigma_arcsec": 2.0}})
    )
    part, _ = read_noise_model(tmp_path / "p.json")
    assert part.jitter.sigma_arcsec == 2.0 and part.attitude == NoiseModel().attitude


@pytest.mark.parametrize(
    "content, message",
    [
        ("{", "not JSON"),
        (json.dumps({"kind": "something else", "version": 1}), "not a noise model"),
        (json.dumps({"kind": "misrgraph noise model", "version": 9}), "version 9"),
        (json.dumps({"kind": "misrgraph noise model", "version": 1, "jiter": {}}), "NoiseModel.jiter"),
        (
            json.dumps({"kind": "misrgraph noise model", "version": 1, "attitude": {"value_sigma_arcsec": [1, 2]}}),
            "attitude.value_sigma_arcsec",
        ),
        (
            json.dumps({"kind": "misrgraph noise model", "version": 1, "jitter": {"periods_s": [120, 8]}}),
            "jitter.periods_s",
        ),
    ],
)
def test_bad_files_are_refused_naming_the_field(tmp_path, content, message):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(FileFormatError, match=message) as err:
        read_noise_model(p)
    assert str(p) in str(err.value)


def test_bad_levels_name_the_field():
    with pytest.raises(InputError, match="camera.angle_prior_px"):
        NoiseModel.from_dict({"camera": {"angle_prior_px": 0.0}})
    with pytest.raises(InputError, match="attitude_rate_sigma_arcsec_per_s"):
        GraphConfig(attitude_rate_sigma_arcsec_per_s=(1.0, 2.0))


def test_the_levels_reach_the_adjustment(small_pass_dir, tmp_path):
    """With the attitude's value sigma doubled and the jitter doubled, the adjustment's summary
    states the file's prior and an unresolved attitude about twice the default (the jitter's
    share is linear in the jitter's sigma, the process's in its sigma: closed form), and its
    posterior attitude sigma grows; the ephemeris offset's prior widened tenfold widens the
    ephemeris posterior."""
    runner.invoke(app, ["noise", "init", "--out", str(tmp_path / "pre.json")])
    m = NoiseModel.from_dict(
        {
            "attitude": {"value_sigma_arcsec": [27.0, 29.0, 24.0]},
            "jitter": {"sigma_arcsec": 2.0},
            "ephemeris": {"offset_sigma_m": 500.0},
        }
    )
    save_noise_model(m, tmp_path / "wide.json")
    out = {}
    for name in ("pre", "wide"):
        res = runner.invoke(
            app, ["adjust", str(small_pass_dir), "--noise-model", str(tmp_path / f"{name}.json"), "--json"]
        )
        assert res.exit_code == 0, res.output
        out[name] = json.loads(res.stdout)
    plain = runner.invoke(app, ["adjust", str(small_pass_dir), "--json"])
    pre, wide = out["pre"], out["wide"]
    assert json.loads(plain.stdout)["nees"] == pre["nees"]  # the pre-flight file changes nothing
    for axis, value in zip(("roll", "pitch", "yaw"), (27.0, 29.0, 24.0)):
        a, b = pre["attitude_sigma"][axis], wide["attitude_sigma"][axis]
        assert b["prior_sigma_arcsec"] == pytest.approx(value)
        # the jitter's share doubles; the slow process's between the knots grows with its sigma
        # (27/13.67 to 24/12 of the pre-flight's): the whole by a factor in between
        ratio = b["unresolved_sigma_arcsec"] / a["unresolved_sigma_arcsec"]
        assert 27.0 / (41.0 / 3) - 1e-9 < ratio < 2.0 + 1e-9, ratio
        assert b["max_sigma_arcsec"] > a["max_sigma_arcsec"]
    assert np.all(np.array(wide["ephemeris"]["sigma"])[:, 3:] > np.array(pre["ephemeris"]["sigma"])[:, 3:])


def test_noise_show_and_a_bad_file_on_the_cli(tmp_path):
    res = runner.invoke(app, ["noise", "show", "--json"])
    assert res.exit_code == 0
    levels = {r["level"]: r for r in json.loads(res.stdout)["levels"]}
    assert levels["ephemeris.offset_sigma_m"]["value"] == 50.0 and levels["ephemeris.offset_sigma_m"]["unit"] == "m"
    (tmp_path / "bad.json").write_text("{}")
    res = runner.invoke(app, ["adjust", str(tmp_path), "--noise-model", str(tmp_path / "bad.json")])
    assert res.exit_code == 2 and "bad.json: not a noise model" in res.stderr


def test_the_campaign_carries_a_noise_model_and_plans_as_before_without_one():
    """A campaign's noise model reaches the calibration's and the adjustments' configurations and
    its plan; without one the plan's configuration is the one earlier campaigns stored, so they
    resume."""
    from misrgraph.campaign import tasks
    from misrgraph.campaign.plan import CampaignConfig, plan_campaign

    m = NoiseModel.from_dict({"ephemeris": {"offset_sigma_m": 120.0}, "attitude": {"damping": 1.0}})
    assert tasks._adjust_config(None) == AdjustConfig()
    assert tasks._adjust_config(m.to_dict()) == AdjustConfig().with_noise(m)
    assert tasks._adjust_config(m.to_dict()).graph.ephemeris_b_sigma_m == 120.0
    base = CampaignConfig(paths=(37,), months=1.0, size="reduced")
    plain = plan_campaign(base).to_dict()["config"]
    assert "noise" not in plain
    withm = CampaignConfig.from_dict({**base.to_dict(), "noise": m.to_dict()})
    assert withm.noise == m
    assert plan_campaign(withm).to_dict()["config"]["noise"]["ephemeris"]["offset_sigma_m"] == 120.0


def _misstated_pass_components(
    tmp_path, seed: int, field: str, scale_field: str, section: str = "observations", **sizes
) -> dict[str, dict]:
    """A model-truth pass drawn with ``field`` = 2 (a file that understates its sigma by half),
    adjusted with its noise-model scale ``section.scale_field`` at 1 ("stated") and at 2 ("scaled"):
    each adjustment's variance components. The model truth has no jitter, and the per-pass
    variance components and data snooping are off, so that sigma0 shows the stated scale."""
    from misrgraph.estimate.adjust import adjust_pass
    from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

    cfg = dict(truth="model", scenario="pass", seed=seed, duration_s=900.0, start_lat_deg=55.0, gcp_blunder_rate=0.0)
    run_simulate(ScenarioConfig(**cfg, **sizes, **{field: 2.0}), tmp_path / "s")
    sc = load_scenario(tmp_path / "s")
    p = sc.load_pass(0)
    base = AdjustConfig.from_dict(attitude_jitter_arcsec=0.0, snooping_rounds=0, variance_component_rounds=0)
    out = {}
    for name, k in (("stated", 1.0), ("scaled", 2.0)):
        m = NoiseModel.from_dict({section: {scale_field: k}})
        g = base.graph.replace(**{**m.graph_fields(), "attitude_jitter_arcsec": 0.0})
        out[name] = adjust_pass(p, sc.camera_model, sc.dem, sc.gcps, base.replace(graph=g)).reliability[
            "variance_components"
        ]
    return out


def test_observation_scales_correct_files_that_misstate_their_accuracy(tmp_path):
    """A pass whose tie-point file understates its sigma by half (the simulator draws them at
    twice the stated sigma) reads a tie-point variance factor near 2; with the noise model's tie
    scale at 2 it reads near 1. The GCP scales reach the GCP rows."""
    vc = _misstated_pass_components(
        tmp_path, 31, "tie_sigma_true_over_stated", "tie_sigma_scale", n_tie_points=150, n_check_points=10, n_gcps=20
    )
    tie = "tie-point observations"
    assert 1.7 < vc["stated"][tie]["sigma0"] < 2.3, vc
    assert 0.85 < vc["scaled"][tie]["sigma0"] < 1.15, vc
    base = AdjustConfig()
    g = base.graph.replace(**NoiseModel.from_dict({"observations": {"gcp_sigma_scale": 3.0}}).graph_fields())
    assert g.gcp_sigma_scale == 3.0 and g.tie_sigma_scale == 1.0


def test_gcp_positions_variance_component_reads_a_misstated_catalogue(tmp_path):
    """A pass whose GCP catalogue understates its positions' sigma by half (drawn at twice the
    stated sigma; the GCP measurements as stated): the GCP positions' variance component (their
    priors' rows) reads near 2, and near 1 with the noise model's GCP scale at 2."""
    vc = _misstated_pass_components(
        tmp_path, 32, "gcp_sigma_true_over_stated", "gcp_sigma_scale", n_tie_points=100, n_check_points=5, n_gcps=400
    )
    got = {k: v["GCP positions"] for k, v in vc.items()}
    s, r = got["stated"]["sigma0"], got["stated"]["redundancy"]
    assert r > 20, got  # enough GCP rows to read the scale
    assert abs(s - 2.0) < 3 * 2.0 / np.sqrt(2 * r), got
    assert 0.7 < got["scaled"]["sigma0"] < 1.3 and 1.6 < s / got["scaled"]["sigma0"] < 2.4, got


def test_the_dem_scale_reads_a_misstated_dem(tmp_path):
    """A pass whose DEM understates its sigma by half (its errors drawn at twice the stated
    sigma), adjusted once with the DEM scale at 1 and once at 2 (no per-pass variance
    components): the DEM factors' sigma also holds the surface fit's residual, which the file does
    not state (a share of their variance strictly between 0 and 1 is the stated sigma);
    class_scale turns each component, with that share and the scale it was read at, into the
    scale on the stated sigma, near 2 both times; at 2 the component itself reads near 1."""
    from misrgraph.estimate.reliability import class_scale

    vc = _misstated_pass_components(
        tmp_path, 33, "dem_sigma_true_over_stated", "sigma_scale", "dem", n_tie_points=200, n_check_points=5, n_gcps=20
    )
    for name, used in (("stated", 1.0), ("scaled", 2.0)):
        c = vc[name]["dem"]
        assert 0.0 < c["stated_share"] < 1.0 and c["redundancy"] > 50, c
        k, amp = class_scale(used, c["sigma0"], c["stated_share"])
        assert abs(k - 2.0) < 3 * 2.0 * amp / np.sqrt(2 * c["redundancy"]), (name, k, amp, c)
    assert abs(vc["scaled"]["dem"]["sigma0"] - 1.0) < 0.2, vc


def test_the_pass_variance_components_learn_a_misstated_dem(tmp_path):
    """With the per-pass variance components on (the default), a pass whose DEM understates its
    sigma by half rescales its DEM factors until their component reads 1: the DEM scale it ends
    with (on the stated sigma) is near 2, and the noise fit's DEM level from that pass agrees."""
    from misrgraph.estimate.adjust import adjust_pass
    from misrgraph.estimate.noisefit import fit_noise_model
    from misrgraph.runs.noise import pass_levels_of
    from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

    cfg = dict(truth="model", scenario="pass", seed=33, duration_s=900.0, start_lat_deg=55.0, gcp_blunder_rate=0.0)
    run_simulate(
        ScenarioConfig(**cfg, n_tie_points=200, n_check_points=5, n_gcps=20, dem_sigma_true_over_stated=2.0),
        tmp_path / "s",
    )
    sc = load_scenario(tmp_path / "s")
    acfg = AdjustConfig.from_dict(attitude_jitter_arcsec=0.0, snooping_rounds=0)
    res = adjust_pass(sc.load_pass(0), sc.camera_model, sc.dem, sc.gcps, acfg)
    d = res.reliability["dem_sigma"]
    se = 2.0 / np.sqrt(2 * d["redundancy"])
    assert d["status"] == "learned" and abs(d["sigma_scale"] - 2.0) < 3 * se, d
    assert abs(d["sigma0"] - 1.0) < max(acfg.variance_component_tol, 3 * se / 2.0) + 1e-9, d
    fit = fit_noise_model([pass_levels_of(res, acfg.graph, "p")])
    lv = fit.levels["dem.sigma_scale"]
    assert abs(lv["value"] - 2.0) < 3 * se and lv["applied"] is True, lv
