"""The demo a newcomer runs first (``make demo``): the whole workflow on simulated data.

Every stage calls the same ``run_*`` functions as the CLI: simulate a standard month of GCP
passes and calibrate the cameras; simulate a 45-minute pass and adjust it with the recalibrated
model; render the images of a shorter pass (the same instrument), measure its GCPs and tie
points in them (``misrgraph match``) and adjust what was measured; simulate repeat passes of one
path and add them incrementally (iSAM2) against a batch re-solve; write a rerun recording and PNG
plots. Each stage reports its accuracy against the simulator's truth and its time. Sizes can be
reduced (``small=True``, used by the tests).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Callable

__all__ = ["run_demo", "STAGES"]

log = logging.getLogger(__name__)


def _sensitivity(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.evaluate.sensitivity import run_sensitivity

    res = run_sensitivity(arcsec=10.0, pixel=0.0, band="red")
    df, an = res["cameras"]["Df"], res["cameras"]["An"]
    return f'+10" pitch moves Df {df["pitch"]["along_m"]:.0f} m, An {an["pitch"]["along_m"]:.0f} m along track'


def _simulate_month(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    cfg = ScenarioConfig(scenario="month", seed=1, **({"n_gcps": 30, "month_days": 16} if st["small"] else {}))
    s = run_simulate(cfg, out / "month")
    return (
        f"{s['passes']} GCP passes, {s['observations']} observations, "
        f"{s['gcps_seen_in_3_or_more_passes']}/{s['gcps_seen']} GCPs in >= 3 passes"
    )


def _calibrate(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.runs.calibrate import run_calibrate
    from misrgraph.viz.plots import plot_calibration

    s = run_calibrate(out / "month", out=out / "camera_calibrated.h5")
    plot_calibration(s, out / "plots")
    worst = max(s["cameras"].items(), key=lambda kv: kv[1]["pointing_error_px"])
    return (
        f"max pointing error {s['max_pointing_error_px']:.3f} px ({worst[0]}; sigma {worst[1]['sigma_px']:.3f} px; "
        f"requirement 0.125), NEES/dim {s['nees']:.2f}, {s['rejected_observations']['count']} blunders rejected"
    )


def _simulate_pass(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    n = 150 if st["small"] else 600
    s = run_simulate(
        ScenarioConfig(
            scenario="pass",
            seed=2,
            n_tie_points=n,
            n_check_points=60,
            camera_truth=str(out / "month" / "camera_truth.h5"),
            **({"duration_s": 900.0, "start_lat_deg": 55.0} if st["small"] else {}),
        ),
        out / "pass",
    )
    return f"{s['observations']} observations of {n} tie points, GCPs and check points (same instrument as the month)"


def _adjust(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.viz.plots import plot_adjustment

    s = run_adjust(out / "pass", camera_model=out / "camera_calibrated.h5", out=out / "pass_result.h5")
    plot_adjustment(out / "pass_result.h5", out / "plots")
    cp = s["checkpoint_geolocation_m"]
    ratios = [v["ratio_before_over_after"] for v in cp.values()]
    after = [v["after"]["mean"] for v in cp.values()]
    st["attitude_sigma"] = s["attitude_sigma"]
    worst = max(v["max_over_prior"] for v in s["attitude_sigma"].values())
    return (
        f"check points {min(ratios):.1f}-{max(ratios):.1f}x better (after {min(after):.0f}-{max(after):.0f} m), "
        f"co-registration <= {max(s['coregistration_px'].values()):.2f} px, "
        f"NEES/dim knots {s['nees']['knots']:.2f} landmarks {s['nees']['landmarks']:.2f}, "
        f"attitude sigma <= {worst:.3f}x its prior"
    )


def _match(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.errors import InputError
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.runs.match import run_match
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate
    from misrgraph.viz.plots import plot_match

    n = 40 if st["small"] else 80
    run_simulate(
        ScenarioConfig(
            scenario="pass",
            seed=3,
            n_tie_points=n,
            n_check_points=10,
            start_lat_deg=45.0,
            duration_s=600.0 if st["small"] else 900.0,
            imagery=True,
            camera_truth=str(out / "month" / "camera_truth.h5"),
        ),
        out / "imagery",
    )
    m = run_match(out / "imagery")
    (pass_file,) = sorted((out / "imagery" / "passes").glob("*.h5"))
    for cam in ("Df", "Da", "Cf", "Ca", "Bf", "Ba", "Af", "Aa", "An"):  # the most oblique view with a GCP
        try:
            plot_match(pass_file, out / "plots", camera=cam)  # a chip, its window, the NCC surface, the LSM fit
            break
        except InputError:  # no GCP window in that camera
            continue
    a = run_adjust(out / "imagery", camera_model=out / "camera_calibrated.h5", observations="matched")
    g, t = m["gcp"], m["tie"]
    cp = [v["after"]["rms"] for v in a["checkpoint_geolocation_m"].values()]
    return (
        f"GCPs {g['matched']}/{g['candidates']} at {g['error_px']['rms']:.3f} px, tie points {t['matched']}/"
        f"{t['candidates']} at {t['error_px']['rms']:.3f} px (RMS vs truth; {g['wrong_matches'] + t['wrong_matches']} "
        f"wrong); adjusted: check points {min(cp):.0f}-{max(cp):.0f} m, co-registration <= "
        f"{max(a['coregistration_px'].values()):.2f} px"
    )


def _incremental(out: Path, st: dict[str, Any]) -> str:
    import shutil

    from misrgraph.runs.update import run_update
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    n_pass = 3 if st["small"] else 4
    run_simulate(
        ScenarioConfig(
            scenario="path",
            seed=3,
            n_passes=n_pass,
            n_tie_points=60 if st["small"] else 150,
            n_check_points=10,
            duration_s=600.0 if st["small"] else 900.0,
            start_lat_deg=55.0,
        ),
        out / "path",
    )
    shutil.rmtree(out / "state", ignore_errors=True)
    files = sorted((out / "path" / "passes").glob("*.h5"))
    last: dict[str, Any] = {}
    for i, f in enumerate(files):
        kw = (
            dict(
                camera_model=out / "path" / "camera_model.h5",
                gcp_file=out / "path" / "gcp.h5",
                dem_file=out / "path" / "dem.h5",
            )
            if i == 0
            else {}
        )
        last = run_update(out / "state", [f], compare_batch=(i == len(files) - 1), **kw)["updates"][0]
    b = last["batch"]
    return (
        f"{len(files)} repeat passes; last update {last['update_seconds']:.2f} s vs batch {b['seconds']:.2f} s, "
        f"max difference {b['max_difference_in_sigma']:.1e} sigma"
    )


def _view(out: Path, st: dict[str, Any]) -> str:
    from misrgraph.viz.viewer import run_view

    r = run_view(out / "pass_result.h5", save=out / "pass_result.rrd")
    run_view(out / "camera_calibrated.h5", save=out / "calibration.rrd")
    return f"{len(r['entities'])} entities -> pass_result.rrd, calibration.rrd (open with: rerun FILE.rrd)"


STAGES: list[tuple[str, Callable[[Path, dict[str, Any]], str]]] = [
    ("forward model sensitivity", _sensitivity),
    ("simulate a month of GCP passes", _simulate_month),
    ("calibrate the cameras", _calibrate),
    ("simulate a 45-minute pass", _simulate_pass),
    ("adjust the pass", _adjust),
    ("images: match and adjust a pass", _match),
    ("incremental update (iSAM2)", _incremental),
    ("rerun recordings + plots", _view),
]


def run_demo(
    out: str | Path, progress: Callable[[str], None] | None = None, small: bool = False
) -> list[dict[str, Any]]:
    """Run every stage; return one record per stage (name, status, summary, seconds)."""
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    state: dict[str, Any] = {"small": small}
    records = []
    for name, fn in STAGES:
        if progress:
            progress(name)
        t0 = time.perf_counter()
        summary = fn(out_dir, state)
        records.append({"stage": name, "status": "done", "summary": summary, "seconds": time.perf_counter() - t0})
        log.info("%s: %s", name, summary)
    return records
