from __future__ import annotations

import json

import h5py
import pytest
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.runs.demo import STAGES


@pytest.mark.slow
def test_small_demo_runs_every_stage(tmp_path):
    res = CliRunner().invoke(app, ["demo", "--small", "--out", str(tmp_path / "d")])
    assert res.exit_code == 0, res.output
    for name, _ in STAGES:
        assert name.split()[0] in res.stdout
    for f in (
        "camera_calibrated.h5",
        "pass_result.h5",
        "pass_result.rrd",
        "calibration.rrd",
        "plots/attitude_error.png",
        "plots/calibration_pointing.png",
        "state/state.json",
    ):
        assert (tmp_path / "d" / f).exists(), f
    assert list((tmp_path / "d" / "plots").glob("match_*.png"))  # a chip, its window, NCC and LSM
    # the images stage matched the pass it rendered (the observations are in its pass file)
    from misrgraph.io.imagery import read_matched

    (f,) = sorted((tmp_path / "d" / "imagery" / "passes").glob("*.h5"))
    s = read_matched(f).summary
    assert s["gcp"]["matched"] > 0 and s["tie"]["matched"] > 0 and s["tie"]["error_px"]["rms"] <= 0.2, s
    # the adjusted pass's attitude sigma never exceeds its prior (Hermite interpolation: <= 0.3 %)
    with h5py.File(tmp_path / "d" / "pass_result.h5", "r") as f:
        att = json.loads(f.attrs["summary_json"])["attitude_sigma"]
    assert set(att) == {"roll", "pitch", "yaw"}
    for v in att.values():
        assert 0.0 < v["max_over_prior"] <= 1.003, att
