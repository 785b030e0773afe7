"""misrgraph monitor on a table of calibration summaries: a step put into one camera's delta is
found at the calibration it happened, naming that camera and parameter; the same table without
the step raises nothing; with calibration errors shared across cameras, a step hidden in the
cameras' own series is found given the others; bad tables are refused in one line."""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from misrgraph.commands.cli import app
from misrgraph.model.constants import CAMERAS

ARCSEC = math.pi / 180 / 3600


def _table(tmp: Path, step_arcsec: float, seed: int = 2, shared: float = 0.0) -> Path:
    """24 monthly calibrations, 0.5" 1-sigma per angle, the share ``shared`` of each parameter's
    error variance common to the nine cameras (the summaries' correlation says so); Da's delta
    steps by ``step_arcsec`` from calibration 16 on."""
    rng = np.random.default_rng(seed)
    start = dt.datetime(2003, 1, 15, tzinfo=dt.timezone.utc)
    rows = ["utc,calibration"]
    params_ = ("delta", "beta", "epsilon", "alpha2")
    labels = [f"{cam}.{p}" for cam in CAMERAS for p in params_]
    corr = np.eye(len(labels))
    for i, a in enumerate(labels):
        for j, b in enumerate(labels):
            if i != j and a.split(".")[1] == b.split(".")[1]:
                corr[i, j] = shared
    for k in range(24):
        common = {p: rng.normal(0, 0.5 * math.sqrt(shared)) for p in params_}
        cams = {}
        for cam in CAMERAS:
            params = {}
            for p in params_:
                v = common[p] + rng.normal(0, 0.5 * math.sqrt(1 - shared))
                v += step_arcsec if (cam, p, k >= 16) == ("Da", "delta", True) else 0.0
                params[p] = {"value": v * ARCSEC, "sigma": 0.5 * ARCSEC}
            cams[cam] = {"params": params, "sigma_px": 0.03}
        f = tmp / f"cal_{k:02d}.json"
        f.write_text(json.dumps({"cameras": cams, "correlation": {"labels": labels, "matrix": corr.tolist()}}))
        t = start + dt.timedelta(days=30 * k)
        rows.append(f"{t.strftime('%Y-%m-%dT%H:%M:%SZ')},{f.name}")
    table = tmp / "series.csv"
    table.write_text("\n".join(rows) + "\n")
    return table


def test_monitor_finds_the_step_and_nothing_without_it(tmp_path: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    r = CliRunner().invoke(app, ["monitor", str(_table(tmp_path / "a", 4.0)), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    assert res["calibrations"] == 24 and res["trained_on"] == 12 and res["new_cgm_needed"]
    first = res["alarms"][0]
    assert (first["camera"], first["parameter"], first["direction"]) == ("Da", "delta", 1)
    step_at = (dt.datetime(2003, 1, 15) + dt.timedelta(days=30 * 16)).strftime("%Y-%m-%d")
    assert first["utc"].startswith(step_at), first
    assert first["onset_utc"].startswith(step_at), first  # an 8-sigma step: the alarm at its onset
    r = CliRunner().invoke(app, ["monitor", str(_table(tmp_path / "b", 0.0)), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output)["alarms"] == []


def test_given_the_others_a_step_hidden_by_a_shared_error_is_found(tmp_path: Path) -> None:
    """90 % of every calibration error shared by the cameras: a 1.5" step (3 sigma of a camera's
    own series) in Da delta is found at its calibration in the conditional view, and not at once in
    the cameras' own series."""
    table = _table(tmp_path, 1.5, seed=4, shared=0.9)
    step_at = (dt.datetime(2003, 1, 15) + dt.timedelta(days=30 * 16)).strftime("%Y-%m-%d")
    r = CliRunner().invoke(app, ["monitor", str(table), "--json"])
    assert r.exit_code == 0, r.output
    res = json.loads(r.output)
    assert res["view"] == "conditional" and res["alarms"], res
    first = res["alarms"][0]
    assert (first["camera"], first["parameter"], first["direction"]) == ("Da", "delta", 1), first
    assert first["utc"].startswith(step_at), first
    r = CliRunner().invoke(app, ["monitor", str(table), "--view", "marginal", "--json"])
    assert r.exit_code == 0, r.output
    own = json.loads(r.output)
    assert own["view"] == "marginal"
    assert not any(a["camera"] == "Da" and a["utc"].startswith(step_at) for a in own["alarms"]), own["alarms"]


def test_monitor_refuses_bad_tables(tmp_path: Path) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("when,file\n2003-01-01T00:00:00Z,x.json\n")
    r = CliRunner().invoke(app, ["monitor", str(bad)])
    assert r.exit_code == 2 and "utc, calibration" in r.output
    short = tmp_path / "short.csv"
    short.write_text("utc,calibration\n2003-01-01T00:00:00Z,x.json\n")
    r = CliRunner().invoke(app, ["monitor", str(short)])
    assert r.exit_code == 2 and "at least 8" in r.output
    table = _table(tmp_path, 0.0)
    s = json.loads((tmp_path / "cal_05.json").read_text())
    del s["correlation"]
    (tmp_path / "cal_05.json").write_text(json.dumps(s))
    r = CliRunner().invoke(app, ["monitor", str(table)])
    assert r.exit_code == 2 and "cal_05.json" in r.output and "--view marginal" in r.output, r.output
    r = CliRunner().invoke(app, ["monitor", str(table), "--view", "marginal", "--json"])
    assert r.exit_code == 0 and json.loads(r.output)["alarms"] == [], r.output
    (tmp_path / "c").mkdir()
    other = _table(tmp_path / "c", 0.0)
    s = json.loads((tmp_path / "c" / "cal_07.json").read_text())
    m = np.array(s["correlation"]["matrix"])
    d = [i for i, x in enumerate(s["correlation"]["labels"]) if x.endswith(".delta")]
    m[np.ix_(d, d)] = 1.0  # every camera's delta the same error: no camera given the others
    s["correlation"]["matrix"] = m.tolist()
    (tmp_path / "c" / "cal_07.json").write_text(json.dumps(s))
    r = CliRunner().invoke(app, ["monitor", str(other)])
    assert r.exit_code == 2 and "cal_07.json" in r.output and "positive definite" in r.output, r.output
    r = CliRunner().invoke(app, ["monitor", str(table), "--view", "joint"])
    assert r.exit_code == 2 and "--view" in r.output and "conditional" in r.output
    (tmp_path / "cal_03.json").write_text("{}")
    r = CliRunner().invoke(app, ["monitor", str(table)])
    assert r.exit_code == 2 and "cal_03.json" in r.output and "Traceback" not in r.output
