"""misrgraph match on a reduced pass with imagery, scored against the simulator's truth, and the
adjustment of the matched observations against the same adjustment of the simulated ones."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from misrgraph.errors import FileFormatError, InputError
from misrgraph.estimate.adjust import AdjustConfig
from misrgraph.io.imagery import read_imagery, read_matched
from misrgraph.model.constants import CAMERAS
from misrgraph.runs.adjust import run_adjust
from misrgraph.runs.match import run_match
from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate


def test_matching_meets_the_seed_accuracies_with_honest_sigma(imagery_pass_dir):
    """GCPs to 1/8 px, tie points to 0.2 px (RMS per coordinate against truth), >= 80 % of the
    candidates matched, no wrong match (no clouds); error / reported sigma RMS in 0.7-1.4 for the
    GCPs and for each camera whose tie sigma the pass's redundancy scaled. A camera with too little
    redundancy (below the fit's 30) takes its twin's scale (the same view angle) when the twin has
    one, else keeps the LSM sigma (``misrgraph.match.precision``): the summary must say which, and
    that is what is checked there."""
    import inspect

    from misrgraph.match.precision import camera_sigma_scales

    min_redundancy = inspect.signature(camera_sigma_scales).parameters["min_redundancy"].default
    m = read_matched(load_scenario(imagery_pass_dir).pass_files[0])
    s = m.summary
    for kind, limit in (("gcp", 0.125), ("tie", 0.2)):
        v = s[kind]
        assert v["error_px"]["rms"] <= limit, (kind, v)
        assert v["matched"] >= 0.8 * v["candidates"], (kind, v)
        assert v["wrong_matches"] == 0, (kind, v)
    assert 0.7 <= s["gcp"]["normalised_error_rms"] <= 1.4, s["gcp"]
    scales = s["tie"]["sigma_scale"]
    estimated = [c for c, v in scales.items() if v["estimated"]]
    assert len(estimated) >= 6, scales  # the shared-attitude fit: all but the D cameras' one with fewest matches
    twin = {c: CAMERAS[len(CAMERAS) - 1 - i] for i, c in enumerate(CAMERAS)}
    for cam, v in scales.items():
        if v["estimated"]:
            assert 0.7 <= s["tie"]["per_camera"][cam]["normalised_error_rms"] <= 1.4, (cam, s["tie"]["per_camera"][cam])
        else:
            assert v["redundancy"] < min_redundancy, (cam, v)
            if scales[twin[cam]]["estimated"]:
                assert v["scale_from"] == twin[cam] and v["scale"] == scales[twin[cam]]["scale"], (cam, v)
            else:
                assert "scale_from" not in v and v["scale"] == 1.0, (cam, v)
    assert np.isnan(m.observations.exposure).all()  # continuous positions


def test_matched_adjustment_is_as_good_as_the_simulated_one(imagery_pass_dir):
    """adjust --observations matched: check points within 1.3x of the simulated-observation run,
    co-registration below 0.2 px in every camera. The matched tie points' shared height error is
    estimated by default (with its standard error), the simulated observations' is not."""
    sim = run_adjust(imagery_pass_dir)
    mat = run_adjust(imagery_pass_dir, observations="matched")
    assert mat["observation_set"] == "matched" and mat["solver_status"] == "converged"
    assert sim["tie_height"]["source"] == "off"
    th = mat["tie_height"]
    assert th["source"] == "estimated" and th["dem_factors"] > 10 and np.isfinite(th["standard_error_m2"]), th
    assert th["variance_m2"] == max(th["unclipped_variance_m2"], 0.0) and th["sigma_m"] ** 2 == pytest.approx(
        th["variance_m2"]
    )
    # without DEM factors nothing sees it: left out, and the summary says so
    no_dem = run_adjust(imagery_pass_dir, observations="matched", cfg=AdjustConfig.from_dict(use_dem=False))
    assert no_dem["tie_height"]["source"] == "off" and no_dem["tie_height"]["reason"] == "no DEM factors"
    assert any("shared height error was not estimated" in d for d in no_dem["diagnostics"])

    def pooled(s):
        v = s["checkpoint_geolocation_m"].values()
        return np.sqrt(np.mean([x["after"]["rms"] ** 2 for x in v]))

    assert pooled(mat) <= 1.3 * pooled(sim)
    assert max(mat["coregistration_px"].values()) < 0.2


def test_match_cli_json(imagery_pass_dir):
    r = subprocess.run(
        [sys.executable, "-m", "misrgraph.commands.cli", "match", str(imagery_pass_dir), "--json"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for kind in ("gcp", "tie"):
        assert {"candidates", "matched", "error_px", "normalised_error_rms", "seconds"} <= set(out[kind])


def test_match_cli_prints_each_cameras_tie_sigma_scale(imagery_pass_dir):
    """The human summary gives each camera's tie sigma scale with its redundancy, and says where a
    camera took its twin's scale or kept the LSM sigma, as the pass's matched summary records."""
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app

    r = CliRunner().invoke(app, ["match", str(imagery_pass_dir)])
    assert r.exit_code == 0, r.output
    scales = read_matched(load_scenario(imagery_pass_dir).pass_files[0]).summary["tie"]["sigma_scale"]
    line = next(ln for ln in r.stdout.splitlines() if "tie sigma scale" in ln)
    for cam, v in scales.items():
        tail = "" if v["estimated"] else (f", {v['scale_from']}'s" if "scale_from" in v else ", LSM sigma kept")
        assert f"{cam} {v['scale']:.2f} ({v['redundancy']:.0f}{tail})" in line, (cam, line)
    assert any(not v["estimated"] for v in scales.values())  # the short pass has one (Df, from Da)
    g = read_matched(load_scenario(imagery_pass_dir).pass_files[0]).summary["gcp"]["sigma_scale"]
    assert g["estimated"], g
    assert f"GCP sigma scale (redundancy): {g['scale']:.2f} ({g['redundancy']:.0f})" in r.stdout, r.stdout


def test_bad_windows_are_reported_per_feature(imagery_pass_dir, tmp_path):
    """NaN pixels in one window, a flat window: that feature's match fails with its reason; the rest
    match; nothing raises."""
    import shutil

    from misrgraph.io.h5 import atomic_h5
    from misrgraph.io.imagery import write_imagery
    from misrgraph.io.passes import OrbitPass
    from misrgraph.io.truth import read_pass_truth, write_pass_truth

    d = tmp_path / "bad"
    shutil.copytree(imagery_pass_dir, d)
    f = load_scenario(d).pass_files[0]
    p, t, im = OrbitPass.load(f), read_pass_truth(f), read_imagery(f)
    px = im.gcp.pixels.astype(np.uint16)
    px[0] = 4000  # a flat window
    im.gcp.pixels = px
    tie = im.tie.pixels
    tie[tie.shape[0] // 2] = 0  # an all-dark window
    with atomic_h5(f, "orbit_pass") as h:
        p.write_into(h)
        write_pass_truth(h, t, len(p.landmarks), len(p.observations))
        write_imagery(h, im)
    res = run_match(d)
    reasons = res["passes"][0]["gcp"]["rejected"]
    assert sum(reasons.values()) >= 1 and res["gcp"]["matched"] == res["gcp"]["candidates"] - sum(reasons.values())


def test_match_without_imagery_is_a_clear_error(small_pass_dir):
    with pytest.raises(FileFormatError, match="--imagery"):
        run_match(small_pass_dir)


def test_clouds_no_wrong_match_survives(tmp_path):
    """30 % cloud: wrong matches (more than 1 px from the truth) are rejected by matching or by the
    adjustment's blunder tests; none is left in the solution."""
    out = tmp_path / "cloudy"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="pass",
            seed=5,
            n_tie_points=60,
            n_check_points=5,
            duration_s=900.0,
            start_lat_deg=45.0,
            imagery=True,
            cloud_fraction=0.3,
        ),
        out,
    )
    res = run_match(out)
    s = run_adjust(out, observations="matched")
    wrong = res["tie"]["wrong_matches"] + res["gcp"]["wrong_matches"]
    assert wrong > 0  # the clouds did fool the matcher: the test exercises the adjustment's side
    b = s["blunders"]
    assert b["injected"] == wrong and b["left_in_solution"] == 0, b
    assert res["passes"][0]["tie"]["rejected"].get("cloud (bright template)", 0) > 0


def test_info_shows_imagery_and_matched(imagery_pass_dir):
    from misrgraph.io.info import run_info

    f = load_scenario(imagery_pass_dir).pass_files[0]
    out = run_info(f)
    im = read_imagery(f)
    assert (
        out["imagery"]["tie_windows"] == len(im.tie) > 0 and out["imagery"]["gcp_chips"] == im.chip_landmark.size
    )  # red only
    assert out["imagery"]["gcp_window_bands"] == ["red"]
    assert out["matched"]["observations"] == len(read_matched(f).observations) > 0


@pytest.fixture(scope="module")
def dense_imagery_dir(tmp_path_factory):
    """A 25-minute pass with 250 tie points: enough redundancy in every camera (the D cameras see
    An's features of the middle 11 minutes only) to measure its precision."""
    out = tmp_path_factory.mktemp("scen") / "dense"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="pass",
            seed=8,
            n_tie_points=250,
            n_check_points=5,
            duration_s=1500.0,
            start_lat_deg=55.0,
            imagery=True,
        ),
        out,
    )
    return out


