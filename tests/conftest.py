"""Shared, seeded fixtures: the nominal camera model, a reference pass geometry and the simulated
scenarios many test files use. A scenario is simulated once per test run and shared by the
pytest-xdist workers (:func:`_built_once`)."""

from __future__ import annotations

import fcntl
import json
import os
import shutil
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
from hypothesis import settings

from misrgraph.model.camera import CameraModel
from misrgraph.model.geolocation import PassGeometry
from misrgraph.model.nominal import nominal_camera_model
from misrgraph.model.orbit import AttitudeSeries, terra_like_orbit

settings.register_profile("ci", max_examples=40, deadline=None, derandomize=True)
settings.load_profile("ci")


def _built_once(tmp_path_factory, name: str, build: Callable[[Path], Any]) -> tuple[Path, Any]:
    """``(directory, build's JSON-able result)``: ``build(directory)`` runs once per test run, in
    whichever xdist worker asks first; the others wait on a lock and reuse the directory (the
    pattern pytest-xdist documents for session fixtures). A build that failed is redone."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # shared by the workers of this run
    base = root / "built-once"
    base.mkdir(exist_ok=True)
    out, done = base / name, base / f"{name}.json"
    with open(base / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not done.exists():
                if out.exists():
                    shutil.rmtree(out)
                done.write_text(json.dumps(build(out)))
            return out, json.loads(done.read_text())
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def nominal_camera() -> CameraModel:
    return nominal_camera_model()


@pytest.fixture(scope="session")
def reference_pass(nominal_camera: CameraModel) -> PassGeometry:
    """A 30-minute descending pass with a slowly varying attitude (not identity, to exercise it)."""
    eph = terra_like_orbit(epoch_date="2001-06-15", path=37, start_lat_deg=60.0, duration_s=1800.0)
    t = eph.t
    w = 2 * np.pi / 600.0
    amp = np.radians(np.array([20.0, 30.0, 15.0]) / 3600.0)
    angles = amp * np.sin(w * t[:, None] + np.array([0.0, 1.0, 2.0]))
    rates = amp * w * np.cos(w * t[:, None] + np.array([0.0, 1.0, 2.0]))
    return PassGeometry(eph, AttitudeSeries(t, angles, rates), nominal_camera)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def small_pass_dir(tmp_path_factory):
    """A reduced 'pass' scenario (seed 11): 150 tie points, 20 check points, 15-minute pass."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    cfg = ScenarioConfig(
        truth="model",
        scenario="pass",
        seed=11,
        n_tie_points=150,
        n_check_points=20,
        duration_s=900.0,
        start_lat_deg=55.0,
        tie_blunder_rate=0.02,
    )
    return _built_once(tmp_path_factory, "pass", lambda out: run_simulate(cfg, out))[0]


@pytest.fixture(scope="session")
def imagery_pass_dir(tmp_path_factory):
    """A reduced 'pass' scenario with imagery (seed 3): 60 tie points, 10 check points, 15-minute
    pass over 45 N, matched once (``misrgraph match``) by the fixture."""
    from misrgraph.runs.match import run_match
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    cfg = ScenarioConfig(
        truth="model",
        scenario="pass",
        seed=3,
        n_tie_points=60,
        n_check_points=10,
        duration_s=900.0,
        start_lat_deg=45.0,
        imagery=True,
    )

    def build(out: Path) -> None:
        run_simulate(cfg, out)
        run_match(out)

    return _built_once(tmp_path_factory, "imagery", build)[0]


@pytest.fixture(scope="session")
def matched_month_dir(tmp_path_factory):
    """A reduced month with imagery (seed 1, 30 GCPs, 5 days: GCP windows and chips in every GCP
    pass), matched once by the fixture; ``(directory, simulate's summary, match's summary)``."""
    from misrgraph.runs.match import run_match
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    cfg = ScenarioConfig(truth="model", scenario="month", seed=1, n_gcps=30, month_days=5, imagery=True)
    out, (s, matched) = _built_once(
        tmp_path_factory, "matched_month", lambda out: (run_simulate(cfg, out), run_match(out))
    )
    return out, s, matched


