"""bench monitor at reduced size: its fields, the Wilson interval against scipy's, and the
monitor finding a 0.1 px step at recalibrations of 0.02 px."""

from __future__ import annotations

import json

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


def test_bench_monitor_cli(tmp_path) -> None:
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"cameras": {c: {"sigma_px": 0.02} for c in CAMERAS}}))
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
