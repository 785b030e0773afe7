from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import DIGEST_ATTR, atomic_h5, reseal, stamp_content_digest
from misrgraph.io.passes import KIND_CHECK, KIND_GCP, KIND_TIE, OrbitPass
from misrgraph.model.constants import ARCSEC, CAMERAS
from misrgraph.model.frames import ecef_to_geodetic
from misrgraph.sim.simulate import (
    ScenarioConfig,
    draw_attitude_error,
    draw_ephemeris_error,
    load_scenario,
    run_simulate,
)


def test_config_rejects_unknown_and_bad_values():
    with pytest.raises(InputError, match="ScenarioConfig.tie_sigma"):
        ScenarioConfig.from_dict({"tie_sigma": 0.2})
    with pytest.raises(InputError, match="scenario"):
        ScenarioConfig(truth="model", scenario="week")
    with pytest.raises(InputError, match="gcp_blunder_rate"):
        ScenarioConfig(truth="model", gcp_blunder_rate=1.5)


def test_noise_free_observations_reproject_exactly(tmp_path):
    out = tmp_path / "nf"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="pass",
            seed=2,
            n_tie_points=60,
            n_check_points=5,
            duration_s=900.0,
            start_lat_deg=55.0,
            noise_free=True,
        ),
        out,
    )
    sc = load_scenario(out)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    o = p.observations
    geo = tp.geometry(p, sc.camera_truth)
    truth = tp.landmark_ecef[o.landmark]
    h = ecef_to_geodetic(truth)[2]
    g = geo.pixel_to_ground(o.camera, o.band, o.line, o.sample, height=h, exposure=o.exposure)
    assert np.max(np.linalg.norm(g - truth, axis=1)) < 1e-4
    assert not tp.blunder.any()


def test_observation_noise_matches_sigma(small_pass):
    sc, p = small_pass
    tp = sc.load_truth(0)
    o = p.observations
    geo = tp.geometry(p, sc.camera_truth)
    truth = tp.landmark_ecef
    resid_l, resid_s, sig = [], [], []
    for c in range(len(CAMERAS)):
        m = (o.camera == c) & ~tp.blunder
        ln, sm, vis, ex, _ = geo.ground_to_pixel(c, 2, truth[o.landmark[m]], continuous=True)
        assert o.continuous[m].all()  # the simulator writes what a matcher measures
        resid_l.append(o.line[m] - ln)
        resid_s.append(o.sample[m] - sm)
        sig.append(o.sigma_px[m])
    z = np.concatenate(resid_l + resid_s) / np.concatenate(sig + sig)
    k = z.size
    assert abs(np.sum(z**2) - k) < 4 * np.sqrt(2 * k)
    assert abs(np.mean(z)) < 4 / np.sqrt(k)


def test_pass_contents(small_pass):
    sc, p = small_pass
    tp = sc.load_truth(0)
    kinds = np.bincount(p.landmarks.kind, minlength=3)
    assert kinds[KIND_TIE] == 150 or kinds[KIND_TIE] > 120  # a few may be seen by < 3 cameras
    assert kinds[KIND_CHECK] > 0
    # every tie point is seen in at least three cameras
    counts = np.bincount(p.observations.landmark, minlength=len(p.landmarks))
    assert np.all(counts[p.landmarks.kind == KIND_TIE] >= 3)
    # tie points are on land, on the true terrain
    lat, lon, h = ecef_to_geodetic(tp.landmark_ecef)
    from misrgraph.sim.simulate import scenario_terrain
    from misrgraph.sim.terrain import SyntheticTerrain, land_mask

    assert land_mask(lat, lon).all()
    # the scenario records its world: seed 11 with the default coast ramp
    cfg = sc.config["config"]
    assert cfg["coast_ramp_m"] == 8000.0
    np.testing.assert_allclose(
        h[p.landmarks.kind == KIND_TIE],
        SyntheticTerrain(seed=11, coast_ramp_m=8000.0).height(lat, lon)[p.landmarks.kind == KIND_TIE],
        atol=1e-3,
    )
    assert scenario_terrain(cfg) == SyntheticTerrain(seed=11, coast_ramp_m=8000.0)
    old = {k: v for k, v in cfg.items() if k != "coast_ramp_m"}  # a scenario from before the ramp
    assert scenario_terrain(old).coast_ramp_m == 0.0
    # blunders: configured rate 2 % on tie points
    tie_obs = p.landmarks.kind[p.observations.landmark] == KIND_TIE
    rate = tp.blunder[tie_obs].mean()
    n = tie_obs.sum()
    assert abs(rate - 0.02) < 4 * np.sqrt(0.02 * 0.98 / n)


