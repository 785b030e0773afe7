"""``run_campaign`` / ``misrgraph campaign`` on a reduced campaign (2 paths x 4 passes): a real
2-worker LocalCluster against the same steps run in this process, resumption, failures reported
per pass, and bad input."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from misrgraph.campaign import campaign_difference, campaign_fingerprint, run_campaign
from misrgraph.commands.cli import app
from misrgraph.errors import InputError
from misrgraph.model.constants import CAMERAS


@pytest.fixture(scope="module")
def runs(campaign_setup, tmp_path_factory):
    cfg, inputs = campaign_setup
    base = tmp_path_factory.mktemp("runs")
    seq = run_campaign(base / "sequential", cfg, inputs=inputs, workers=0)
    clu = run_campaign(base / "cluster", cfg, inputs=inputs, workers=2)
    return cfg, inputs, base, seq, clu


def test_cluster_run_equals_the_sequential_run(runs) -> None:
    cfg, _, base, seq, clu = runs
    assert clu["cluster"]["kind"] == "dask" and clu["cluster"]["workers"] == 2
    assert len(clu["cluster"]["peak_rss_mb"]) == 2  # one figure per worker process
    # the tasks ran on both worker processes, none in this one; in-process, all here
    assert len(clu["cluster"]["task_pids"]) == 2 and os.getpid() not in clu["cluster"]["task_pids"]
    assert seq["cluster"]["task_pids"] == [os.getpid()]
    for s in (seq, clu):
        assert s["passes"] == {"planned": 8, "done": 8, "failed": 0}, s["failed"]
        assert s["failed"] == []
    d = campaign_difference(base / "sequential", base / "cluster")
    assert d["missing"] == [] and d["other"] == []
    # workers run one BLAS thread each, this process several: the sums are ordered differently,
    # so the numbers agree to round-off (float32 PP grids: a few 1e-8), not bit for bit
    assert d["max_relative"] < 1e-6, d
    n_out = len(campaign_fingerprint(base / "cluster"))
    assert n_out == 1 + 8 + 2 * (4 + 1 + 1)  # calibration, 8 passes; per path 4 state passes, estimate, PP


def test_the_campaign_improves_on_the_supplied_navigation_in_every_camera(runs) -> None:
    _, _, base, _, clu = runs
    assert set(clu["cameras"]) == set(CAMERAS)
    for cam, v in clu["cameras"].items():
        assert v["passes"] == 8
        # check points against the simulator's truth: after adjustment, well under the supplied error
        assert v["checkpoint_rms_m"] < 0.5 * v["supplied_mean_m"], (cam, v)
    # the calibrated model carries its covariance into each adjustment's camera prior: the camera
    # corrections' NEES of every pass inside the 99.9 % chi-square band of its dimension (with
    # the per-camera default prior, 1/16 px, they read 7-9 on a reduced month's calibration)
    from scipy.stats import chi2

    for name in ("sequential", "cluster"):
        for f in sorted((base / name / "adjusted").rglob("*.h5")):
            import h5py

            with h5py.File(f) as h:
                s = json.loads(h.attrs["summary_json"])
            n = s["nees"]["camera_dim"]
            assert s["camera_prior"].startswith("the camera model's calibration")
            assert s["nees"]["camera"] < chi2.ppf(0.999, n) / n, (f.name, s["nees"]["camera"])
    from misrgraph.runs.update import restore_state

    solver = restore_state(Path(clu["paths"]["37"]["products"]["dir"]) / "state")[0]  # the path's state: the same prior
    assert solver.camera_prior is not None and len(solver.camera_prior[0]) == 45
    for path in ("37", "38"):
        p = clu["paths"][path]
        assert p["passes"] == {"planned": 4, "done": 4, "failed": 0}
        assert p["products"]["status"] == "done" and np.isfinite(p["products"]["pp_error_rms_m"])
        assert p["coregistration_px_max"] < 0.5
    md = (base / "cluster" / "report" / "campaign.md").read_text()
    assert "| 37 | 4/4 |" in md and "Calibration" in md
    for fig in ("cameras.png", "paths.png", "map.png", "stages.png"):
        assert (base / "cluster" / "report" / fig).stat().st_size > 1000
    assert json.loads((base / "cluster" / "summary.json").read_text())["passes"]["done"] == 8


def test_a_rerun_on_a_users_scheduler_finds_everything_done(runs) -> None:
    from distributed import LocalCluster

    cfg, inputs, base, _, clu = runs
    before = campaign_fingerprint(base / "cluster")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        again = run_campaign(base / "cluster", cfg, inputs=inputs, scheduler=cluster.scheduler_address)
    assert again["cluster"]["scheduler"] == cluster.scheduler_address
    assert all(s["found_done"] == s["tasks"] for s in again["stages"].values()), again["stages"]
    assert again["passes"] == clu["passes"]  # each planned pass counted once
    assert campaign_fingerprint(base / "cluster") == before


@pytest.mark.slow
def test_a_path_with_strips_gets_its_reference_orbit_imagery(runs, campaign_roi_path_dir, tmp_path) -> None:
    """``campaign --roi``: a path whose passes carry whole-swath strips (the ROI scenario, the
    month's instrument) gets its incremental state, PP and ROI from that state (iSAM2's joint
    estimate, the calibrated camera; the SOM DEM beside the inputs' DEM). The ROI's true
    misregistration stays within 3x of what its PP's 1 sigma and the DEM predict, as the per-pass
    ROI's does (tests/misrgraph/products/test_roi.py), and the report names it."""
    from misrgraph.bench.campaign import _seed_calibration
    from misrgraph.io.products import read_pp
    from misrgraph.io.roi import read_roi

    cfg, inputs, base, _, _ = runs
    mine = tmp_path / "inputs"
    mine.mkdir()
    (mine / "month").symlink_to(inputs / "month")
    (mine / "path_037").symlink_to(campaign_roi_path_dir)
    out = tmp_path / "campaign"
    _seed_calibration(base / "sequential", out)  # the month's calibration, found done
    res = run_campaign(out, cfg.replace(paths=(37,), roi=True), inputs=mine, workers=0)
    assert res["failed"] == [] and res["stages"]["calibration"]["found_done"] == 1
    roi_entry = res["paths"]["37"]["products"]["roi"]
    roi = read_roi(roi_entry["file"])
    assert (
        roi.cameras == ("Df", "An", "Da") and len(roi.pass_ids) == 4 and roi_entry["blocks"] == [int(roi.blocks[0])] * 2
    )
    summary = json.loads((Path(res["paths"]["37"]["products"]["dir"]) / "path.json").read_text())
    r = summary["products"]["roi"]
    assert r["passes"] == list(roi.pass_ids)
    pps = [read_pp(p) for p in sorted((out / "paths").glob("path_037-*/products/roi/PP_*.h5"))]
    assert len(pps) == 4
    dem_parallax_px = 10.0 * np.tan(np.radians(70.5)) / 275.0  # the SOM DEM's 10 m in the D cameras
    for cam in ("Df", "An", "Da"):
        sig = max(
            float(np.nanmedian(np.hypot(pp.sigma_line[pp.cameras.index(cam)], pp.sigma_sample[pp.cameras.index(cam)])))
            for pp in pps
        )
        assert r["truth_px"]["between_passes_px"][cam] < 3 * np.sqrt(2) * sig, (cam, r["truth_px"], sig)
        if cam != "An":
            assert r["truth_px"]["between_cameras_px"][cam] < 3 * np.sqrt(dem_parallax_px**2 + 2 * sig**2), (
                cam,
                r["truth_px"],
            )
    assert 0 < roi_entry["coregistration_px_max"] < 0.5
    assert "co-registration ≤" in (out / "report" / "campaign.md").read_text()


def test_a_failing_pass_is_reported_and_the_others_go_on(campaign_setup, tmp_path) -> None:
    cfg, inputs = campaign_setup
    mine = tmp_path / "inputs"
    shutil.copytree(inputs, mine)
    bad = sorted((mine / "path_038" / "passes").glob("*.h5"))[1]
    bad.write_bytes(bad.read_bytes()[:5000])  # truncated
    r = CliRunner().invoke(
        app,
        [
            "campaign",
            "--out",
            str(tmp_path / "out"),
            "--inputs",
            str(mine),
            "--paths",
            "37,38",
            "--months",
            "2",
            "--size",
            "reduced",
            "--workers",
            "0",
            "--no-products",
            "--json",
        ],
    )
    assert r.exit_code == 1, r.output
    s = json.loads(r.stdout)
    assert s["passes"] == {"planned": 8, "done": 7, "failed": 1}
    (f,) = s["failed"]
    assert f["name"] == bad.stem and bad.name in f["reason"]
    assert s["paths"]["38"]["passes"]["failed"] == 1 and s["paths"]["37"]["passes"]["failed"] == 0


def test_bad_input_is_one_clear_error(campaign_setup, tmp_path) -> None:
    cfg, inputs = campaign_setup
    with pytest.raises(InputError, match="--inputs"):
        run_campaign(tmp_path / "a", cfg, inputs=tmp_path, workers=0)
    with pytest.raises(InputError, match="--paths"):
        run_campaign(tmp_path / "a", cfg.replace(paths=(99,)), inputs=inputs, workers=0)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "campaign.json").write_text(json.dumps({"digest": "other", "config": {"months": 1}}))
    with pytest.raises(InputError, match="options of the campaign already in it"):
        run_campaign(tmp_path / "b", cfg, inputs=inputs, workers=0)
    # a plan written before a config field existed: said to be an earlier version's, not other options
    (tmp_path / "e").mkdir()
    old = {k: v for k, v in cfg.to_dict().items() if k != "observations"}
    (tmp_path / "e" / "campaign.json").write_text(json.dumps({"digest": "older", "config": old}, default=list))
    with pytest.raises(InputError, match="planned by an earlier misrgraph .its plan has no observations."):
        run_campaign(tmp_path / "e", cfg, inputs=inputs, workers=0)
    r = CliRunner().invoke(
        app, ["campaign", "--out", str(tmp_path / "c"), "--workers", "1", "--scheduler", "tcp://x:1"]
    )
    assert r.exit_code == 2 and "give one" in r.output
    r = CliRunner().invoke(app, ["campaign", "--out", str(tmp_path / "c"), "--paths", "300"])
    assert r.exit_code == 2 and "paths" in r.output and "1..233" in r.output


