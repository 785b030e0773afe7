"""bench monitor at reduced size: its fields, the Wilson interval against scipy's, the monitor
finding a 0.1 px step at recalibrations of 0.02 px, and, with errors shared across cameras, the
conditional view finding more drifts than the cameras' own series."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import binomtest
from typer.testing import CliRunner

from misrgraph.bench.monitor import wilson_interval
from misrgraph.commands.cli import app
from misrgraph.model.constants import CAMERAS


def test_wilson_interval_is_scipys() -> None:
    for k, n in ((0, 10), (3, 10), (19, 20), (50, 100)):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert wilson_interval(k, n) == pytest.approx([ci.low, ci.high], abs=1e-4)


def _calibration(path, sigma_px: float, shared: float) -> None:
    """A calibration summary: every angle's ``sigma_px``, the cameras' errors of one parameter
    correlated at ``shared``."""
    pars = ("delta", "beta", "epsilon")
    labels = [f"{c}.{p}" for c in CAMERAS for p in pars]
    corr = np.array([[1.0 if a == b else shared * (a[-5:] == b[-5:]) for b in labels] for a in labels])
    cams = {
        c: {"sigma_px": 2 * sigma_px, "params": {p: {"sigma": 1e-6, "sigma_px": sigma_px} for p in pars}}
        for c in CAMERAS
    }
    path.write_text(json.dumps({"cameras": cams, "correlation": {"labels": labels, "matrix": corr.tolist()}}))


def test_bench_monitor_cli(tmp_path) -> None:
    cal = tmp_path / "cal.json"
    _calibration(cal, 0.02, 0.0)
    r = CliRunner().invoke(
        app,
        ["bench", "monitor", "--campaigns", "20", "--years", "4", "--calibration", str(cal), "--seed", "3", "--json"],
    )
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    assert res["campaigns"] == 20 and res["sigma_source"] == str(cal) and res["provenance"]["command"]
    for part, keys in (("step", ("detected", "right_camera")), ("drift", ("flagged",))):
        for key in keys:
            lo, hi = res[part]["interval"][key]
            assert lo <= res[part][key] <= hi
    lo, hi = res["interval"]["false_alarm_rate"]
    assert lo <= res["false_alarm_rate"] <= hi
    # a 0.1 px step is five sigmas of a recalibration here: found at once, in the right camera
    assert res["step"]["detected"] >= 0.8 and res["step"]["right_camera"] >= 0.8, res["step"]
    # the configured rate is inside the false alarms' interval (20 campaigns: a loose check)
    assert lo <= res["alpha"], res["interval"]
    bad = CliRunner().invoke(app, ["bench", "monitor", "--calibration", str(tmp_path / "none.json")])
    assert bad.exit_code == 2 and "none.json" in bad.output
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"cameras": {c: {"sigma_px": 0.02} for c in CAMERAS}}))
    bad = CliRunner().invoke(app, ["bench", "monitor", "--calibration", str(old)])
    assert bad.exit_code == 2 and "old.json" in bad.output and "sigma_px" in bad.output


def test_a_shared_error_hides_drifts_from_the_cameras_own_series(tmp_path) -> None:
    """Recalibrations of 0.03 px whose errors the nine cameras share at 0.9: the conditional view
    flags most 0.05 px/yr drifts before 1/16 px, the cameras' own series few."""
    cal = tmp_path / "cal.json"
    _calibration(cal, 0.03, 0.9)
    got = {}
    for view in ("conditional", "marginal"):
        r = CliRunner().invoke(
            app,
            ["bench", "monitor", "--campaigns", "30", "--years", "4", "--recalibrate-days", "60"]
            + ["--calibration", str(cal), "--seed", "5", "--view", view, "--json"],
        )
        assert r.exit_code == 0, r.output
        got[view] = json.loads(r.output)
        assert got[view]["view"] == view
    hi, lo = got["conditional"]["drift"], got["marginal"]["drift"]
    assert hi["interval"]["flagged"][0] > lo["interval"]["flagged"][1], (hi, lo)