def test_truth_draw_statistics():
    cfg = ScenarioConfig(truth="model")
    rng = np.random.default_rng(0)
    n = 400
    p = np.stack([draw_ephemeris_error(rng, cfg, 0.0, 2700.0).params[0] for _ in range(n)])
    sig = np.array([0.05, 0.01, 0.01, 50, 50, 50])
    chi2 = np.sum((p / sig) ** 2, axis=0)
    assert np.all(np.abs(chi2 - n) < 4 * np.sqrt(2 * n))
    vals = [[], [], []]
    for _ in range(150):
        m = draw_attitude_error(rng, cfg, 0.0, 2700.0)
        for a in range(3):
            vals[a].append(m.knots[a][:, 0])
    for a in range(3):
        v = np.concatenate(vals[a]) / (cfg.attitude_sigma_arcsec[a] * ARCSEC)
        # knots within a draw are correlated; 150 independent draws -> ~5 % tolerance is 4 sigma
        assert abs(np.std(v) - 1.0) < 0.15


def test_month_scenario_gcps_seen_three_times(tmp_path):
    out = tmp_path / "month"
    s = run_simulate(ScenarioConfig(truth="model", scenario="month", seed=3, n_gcps=24, month_days=30), out)
    assert s["gcps_seen"] >= 22
    assert s["gcps_seen_in_3_or_more_passes"] >= 0.85 * s["gcps_seen"]
    sc = load_scenario(out)
    p = sc.load_pass(0)
    assert np.all(p.landmarks.kind == KIND_GCP)
    # the supplied model is the nominal one; the truth is misaligned by tens of arcsec
    d = np.abs(sc.camera_truth.beta - sc.camera_model.beta) / ARCSEC
    assert 5 < np.median(d) < 200


