"""Noise levels learned from an ``update`` state (``update --noise-fit``) and from a result in memory."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.estimate.adjust import AdjustConfig
from misrgraph.io.noise import read_noise_model
from misrgraph.model.noise import NoiseModel
from misrgraph.runs.noise import pass_levels_of, read_pass_levels, run_noise_fit
from misrgraph.sim.simulate import load_scenario


def test_a_result_in_memory_gives_what_its_file_gives(small_pass_dir, tmp_path, monkeypatch):
    """``pass_levels_of`` on the adjustment result ``run_adjust`` holds in memory equals
    ``read_pass_levels`` on the RESULT.h5 it writes, field by field."""
    import misrgraph.runs.adjust as ra

    held = {}
    solve = ra.adjust_observation_set

    def keep(*a, **k):
        held["res"] = solve(*a, **k)
        return held["res"]

    monkeypatch.setattr(ra, "adjust_observation_set", keep)
    cfg = AdjustConfig()
    ra.run_adjust(small_pass_dir, out=tmp_path / "r.h5", cfg=cfg)
    mem = pass_levels_of(held["res"], cfg.graph, "mem")
    disk = read_pass_levels(tmp_path / "r.h5")
    for a in range(3):
        np.testing.assert_allclose(mem.knot_times[a], disk.knot_times[a])
        np.testing.assert_allclose(mem.knots[a], disk.knots[a])
        np.testing.assert_allclose(mem.knot_cov[a], disk.knot_cov[a])
    np.testing.assert_allclose(mem.ephemeris_boundaries, disk.ephemeris_boundaries)
    np.testing.assert_allclose(mem.ephemeris, disk.ephemeris)
    np.testing.assert_allclose(mem.ephemeris_cov, disk.ephemeris_cov)
    assert mem.classes == disk.classes and mem.classes
    assert set(mem.used) == set(disk.used)
    for k, v in mem.used.items():
        if isinstance(v, str):
            assert v == disk.used[k]
        else:
            np.testing.assert_allclose(np.asarray(v, float), np.asarray(disk.used[k], float), err_msg=k)


def test_update_noise_fit_learns_from_the_states_passes(path_dir, tmp_path):
    """``update --noise-fit`` on a state of four passes writes a noise model that ``--noise-model``
    reads: the state's own levels for what the passes do not carry (here a 2 arcsec jitter the
    state was created with), and attitude sigmas that agree, within their 1 sigma, with
    ``noise fit`` on the same passes adjusted one by one (the state solves them jointly: shared
    camera and GCPs). A later call with no new pass refits; a state that does not exist is refused."""
    sc = load_scenario(path_dir)
    files = [str(f) for f in sc.pass_files[:4]]
    start = NoiseModel.from_dict({"jitter": {"sigma_arcsec": 2.0}})
    from misrgraph.io.noise import save_noise_model

    save_noise_model(start, tmp_path / "start.json")
    common = ["--camera-model", str(path_dir / "camera_model.h5"), "--gcps", str(path_dir / "gcp.h5")]
    common += ["--dem", str(path_dir / "dem.h5"), "--noise-model", str(tmp_path / "start.json")]
    out = tmp_path / "nf.json"
    r = CliRunner().invoke(app, ["update", str(tmp_path / "s"), *files, *common, "--noise-fit", str(out), "--json"])
    assert r.exit_code == 0, r.output
    nf = json.loads(r.stdout)["noise_fit"]
    assert nf["passes"] == 4 and nf["out"] == str(out)
    model, source = read_noise_model(out)
    assert model.jitter.sigma_arcsec == 2.0 and source["jitter"] == "input"
    # the same passes adjusted one by one, with the same levels, then 'noise fit'
    results = []
    for i, f in enumerate(files):
        from misrgraph.runs.adjust import run_adjust

        res = tmp_path / f"r{i}.h5"
        run_adjust(path_dir, pass_file=f, out=res, cfg=AdjustConfig().with_noise(start))
        results.append(res)
    batch = run_noise_fit(results)
    for ang in ("roll", "pitch", "yaw"):
        a, b = nf["levels"][f"attitude.value_sigma_arcsec.{ang}"], batch["levels"][f"attitude.value_sigma_arcsec.{ang}"]
        assert a["sigma"] is not None and b["sigma"] is not None
        assert abs(a["value"] - b["value"]) < max(a["sigma"], b["sigma"]), (ang, a, b)
    # no new pass: the state is refitted as it is
    again = CliRunner().invoke(app, ["update", str(tmp_path / "s"), "--noise-fit", str(tmp_path / "nf2.json")])
    assert again.exit_code == 0, again.output
    assert read_noise_model(tmp_path / "nf2.json")[0] == model
    bad = CliRunner().invoke(app, ["update", str(tmp_path / "none"), "--noise-fit", str(tmp_path / "x.json")])
    assert bad.exit_code == 2 and not (tmp_path / "x.json").exists()


def test_the_noise_model_of_a_graph_configuration_is_the_one_it_came_from():
    """``NoiseModel.from_graph`` inverts ``graph_fields`` for a model whose every level differs
    from the pre-flight one."""
    m = NoiseModel.from_dict(
        {
            "attitude": {
                "value_sigma_arcsec": [20.0, 21.0, 22.0],
                "rate_sigma_arcsec_per_s": [0.5, 0.6, 0.7],
                "damping": 0.7,
                "knot_spacing_s": [30.0, 20.0, 15.0],
            },
            "jitter": {"sigma_arcsec": 0.5, "periods_s": [10.0, 200.0]},
            "ephemeris": {"offset_sigma_m": 80.0, "drift_sigma_mps": [0.1, 0.2, 0.3], "once_per_rev_m": 40.0},
            "camera": {"angle_prior_px": 0.1, "focal_prior_px": 0.2},
            "dem": {"sigma_scale": 1.5},
            "observations": {"tie_sigma_scale": 1.2, "gcp_pixel_sigma_scale": 1.3, "gcp_sigma_scale": 1.4},
        }
    )
    assert m != NoiseModel()
    assert NoiseModel.from_graph(AdjustConfig().with_noise(m).graph) == m