@pytest.mark.slow
def test_a_campaign_from_matched_observations(matched_month_dir, campaign_setup, tmp_path) -> None:
    """``campaign --observations matched`` on brought inputs that ``misrgraph match`` measured (a
    5-day month's GCP chips; two passes of path 37 flown by the month's instrument, tie points and
    GCPs matched in their imagery): the calibration, every adjustment and the path's state and PP
    use the matched set, and the check points still end well under the supplied navigation's
    error in every camera, as on the simulated observations. Inputs never matched are refused
    with the command that fixes them, and the tasks that need them say so."""
    import h5py

    from misrgraph.campaign import CampaignConfig
    from misrgraph.runs.match import run_match
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    month = matched_month_dir[0]
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    (inputs / "month").symlink_to(month, target_is_directory=True)
    run_simulate(
        ScenarioConfig(
            truth="model",
            scenario="path",
            seed=43,
            n_passes=2,
            n_tie_points=30,
            n_check_points=5,
            duration_s=600.0,
            start_lat_deg=52.0,
            imagery=True,
            camera_truth=str(month / "camera_truth.h5"),
        ),
        inputs / "path_037",
    )
    run_match(inputs / "path_037")
    cfg = CampaignConfig(paths=(37,), size="reduced", pp_blocks=1, passes_per_path=2, observations="matched")
    s = run_campaign(tmp_path / "out", cfg, inputs=inputs, workers=0)
    assert s["passes"] == {"planned": 2, "done": 2, "failed": 0} and s["failed"] == [], s["failed"]
    assert s["calibration"]["observation_set"] == "matched"
    for cam, v in s["cameras"].items():
        assert v["checkpoint_rms_m"] < 0.5 * v["supplied_mean_m"], (cam, v)
    p = s["paths"]["37"]
    assert p["products"]["status"] == "done" and np.isfinite(p["products"]["pp_error_rms_m"])
    for f in p["adjusted"]:
        with h5py.File(f) as h:
            assert json.loads(h.attrs["summary_json"])["observation_set"] == "matched"
    d = Path(p["products"]["dir"])
    assert json.loads((d / "state" / "state.json").read_text())["observations"] == "matched"
    assert json.loads((d / "path.json").read_text())["observation_set"] == "matched"
    assert "matched observations (measured in the imagery" in (tmp_path / "out" / "report" / "campaign.md").read_text()
    # the reduced campaign's inputs were never matched: refused, and nothing else runs on them
    bare = run_campaign(
        tmp_path / "bare",
        campaign_setup[0].replace(observations="matched", products=False),
        inputs=campaign_setup[1],
        workers=0,
    )
    reasons = {(f["stage"], f["name"]): f["reason"] for f in bare["failed"]}
    assert (
        "no matched observations" in reasons[("inputs", "month")] and "misrgraph match" in reasons[("inputs", "month")]
    )
    assert reasons[("calibration", "month")] == "needs inputs month, which failed"
    assert bare["passes"]["done"] == 0