# ------------------------------------------------------------------------ file robustness
def test_corrupt_truncated_wrong_version_and_missing_fields(small_pass_dir, tmp_path):
    src = sorted((small_pass_dir / "passes").glob("*.h5"))[0]
    data = src.read_bytes()
    (tmp_path / "trunc.h5").write_bytes(data[: len(data) // 3])
    with pytest.raises(FileFormatError, match="file checksum mismatch"):
        OrbitPass.load(tmp_path / "trunc.h5")
    (tmp_path / "junk.h5").write_bytes(b"\x00" * 1000)
    with pytest.raises(FileFormatError, match="no misrgraph checksum block"):
        OrbitPass.load(tmp_path / "junk.h5")
    import shutil

    for case in ("version", "missing_group", "missing_ds", "bad_shape", "edited", "no_digest", "raw_edit"):
        f = tmp_path / f"{case}.h5"
        shutil.copy(src, f)
        with h5py.File(f, "a") as h:
            if case == "version":
                h.attrs["format_version"] = 99
            elif case == "missing_group":
                del h["timing"]
            elif case in ("missing_ds", "edited", "raw_edit"):
                del h["observations/sample"]
            elif case == "no_digest":
                del h.attrs[DIGEST_ATTR]
            else:
                del h["timing/t0"]
                h["timing/t0"] = np.zeros((9, 3))
            if case in ("missing_group", "missing_ds", "bad_shape"):
                # a well-formed file (valid digest) from a writer that got the layout wrong
                stamp_content_digest(h)
        if case != "raw_edit":
            reseal(f)  # past the whole-file checksum, to reach the check under test
        pattern = {
            "version": "format_version is 99",
            "missing_group": "missing group /timing",
            "missing_ds": "missing dataset /observations/sample",
            "bad_shape": r"t0 has shape \(9, 3\)",
            "edited": "content digest mismatch",
            "no_digest": "no content_sha256",
            "raw_edit": "file checksum mismatch",
        }[case]
        with pytest.raises(FileFormatError, match=pattern):
            OrbitPass.load(f)


def test_zeroed_bytes_in_a_pass_file_are_refused(small_pass_dir, tmp_path):
    """The reported case: 4000 zero bytes in the middle of a pass file. Refused on read with one
    error naming the file (a checksum or the content digest), never a silent result."""
    src = sorted((small_pass_dir / "passes").glob("*.h5"))[0]
    data = bytearray(src.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 4000] = bytes(4000)
    bad = tmp_path / "zeroed.h5"
    bad.write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="zeroed.h5"):
        OrbitPass.load(bad)


def test_files_are_written_with_checksums_and_the_umask_mode(tmp_path):
    import os

    old = os.umask(0o027)
    try:
        with atomic_h5(tmp_path / "x.h5", "dem") as f:
            f.create_group("g")
            from misrgraph.io.h5 import write_dataset

            write_dataset(f["g"], "a", np.arange(10.0))
    finally:
        os.umask(old)
    assert (os.stat(tmp_path / "x.h5").st_mode & 0o777) == 0o640
    with h5py.File(tmp_path / "x.h5", "r") as h:
        assert h["g/a"].fletcher32 and len(h.attrs[DIGEST_ATTR]) == 64


def test_crash_during_write_leaves_no_file(tmp_path):
    target = tmp_path / "x.h5"
    with pytest.raises(RuntimeError):
        with atomic_h5(target, "dem") as f:
            f.create_dataset("a", data=np.arange(10))
            raise RuntimeError("simulated crash")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []


def test_crash_during_simulation_leaves_no_directory(tmp_path, monkeypatch):
    import misrgraph.sim.simulate as sim

    def boom(*a, **k):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(sim, "simulate_dem_tiles", boom)
    with pytest.raises(RuntimeError):
        run_simulate(
            ScenarioConfig(
                truth="model", scenario="pass", n_tie_points=5, n_check_points=0, duration_s=300.0, start_lat_deg=45.0
            ),
            tmp_path / "out",
        )
    assert list(tmp_path.iterdir()) == []


def test_scenario_directory_validation(tmp_path):
    with pytest.raises(FileFormatError, match="scenario.json"):
        load_scenario(tmp_path)
    (tmp_path / "scenario.json").write_text("{not json")
    with pytest.raises(FileFormatError, match="invalid JSON"):
        load_scenario(tmp_path)


def test_refuses_to_overwrite_foreign_directory(tmp_path):
    (tmp_path / "precious.txt").write_text("data")
    with pytest.raises(InputError, match="--out"):
        run_simulate(ScenarioConfig(truth="model", n_tie_points=5), tmp_path)
    assert (tmp_path / "precious.txt").read_text() == "data"
    assert not (tmp_path / "scenario.json").exists() and json.loads("{}") == {}


def test_replacing_a_scenario_keeps_user_files_and_leaves_no_debris(tmp_path):
    """A scenario directory is replaced only if it holds nothing but what simulate writes; the
    replacement swaps directories (the old one is deleted after the new one is in place)."""
    cfg = ScenarioConfig(
        truth="model", scenario="pass", n_tie_points=5, n_check_points=0, duration_s=300.0, start_lat_deg=45.0
    )
    out = tmp_path / "scen"
    run_simulate(cfg, out)
    first = (out / "scenario.json").read_text()
    (out / "my_notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="my_notes.txt"):
        run_simulate(dataclasses.replace(cfg, seed=cfg.seed + 1), out)
    assert (out / "my_notes.txt").read_text() == "keep me" and (out / "scenario.json").read_text() == first
    (out / "my_notes.txt").unlink()
    run_simulate(dataclasses.replace(cfg, seed=cfg.seed + 1), out)
    assert json.loads((out / "scenario.json").read_text())["config"]["seed"] == cfg.seed + 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scen"]  # no temporary or old directories left
    load_scenario(out)


def test_independent_truth_settings_are_checked():
    for field, value in (
        ("noise_tail_dof", 2.0),
        ("mismatch_rate", 1.5),
        ("mismatch_px", (2.0, 1.0)),
        ("dem_correlated_fraction", -0.1),
        ("subposting_relief_m", -1.0),
    ):
        with pytest.raises(InputError, match=field):
            ScenarioConfig(**{field: value})


def test_student_t_matching_noise_has_unit_variance_and_heavier_tails():
    from scipy import stats

    from misrgraph.sim.simulate import matching_noise

    n = 200_000
    x = matching_noise(np.random.default_rng(5), n, 5.0)
    # the sample variance of t5 has a large spread (kurtosis 9): 4 standard errors
    assert abs(x.var() - 1.0) < 4 * np.sqrt((9.0 - 1.0) / n)
    assert stats.kurtosis(x, fisher=False) > 4.0  # Gaussian: 3
    g = matching_noise(np.random.default_rng(5), n, 0.0)
    assert abs(stats.kurtosis(g, fisher=False) - 3.0) < 0.1


def test_sub_posting_relief_has_its_rms_and_is_finer_than_the_dem():
    from misrgraph.sim.terrain import SyntheticTerrain

    rng = np.random.default_rng(1)
    lat, lon = rng.uniform(-60, 60, 4000), rng.uniform(-180, 180, 4000)
    d = SyntheticTerrain(seed=4, fine_relief_m=3.0).relief(lat, lon) - SyntheticTerrain(seed=4).relief(lat, lon)
    assert abs(np.sqrt(np.mean((d - d.mean()) ** 2)) - 3.0) < 0.3
    # 45 m away (half a 3" posting) the fine relief is nearly independent of itself
    d2 = SyntheticTerrain(seed=4, fine_relief_m=3.0).relief(lat + 45 / 111e3, lon) - SyntheticTerrain(seed=4).relief(
        lat + 45 / 111e3, lon
    )
    assert abs(np.corrcoef(d, d2)[0, 1]) < 0.6


def test_scene_correlated_gcp_errors():
    """Half the variance shared by the GCPs of a 2 x 2 deg cell: pairs in one cell correlate at
    ~0.5 per axis, the per-axis RMS stays the stated sigma."""
    from misrgraph.model.frames import ecef_to_geodetic, enu_basis
    from misrgraph.sim.gcps import generate_gcp_database
    from misrgraph.sim.terrain import SyntheticTerrain

    db, truth = generate_gcp_database(
        np.random.default_rng(3), SyntheticTerrain(seed=3), 1500, 30.0, scene_fraction=0.5
    )
    lat, lon, _ = ecef_to_geodetic(truth)
    e = np.einsum("gji,gj->gi", enu_basis(lat, lon), db.ecef() - truth)
    assert abs(np.sqrt(np.mean(e**2)) - 30.0) < 3.0
    cell = np.floor(lat / 2).astype(int) * 1000 + np.floor(lon / 2).astype(int)
    a, b = [], []
    for c in np.unique(cell):
        i = np.flatnonzero(cell == c)
        if i.size >= 2:
            a.append(e[i[0], 0])
            b.append(e[i[1], 0])
    assert len(a) > 50
    assert 0.3 < np.corrcoef(a, b)[0, 1] < 0.7


def test_focal_plane_perturbation_moves_the_swath_edge_by_its_sigma(nominal_camera):
    """alpha_2 and alpha_3 each move the edge pixel (s - c_y = 752) by N(0, px) pixels of
    cross-track angle: the RMS over many draws is px * sqrt(2)."""
    from misrgraph.sim.simulate import perturb_focal_plane

    rng = np.random.default_rng(9)
    shifts = []
    for _ in range(60):
        m = perturb_focal_plane(rng, nominal_camera, 0.05)
        y0 = (
            nominal_camera.focal_plane_y(np.arange(9), np.full(9, 2), nominal_camera.cy[:, 2] + 752.0)
            / nominal_camera.focal_length[:, 2]
        )
        y1 = m.focal_plane_y(np.arange(9), np.full(9, 2), nominal_camera.cy[:, 2] + 752.0) / m.focal_length[:, 2]
        shifts.append((y1 - y0) / nominal_camera.alpha[:, 2, 1])
    rms = np.sqrt(np.mean(np.square(shifts)))
    assert abs(rms - 0.05 * np.sqrt(2)) < 0.15 * 0.05 * np.sqrt(2)


def test_model_truth_supplies_alpha_off_by_the_adjustments_prior(small_pass):
    """Under the model truth the supplied camera's alpha_2, alpha_3 differ from the truth's by
    the pass adjustment's own prior (camera_focal_prior_px at the swath edge), the same for every
    band, and f is exact: the normalised differences over the 9 cameras are 18 unit normals
    (chi-square band at 99.9 %)."""
    from scipy.stats import chi2

    from misrgraph.estimate.graph import GraphConfig

    sc, _ = small_pass
    sup, tru = sc.camera_model, sc.camera_truth
    np.testing.assert_array_equal(sup.focal_length, tru.focal_length)
    d = sup.alpha[:, :, 2:4] - tru.alpha[:, :, 2:4]
    np.testing.assert_allclose(d, d[:, :1, :].repeat(d.shape[1], axis=1), rtol=1e-9, atol=0)
    px = GraphConfig().camera_focal_prior_px
    z = d[:, 0, :] * (752.0 ** np.array([2, 3])) / (px * tru.alpha[:, 0, 1:2])
    assert chi2.ppf(0.0005, z.size) < np.sum(z**2) < chi2.ppf(0.9995, z.size)


def test_measurements_moved_outside_the_pass_are_not_made(tmp_path):
    """Noise, blunders and mismatches can move a point near the pass's ends before its first or
    after its last line; a matcher cannot measure there, so the simulator drops those
    measurements instead of writing a pass file that fails its own check (seen at standard
    size: a mismatch put a line at -0.56). Large blunders at a high rate make it certain here."""
    out = tmp_path / "edge"
    cfg = ScenarioConfig(
        truth="model",
        scenario="pass",
        seed=4,
        n_tie_points=60,
        n_check_points=5,
        duration_s=600.0,
        start_lat_deg=50.0,
        tie_blunder_rate=0.5,
        blunder_min_px=200.0,
        blunder_max_px=400.0,
    )
    run_simulate(cfg, out)
    sc = load_scenario(out)
    p, tp = sc.load_pass(0), sc.load_truth(0)
    t = p.observation_times()
    lo, hi = p.span
    assert lo <= t.min() and t.max() <= hi
    assert tp.blunder.size == len(p.observations) and tp.blunder.sum() > 100  # the truth stays aligned
    # the same scenario without blunders keeps every measurement it makes (nothing else moves)
    clean = tmp_path / "clean"
    run_simulate(dataclasses.replace(cfg, tie_blunder_rate=0.0), clean)
    assert len(load_scenario(clean).load_pass(0).observations) > len(p.observations)


def test_cli_refuses_a_negative_coast_ramp(tmp_path):
    """``simulate --coast-ramp-m -5``: a clear error naming the field and the expected value, and
    no scenario directory left behind."""
    import subprocess
    import sys

    out = tmp_path / "scen"
    r = subprocess.run(
        [sys.executable, "-m", "misrgraph", "simulate", "--coast-ramp-m", "-5", "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert r.returncode != 0
    assert "coast_ramp_m" in r.stderr and "-5.0" in r.stderr and ">= 0" in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


def test_simulate_draws_the_independent_truth_unless_told(tmp_path):
    """``misrgraph simulate`` and ``ScenarioConfig`` without a truth draw the independent one (the
    attitude truth on its own 2 s grid, not on the estimator's 60 s knots); ``--truth model``
    draws the estimator's own."""
    from typer.testing import CliRunner

    from misrgraph.commands.cli import app
    from misrgraph.sim.simulate import load_scenario

    args = ["simulate", "--scenario", "pass", "--tie-points", "5", "--check-points", "0", "--duration", "300"]
    spacing = {}
    for name, extra in (("default", []), ("model", ["--truth", "model"])):
        r = CliRunner().invoke(app, [*args, *extra, "--out", str(tmp_path / name)])
        assert r.exit_code == 0, r.output
        spacing[name] = float(
            np.median(np.diff(load_scenario(tmp_path / name).load_truth(0).attitude_error.knot_times[1]))
        )
    assert spacing == {"default": 2.0, "model": 60.0}
    assert json.loads((tmp_path / "default" / "scenario.json").read_text())["config"]["truth"] == "independent"


def test_paired_sources_leave_every_other_draw_unchanged(tmp_path, monkeypatch):
    """PAIRED_SOURCES is exactly the set of independent-truth sources whose switch-off leaves the
    scenario's main generator where the scenario with every source on leaves it (the same draws,
    in the same order); the others shift it, so this check can tell them apart."""
    import misrgraph.sim.simulate as simulate

    finals: list[np.random.Generator] = []
    make = simulate._scenario_rng

    def recording(seed):
        g = make(seed)
        finals.append(g)
        return g

    monkeypatch.setattr(simulate, "_scenario_rng", recording)

    def final_state(**extra):
        cfg = ScenarioConfig(
            scenario="pass",
            truth="independent",
            seed=21,
            n_tie_points=25,
            n_check_points=3,
            n_gcps=20,
            duration_s=300.0,
            start_lat_deg=50.0,
            **extra,
        )
        run_simulate(cfg, tmp_path / f"s{len(finals)}")
        return finals[-1].bit_generator.state["state"]

    everything = final_state()
    assert final_state() == everything  # the check itself is deterministic
    moves_nothing = {k for k, off in simulate.INDEPENDENT_SOURCES.items() if final_state(**{k: off}) == everything}
    assert moves_nothing == simulate.PAIRED_SOURCES


def test_files_that_misstate_their_accuracy(tmp_path):
    """Each misstatement knob draws its error with that many times the sigma its file states:
    against the noise-free observations of the same seed (the truth), the tie-point and GCP image
    errors scale by their factors exactly, the GCP catalogue's error likewise, the DEM's error
    field is drawn again at the factor's size, and every stated sigma stays as it was."""
    from misrgraph.model.dem import QUALITY_SIGMA_M
    from misrgraph.model.frames import geodetic_to_ecef
    from misrgraph.sim.simulate import KIND_CHECK, KIND_GCP, KIND_TIE, ScenarioConfig, load_scenario, run_simulate

    base = dict(
        truth="model",
        scenario="pass",
        seed=21,
        n_tie_points=40,
        n_check_points=10,
        n_gcps=20,
        duration_s=600.0,
        start_lat_deg=50.0,
        gcp_blunder_rate=0.0,
        tie_blunder_rate=0.0,
    )
    knobs = dict(
        tie_sigma_true_over_stated=2.5,
        gcp_pixel_sigma_true_over_stated=0.5,
        gcp_sigma_true_over_stated=3.0,
        dem_sigma_true_over_stated=2.0,
    )
    sc = {}
    for name, extra in (("stated", {}), ("misstated", knobs), ("truth", {"noise_free": True})):
        run_simulate(ScenarioConfig.from_dict({**base, **extra}), tmp_path / name)
        sc[name] = load_scenario(tmp_path / name)
    p = {k: v.load_pass(0) for k, v in sc.items()}
    o1, o2, o0 = p["stated"].observations, p["misstated"].observations, p["truth"].observations
    assert np.array_equal(o1.landmark, o2.landmark) and np.array_equal(o1.landmark, o0.landmark)
    np.testing.assert_array_equal(o1.sigma_px, o2.sigma_px)  # what the file states is unchanged
    kind = p["stated"].landmarks.kind[o1.landmark]
    for k, f in ((KIND_TIE, 2.5), (KIND_GCP, 0.5), (KIND_CHECK, 1.0)):
        m = kind == k
        assert m.sum() > 5
        for c in ("line", "sample"):
            e1, e2 = getattr(o1, c)[m] - getattr(o0, c)[m], getattr(o2, c)[m] - getattr(o0, c)[m]
            assert np.abs(e1).max() > 1e-3
            np.testing.assert_allclose(e2, f * e1, atol=1e-9)
    g1, g2, truth = sc["stated"].gcps, sc["misstated"].gcps, sc["stated"].gcp_truth()
    np.testing.assert_array_equal(g1.sigma_m, g2.sigma_m)
    d1 = geodetic_to_ecef(g1.lat, g1.lon, g1.height) - truth
    d2 = geodetic_to_ecef(g2.lat, g2.lon, g2.height) - truth
    np.testing.assert_allclose(d2, 3.0 * d1, atol=1e-3)
    dem1, dem2 = sc["stated"].dem, sc["misstated"].dem
    np.testing.assert_array_equal(dem1.quality, dem2.quality)
    # the same draw at twice its size: the difference is one stated-sigma draw of the error field
    sig_q = np.vectorize(QUALITY_SIGMA_M.get)(dem1.quality)[:, None, None]
    z = (dem2.heights - dem1.heights) / sig_q
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.5
    with pytest.raises(InputError, match="dem_sigma_true_over_stated"):
        ScenarioConfig(dem_sigma_true_over_stated=20.0)


def test_the_attitude_spectrum_is_a_knob_of_the_world(tmp_path):
    """The independent truth's attitude follows the band, slope and lines it is given: the ratio of
    the rate's RMS to the value's lies between the band's angular frequencies (a weighted mean of
    the terms' frequencies), and a discrete line stands out at its period in the spectrum."""
    from misrgraph.model.constants import ARCSEC
    from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

    base = dict(
        truth="independent",
        scenario="pass",
        seed=5,
        n_tie_points=20,
        n_check_points=5,
        n_gcps=20,
        duration_s=1200.0,
        jitter_arcsec=0.0,
    )
    worlds = {
        "default": {},
        "fast": {"attitude_periods_s": [30.0, 300.0], "attitude_spectral_slope": 1.0},
        "line": {"attitude_lines": [[50.0, 20.0]]},
    }
    truth = {}
    for name, extra in worlds.items():
        run_simulate(ScenarioConfig.from_dict({**base, **extra}), tmp_path / name)
        truth[name] = load_scenario(tmp_path / name).load_truth(0).attitude_error
    for name, band in (("default", (200.0, 2000.0)), ("fast", (30.0, 300.0))):
        for a in range(3):
            v = truth[name].knots[a]
            ratio = np.sqrt(np.mean(v[:, 1] ** 2) / np.mean(v[:, 0] ** 2))
            assert 2 * np.pi / band[1] * 0.8 < ratio < 2 * np.pi / band[0] * 1.2, (name, a, ratio)
    v = truth["line"].knots[0][:, 0] / ARCSEC  # roll on its 2 s grid
    spec = np.abs(np.fft.rfft(v - v.mean()))
    f = np.fft.rfftfreq(v.size, 2.0)
    at = np.argmin(np.abs(f - 1 / 50.0))
    assert spec[at] > 10 * np.median(spec[f > 1 / 150.0])
    with pytest.raises(InputError, match="attitude_periods_s"):
        ScenarioConfig(attitude_periods_s=(300.0, 30.0))
    with pytest.raises(InputError, match="jitter_lines"):
        ScenarioConfig(jitter_lines=((10.0,),))


def test_a_camera_that_changes_over_the_years(tmp_path):
    """A drift, an annual term and a dated step of the true camera: each pass's true camera
    (in its truth file) differs from camera_truth.h5 by exactly their sum on its date, field by
    field; nothing else moves."""
    import datetime

    from misrgraph.io.camera import read_camera_file
    from misrgraph.io.truth import read_pass_truth

    cfg = ScenarioConfig(
        truth="model",
        scenario="path",
        seed=5,
        n_passes=3,
        n_tie_points=10,
        n_check_points=2,
        duration_s=300.0,
        start_lat_deg=50.0,
        camera_drifts=(("Cf", "beta", 36.525),),
        camera_annual=(("An", "epsilon", 2.0),),
        camera_steps=(("2001-06-20", "Da", "delta", 3.0),),
    )
    run_simulate(cfg, tmp_path / "s")
    base = read_camera_file(tmp_path / "s" / "camera_truth.h5")
    files = sorted((tmp_path / "s" / "passes").glob("*.h5"))
    assert len(files) == 3
    for k, f in enumerate(files):
        days = 16 * k  # a repeat pass every 16 days from epoch_date, 2001-06-15
        assert cfg.epoch_date == "2001-06-15"
        want = np.zeros((3, len(CAMERAS)))  # delta, beta, epsilon (arcsec)
        want[1, CAMERAS.index("Cf")] = 36.525 * days / 365.25
        want[2, CAMERAS.index("An")] = 2.0 * np.sin(2 * np.pi * days / 365.25)
        step_on = datetime.date(2001, 6, 15) + datetime.timedelta(days=days) >= datetime.date(2001, 6, 20)
        want[0, CAMERAS.index("Da")] = 3.0 if step_on else 0.0
        got = read_pass_truth(f).camera_model
        for i, ang in enumerate(("delta", "beta", "epsilon")):
            np.testing.assert_allclose((getattr(got, ang) - getattr(base, ang)) / ARCSEC, want[i], atol=1e-9)
    # a step before the scenario's epoch: in camera_truth.h5 and in every pass alike
    run_simulate(
        dataclasses.replace(cfg, n_passes=1, camera_steps=(("2001-06-01", "Df", "beta", 5.0),)), tmp_path / "e"
    )
    early = read_camera_file(tmp_path / "e" / "camera_truth.h5")
    np.testing.assert_allclose((early.beta - base.beta)[CAMERAS.index("Df")] / ARCSEC, 5.0, atol=1e-9)
    got = read_pass_truth(next((tmp_path / "e" / "passes").glob("*.h5"))).camera_model
    np.testing.assert_allclose(got.beta, early.beta, atol=1e-15)
    with pytest.raises(InputError, match="camera_steps"):
        ScenarioConfig(camera_steps=(("2001-13-01", "Da", "delta", 1.0),))
    with pytest.raises(InputError, match="camera_drifts"):
        ScenarioConfig(camera_drifts=(("Dx", "delta", 1.0),))