@pytest.mark.slow
def test_sigma_from_redundancy_makes_the_d_cameras_honest(dense_imagery_dir):
    """The LSM sigma alone is optimistic where the view angle changes the pattern most (the D
    cameras); scaled by each camera's precision from the pass's redundancy it is honest there:
    error / sigma RMS in 0.7-1.4 per D camera and pooled over the correct matches (truth never
    enters the scale). Wrong matches (> 1 px: ~1 % here, which ones depends on the last count of
    a pixel) are the blunder test's to reject; one among 60 doubles the RMS over all matches."""
    from misrgraph.match.pipeline import MatchConfig

    plain = run_match(dense_imagery_dir, MatchConfig(sigma_from_redundancy=False))["passes"][0]["tie"]
    scaled = run_match(dense_imagery_dir)["passes"][0]["tie"]
    assert all(v["estimated"] for v in scaled["sigma_scale"].values()), scaled["sigma_scale"]
    for cam in ("Df", "Da"):
        assert plain["per_camera"][cam]["normalised_error_rms_correct"] > 1.4  # what the LSM sigma alone gives
        assert 0.7 <= scaled["per_camera"][cam]["normalised_error_rms_correct"] <= 1.4, scaled["per_camera"][cam]
        assert scaled["sigma_scale"][cam]["scale"] > 1.2
    assert 0.7 <= scaled["normalised_error_rms_correct"] <= 1.4
    # a sanity bound on the matcher, not a model figure: measured 14 of 1305 (1.1 %)
    assert scaled["wrong_matches"] <= 0.03 * scaled["matched"], (scaled["wrong_matches"], scaled["matched"])
    assert scaled["normalised_error_rms"] >= scaled["normalised_error_rms_correct"]