@pytest.fixture(scope="session")
def path_dir(tmp_path_factory):
    """A repeat-path scenario (seed 41): ten 10-minute passes of one path, 40 tie points each."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    cfg = ScenarioConfig(
        truth="model",
        scenario="path",
        seed=41,
        n_passes=10,
        n_tie_points=40,
        n_check_points=5,
        duration_s=600.0,
        start_lat_deg=52.0,
    )
    return _built_once(tmp_path_factory, "path", lambda out: run_simulate(cfg, out))[0]


def _simulate_roi_path(out, camera_truth=None):
    """Four passes of path 37 with imagery (seed 41, clouds 20 %) and whole-line strips over the
    block under the mid-pass nadir point, reduced for the suite: cameras Df, An, Da, 256 of the
    1504 samples (600-855), no feature windows."""
    from misrgraph.campaign.tasks import mid_pass_block
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    block = mid_pass_block({"scenario": "path", "path": 37, "start_lat_deg": 52.0, "duration_s": 600.0})
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="path",
            seed=41,
            n_passes=4,
            n_tie_points=30,
            n_check_points=5,
            n_gcps=20,
            duration_s=600.0,
            start_lat_deg=52.0,
            imagery=True,
            cloud_fraction=0.2,
            roi_blocks=(block, block),
            strip_cameras=("Df", "An", "Da"),
            strip_samples=(600, 256),
            feature_windows=False,
            camera_truth=camera_truth or "",
        ),
        out,
    )
    return out


@pytest.fixture(scope="session")
def roi_path_dir(tmp_path_factory):
    """The ROI scenario (:func:`_simulate_roi_path`) with its own instrument."""
    return _simulate_roi_path(tmp_path_factory.mktemp("scen") / "roi")


@pytest.fixture(scope="session")
def campaign_roi_path_dir(tmp_path_factory, campaign_setup):
    """The ROI scenario flown by the campaign month's instrument (its true camera model), so that
    a campaign can calibrate on that month and map these passes."""
    truth = campaign_setup[1] / "month" / "camera_truth.h5"
    return _simulate_roi_path(tmp_path_factory.mktemp("scen") / "campaign_roi", str(truth))


@pytest.fixture(scope="session")
def small_pass(small_pass_dir):
    from misrgraph.sim.simulate import load_scenario

    sc = load_scenario(small_pass_dir)
    return sc, sc.load_pass(0)


@pytest.fixture(scope="session")
def exact_pass(tmp_path_factory):
    """Noise-free pass, no camera residual, knots on the graph's grid: the truth is a zero of
    every collinearity residual."""
    from misrgraph.sim.simulate import ScenarioConfig, load_scenario, run_simulate

    out = tmp_path_factory.mktemp("scen") / "exact"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="pass",
            seed=21,
            n_tie_points=40,
            n_check_points=0,
            duration_s=900.0,
            start_lat_deg=55.0,
            noise_free=True,
            camera_residual_px=0.0,
            camera_f_alpha_px=0.0,
        ),
        out,
    )
    sc = load_scenario(out)
    return sc, sc.load_pass(0)


@pytest.fixture(scope="session")
def small_month_dir(tmp_path_factory):
    """A reduced 'month' scenario: 30 GCPs over 16 days (about 40 GCP passes)."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    cfg = ScenarioConfig(truth="model", scenario="month", seed=31, n_gcps=30, month_days=16)
    return _built_once(tmp_path_factory, "small_month", lambda out: run_simulate(cfg, out))[0]


@pytest.fixture(scope="session")
def thermal_month_dir(tmp_path_factory):
    """A reduced 'month' with a thermal truth: 40 GCPs over 30 days (about 110 GCP passes at
    1-10 C), per-camera delta/beta slopes of 2 arcsec/C and focal-scale slopes of 20 ppm/C (1 sigma)."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    out = tmp_path_factory.mktemp("scen") / "thermal_month"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="month",
            seed=5,
            n_gcps=40,
            month_days=30,
            thermal_arcsec_per_c=2.0,
            thermal_focal_ppm_per_c=20.0,
        ),
        out,
    )
    return out


@pytest.fixture(scope="session")
def band_month_dir(tmp_path_factory):
    """A reduced 'month' observed in all four bands, whose true camera has per-band angle offsets
    (10 arcsec 1 sigma per band and angle): 30 GCPs over 16 days."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    out = tmp_path_factory.mktemp("scen") / "band_month"
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="month",
            seed=7,
            n_gcps=30,
            month_days=16,
            bands=("blue", "green", "red", "nir"),
            band_misalignment_arcsec=10.0,
        ),
        out,
    )
    return out


@pytest.fixture(scope="session")
def campaign_setup(tmp_path_factory):
    """A reduced campaign (seed 0): paths 37 and 38, two months of data (four repeat passes a
    path), one PP block; its inputs simulated once into ``inputs/month`` and ``inputs/path_PPP``."""
    from misrgraph.bench.campaign import prepare_campaign_inputs
    from misrgraph.campaign import CampaignConfig

    cfg = CampaignConfig(paths=(37, 38), months=2.0, size="reduced", pp_blocks=1)
    _, inputs = _built_once(tmp_path_factory, "campaign", lambda out: str(prepare_campaign_inputs(out, cfg)))
    return cfg, Path(inputs)
