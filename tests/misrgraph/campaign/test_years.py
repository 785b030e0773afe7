"""The campaign over years: windows and orbits in closed form, the versions the monitor calls for on
series made by hand, the stale passes, and (slow) a campaign whose true Da camera steps, run,
killed and resumed."""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest

from misrgraph.campaign.plan import CampaignConfig
from misrgraph.campaign.years import (
    calibration_days,
    first_orbit_of_day,
    pass_day,
    plan_versions,
    stale_passes,
    window_starts,
)
from misrgraph.errors import InputError
from misrgraph.model.constants import CAMERAS

ARCSEC = math.pi / 180 / 3600


def test_windows_and_orbits() -> None:
    cfg = CampaignConfig(months=12, recalibrate_months=3)
    starts = window_starts(cfg)
    assert starts == pytest.approx([0.0, 91.3125, 182.625, 273.9375])
    assert first_orbit_of_day(16.0) == 233 and first_orbit_of_day(91.3125) == math.ceil(91.3125 * 233 / 16)
    assert pass_day("P037_O0466") == 32.0
    with pytest.raises(InputError, match="recalibrate_months"):
        CampaignConfig(months=6, recalibrate_months=3)
    with pytest.raises(InputError, match="camera_steps"):
        CampaignConfig(camera_steps=(("2001-06-01", "Da", "delta", 3.0),))


def _summaries(rng: np.random.Generator, n: int, step_at: int | None, sigma_arcsec: float = 1.0) -> list[dict]:
    out = []
    for k in range(n):
        cams = {}
        for cam in CAMERAS:
            params = {}
            for par in ("delta", "beta", "epsilon"):
                v = rng.normal(0, sigma_arcsec)
                if step_at is not None and k >= step_at and (cam, par) == ("Da", "delta"):
                    v += 10 * sigma_arcsec
                params[par] = {"value": v * ARCSEC, "sigma": sigma_arcsec * ARCSEC}
            cams[cam] = {"params": params}
        labels = [f"{cam}.{par}" for cam in CAMERAS for par in ("delta", "beta", "epsilon")]
        out.append({"cameras": cams, "correlation": {"labels": labels, "matrix": np.eye(len(labels)).tolist()}})
    return out


def test_a_step_makes_a_version_at_its_window_and_nothing_else_does(rng) -> None:
    """Twelve windows of 1-arcsec calibrations: a 10-sigma step of Da delta at window 7 (index 6)
    gives version 2 at window 7 or 8 naming Da delta, with the onset at or before the alarm; the
    same series without the step gives one version."""
    t = [30.0 * k for k in range(12)]
    got = plan_versions(t, _summaries(rng, 12, 6))
    assert got["version_windows"][0] == 0 and got["version_windows"][1] in (6, 7), got["alarms"]
    a = got["alarms"][0]
    assert (a["camera"], a["parameter"], a["direction"]) == ("Da", "delta", 1)
    assert a["onset_window"] <= a["window"] and a["onset_window"] >= 5
    assert got["series"]["Da"]["delta"]["sigma_arcsec"] == pytest.approx([1.0] * 12)
    calm = plan_versions(t, _summaries(np.random.default_rng(5), 12, None))
    assert calm["version_windows"] == [0] and calm["alarms"] == []


def test_stale_passes_are_those_from_the_last_blind_calibration_to_the_new_version() -> None:
    """An alarm at window 3 whose CUSUM run starts at window 2: the passes after window 1's
    calibration (the middle of its 30-day GCP scenario, day 91.3 + 15) and before window 3's
    first day (182.6) are stale; none before or after."""
    cfg = CampaignConfig(months=12, recalibrate_months=3)
    assert calibration_days(cfg) == pytest.approx([15.0, 106.3125, 197.625, 288.9375])
    alarm = {"camera": "Da", "parameter": "delta", "kind": "step", "window": 2, "onset_window": 1}
    passes = {f"P037_O{233 * k:04d}": ("v001" if 16 * k < 182.625 else "v002") for k in range(23)}
    stale = stale_passes(cfg, passes, [alarm])
    want = sorted(p for p in passes if 15.0 < pass_day(p) < 182.625)
    assert [r["pass_id"] for r in stale] == want and len(want) == 11  # cycles 1-11 (days 16-176)
    assert {r["version"] for r in stale} == {"v001"} and {r["superseded_by"] for r in stale} == {"v002"}
    assert stale[0]["date"] == "2001-07-01"  # cycle 1, 16 days after 2001-06-15
    alarm["onset_window"] = 2  # the run starts at the alarm: from window 2's calibration (day 106.3)
    assert [r["pass_id"] for r in stale_passes(cfg, passes, [alarm])] == [p for p in want if pass_day(p) > 106.3125]