@pytest.mark.slow
def test_a_month_calibrates_from_gcps_matched_in_its_imagery(matched_month_dir):
    """A reduced month with imagery (GCP windows and chips in every GCP pass): the GCPs matched
    in it to 1/8 px with no wrong match, and ``calibrate --observations matched`` recovers every
    camera within 3 sigma of the truth and better than the supplied model, as the calibration of
    the simulated observations does."""
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.runs.calibrate import run_calibrate

    out, s, res = matched_month_dir
    g = res["gcp"]
    assert len(res["passes"]) == s["passes"] > 1 and res["tie"]["candidates"] == 0
    assert g["error_px"]["rms"] <= 0.125 and g["matched"] >= 0.8 * g["candidates"] and g["wrong_matches"] == 0, g
    sim = run_calibrate(out)
    r = CliRunner().invoke(app, ["calibrate", str(out), "--observations", "matched", "--json"])
    assert r.exit_code == 0, r.output
    mat = json.loads(r.stdout)
    assert mat["observation_set"] == "matched" and sim["observation_set"] == "simulated"
    assert mat["passes"] == sim["passes"]
    for cam, v in mat["cameras"].items():
        assert v["pointing_error_px"] < 3 * v["sigma_px"], (cam, v["pointing_error_px"], v["sigma_px"])
        assert v["pointing_error_px"] < v["pointing_error_before_px"], cam
    # as good as the simulated observations (the criterion the matched adjustment meets, above)
    assert mat["max_pointing_error_px"] <= 1.3 * sim["max_pointing_error_px"], (
        mat["max_pointing_error_px"],
        sim["max_pointing_error_px"],
    )


@pytest.mark.slow
def test_gcps_matched_in_two_bands_calibrate_each_band(tmp_path):
    """A short month observed in red and NIR, whose true bands are misaligned by 10" (1 sigma per
    angle, ~0.1-0.2 px): GCP windows and chips are rendered in both bands, matched in each to
    1/8 px with no wrong match, and ``calibrate --observations matched --per-band`` puts every
    band of every camera within 3 sigma of the truth and better than the supplied model."""
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.model.constants import BANDS

    out = tmp_path / "month2"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="month",
            seed=1,
            n_gcps=20,
            month_days=3,
            imagery=True,
            bands=("red", "nir"),
            band_misalignment_arcsec=10.0,
        ),
        out,
    )
    im = read_imagery(load_scenario(out).pass_files[0])
    assert set(im.gcp.band.tolist()) == {BANDS.index("red"), BANDS.index("nir")}
    assert set(im.chip_index()) == {(int(r), int(b)) for r, b in zip(im.gcp.landmark, im.gcp.band)}
    g = run_match(out)["gcp"]
    assert set(g["per_band"]) == {"red", "nir"}
    for band, v in g["per_band"].items():
        assert v["error_px"]["rms"] <= 0.125 and v["wrong_matches"] == 0, (band, v)
    assert g["matched"] >= 0.8 * g["candidates"], g
    r = CliRunner().invoke(app, ["calibrate", str(out), "--observations", "matched", "--per-band", "--json"])
    assert r.exit_code == 0, r.output
    cal = json.loads(r.stdout)
    for cam, v in cal["cameras"].items():
        assert {p.split(".")[0] for p in v["params"]} == {"red", "nir"}, cam
        assert v["pointing_error_px"] < 3 * v["sigma_px"], (cam, v["pointing_error_px"], v["sigma_px"])
        assert v["pointing_error_px"] < v["pointing_error_before_px"], cam


def test_calibrate_refuses_matched_observations_without_matching(small_pass_dir):
    from misrgraph.errors import MisrGraphError
    from misrgraph.runs.calibrate import run_calibrate

    with pytest.raises(MisrGraphError, match="matched|imagery"):
        run_calibrate(small_pass_dir, observations="matched")


def test_the_search_range_defaults_to_the_windows_own(tmp_path):
    """Windows rendered for a 12 px search are searched over 12 px unless told otherwise; a
    search range below 1 px is refused."""
    from misrgraph.match.pipeline import MatchConfig

    out = tmp_path / "wide"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="pass",
            seed=4,
            n_tie_points=12,
            n_check_points=2,
            duration_s=300.0,
            start_lat_deg=45.0,
            imagery=True,
            search_px=12,
        ),
        out,
    )
    assert read_imagery(load_scenario(out).pass_files[0]).gcp.pixels.shape[-1] == 64 + 2 * 12
    wide = run_match(out)["passes"][0]
    narrow = run_match(out, MatchConfig(search_px=8))["passes"][0]
    assert wide["search_px"] == 12 and narrow["search_px"] == 8
    assert wide["gcp"]["matched"] + wide["tie"]["matched"] > 0
    with pytest.raises(InputError, match="search_px"):
        MatchConfig(search_px=0)


def test_an_sigma_from_the_conjugates_shared_offset(imagery_pass_dir, tmp_path):
    """``an_sigma="shared-offset"``: the precision fit also models the offset all conjugates of a
    feature share and reports its sigma (``tie.shared_offset``); every An observation takes it
    (at least the sigma floor), and the conjugates' pooled scale, no longer counting it, is not
    larger than the default fit's (within its standard error). A value outside the two is refused
    by name."""
    import shutil

    from misrgraph.io.passes import KIND_TIE
    from misrgraph.match.pipeline import AN, MatchConfig

    out = tmp_path / "imagery"
    shutil.copytree(imagery_pass_dir, out)
    cfg = MatchConfig(an_sigma="shared-offset")
    s = run_match(out, cfg)["passes"][0]["tie"]
    so = s["shared_offset"]
    assert so["estimated"] and so["sigma_px"] > 0, so
    m = read_matched(load_scenario(out).pass_files[0])
    obs = m.observations
    an = obs.sigma_px[(obs.camera == AN) & (m.landmarks.kind[obs.landmark] == KIND_TIE)]  # An's GCP views keep theirs
    assert an.size > 0 and np.allclose(an, max(so["sigma_px"], cfg.sigma_floor_px))
    dm = read_matched(load_scenario(imagery_pass_dir).pass_files[0])
    default = dm.summary["tie"]
    # the default measures the same offset by a second fit (for the adjustment's tie covariance)
    # and keeps giving An its conjugates' median sigma
    assert default["shared_offset"]["sigma_px"] == pytest.approx(so["sigma_px"], rel=1e-9)
    o, kind = dm.observations, dm.landmarks.kind
    for lm in np.unique(o.landmark[(o.camera == AN) & (kind[o.landmark] == KIND_TIE)])[:10]:
        mine = o.landmark == lm
        assert o.sigma_px[mine & (o.camera == AN)][0] == pytest.approx(np.median(o.sigma_px[mine & (o.camera != AN)]))

    def pooled(scales):  # over the estimated cameras, weighted by redundancy; its standard error
        est = [v for v in scales.values() if v["estimated"]]
        r = sum(v["redundancy"] for v in est)
        return np.sqrt(sum(v["scale"] ** 2 * v["redundancy"] for v in est) / r), 1.0 / np.sqrt(2.0 * r)

    (k_off, _), (k_def, se) = pooled(s["sigma_scale"]), pooled(default["sigma_scale"])
    assert k_off <= k_def * (1.0 + se), (k_off, k_def, se)
    with pytest.raises(InputError, match="an_sigma"):
        MatchConfig(an_sigma="mean")