@pytest.mark.slow
def test_a_campaign_over_months_finds_the_step_and_resumes(tmp_path) -> None:
    """Four windows of half a month; Da's true delta steps by 60 arcsec on 2001-07-10. The monitor
    asks for a version at the window after the step; each pass is adjusted with the version the
    store gives its orbit; the new version's Da delta differs from the first's by the step (within
    4 sigma of the two calibrations), and no other camera angle moved by more than 4 sigma; a
    rerun finds every task done and the outputs unchanged."""
    from misrgraph.campaign.run import campaign_fingerprint, run_campaign
    from misrgraph.io.cgm import open_store, version_for_orbit
    from misrgraph.runs.cgm import run_cgm_diff
    from misrgraph.runs.update import _pass_orbit

    cfg = CampaignConfig.from_dict(
        {
            "months": 2,
            "recalibrate_months": 0.5,
            "size": "reduced",
            "paths": [37],
            "products": False,
            "camera_steps": [["2001-07-10", "Da", "delta", 60.0]],
        }
    )
    out = tmp_path / "c"
    s = run_campaign(out, cfg, workers=0)
    y = s["years"]
    assert y["status"] == "done" and s["passes"]["failed"] == 0
    assert [v["window"] for v in y["versions"]] == [0, 2]  # the step is in window 2; the alarm at 3
    assert (y["alarms"][0]["camera"], y["alarms"][0]["parameter"]) == ("Da", "delta")
    store = open_store(y["store"])
    for pid, vid in y["pass_versions"].items():
        f = next((out / "inputs").glob(f"path_037-*/passes/{pid}.h5"))
        assert version_for_orbit(store, _pass_orbit(f))[0].id == vid
    diff = run_cgm_diff(y["store"], "v001", "v002")
    da = diff["cameras"]["Da"]["delta"]
    assert abs(da["arcsec"] - 60.0) < 4 * da["sigma_arcsec"], da
    others = [v for e in diff["cameras"].values() for p, v in e.items() if p in ("delta", "beta", "epsilon")]
    assert sum(abs(v["z"]) > 4 for v in others) == 1, others
    assert {r["pass_id"] for r in y["stale_passes"]} <= set(y["pass_versions"])
    report = (out / "report" / "campaign.md").read_text()
    assert "Over the years" in report and (out / "report" / "camera_years.png").exists()
    before = campaign_fingerprint(out)
    again = run_campaign(out, cfg, workers=0)
    assert all(st["found_done"] == st["tasks"] for st in again["stages"].values()), again["stages"]
    assert campaign_fingerprint(out) == before
    assert json.loads((out / "summary.json").read_text())["years"]["versions"] == y["versions"]
    # the same campaign from the CLI, SIGKILLed while it calibrates the windows, then resumed
    from misrgraph.bench.faults import _cli, _run_and_kill

    conf = tmp_path / "c.json"
    conf.write_text(json.dumps({"camera_steps": [["2001-07-10", "Da", "delta", 60.0]]}))
    args = ["campaign", "--months", "2", "--recalibrate", "0.5", "--size", "reduced", "--paths", "37"]
    args += ["--no-products", "--workers", "0", "--config", str(conf), "--out", str(tmp_path / "k")]
    assert _run_and_kill(_cli(*args), 20.0, group=True)
    assert not (tmp_path / "k" / "summary.json").exists()
    r = subprocess.run(_cli(*args), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-800:]
    assert campaign_fingerprint(tmp_path / "k") == before
    resumed = json.loads((tmp_path / "k" / "summary.json").read_text())["years"]
    assert resumed["versions"] == y["versions"] and resumed["pass_versions"] == y["pass_versions"]


def test_the_years_in_rerun_hold_the_series_and_versions(tmp_path, rng) -> None:
    """A campaign summary over years viewed in rerun: each camera angle's values and its 1-sigma
    band on the date timeline, value by value, and one text row per version and alarm."""
    pytest.importorskip("rerun")
    import rerun.chunk as rc

    from misrgraph.viz.viewer import run_view

    t = [30.0 * k for k in range(12)]
    plan = plan_versions(t, _summaries(rng, 12, 6))
    years = {
        "status": "done",
        "windows": [{"window": k + 1, "start": f"2002-{k + 1:02d}-01"} for k in range(12)],
        "series": plan["series"],
        "alarms": plan["alarms"],
        "versions": [
            {"id": f"v{i + 1:03d}", "window": w, "first_orbit": 0, "reason": "r"}
            for i, w in enumerate(plan["version_windows"])
        ],
    }
    (tmp_path / "summary.json").write_text(json.dumps({"years": years}))
    out = run_view(tmp_path, save=tmp_path / "y.rrd")
    assert out["kind"] == "campaign"
    cols: dict[str, list] = {}
    for ch in rc.RrdReader(str(tmp_path / "y.rrd")).store().stream():
        rb = ch.to_record_batch()
        name = [c for c in rb.schema.names if "scalars" in c.lower() or "text" in c.lower()]
        if name:
            cols.setdefault(str(ch.entity_path), []).extend(rb.column(name[0]).to_pylist())
    e = plan["series"]["Da"]["delta"]
    got = np.ravel(cols["/years/Da/delta/value"]).astype(float)
    np.testing.assert_allclose(got, e["value_arcsec"])
    upper = np.ravel(cols["/years/Da/delta/upper"]).astype(float)
    np.testing.assert_allclose(upper - got, e["sigma_arcsec"])
    assert len(cols["/years/versions"]) == len(years["versions"]) == 2
    assert len(cols["/years/alarms"]) == len(plan["alarms"])
