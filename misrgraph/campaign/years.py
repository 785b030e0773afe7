"""The campaign over years: a calibration per window, the calibrations watched for a change of the
camera model, and camera-model versions by orbit range.

With ``CampaignConfig.recalibrate_months`` = ``R`` > 0 the campaign's ``months`` are cut into
windows of ``R`` months (``R x 30.4375`` days; window ``w`` covers days ``[w R, (w + 1) R)`` after
``epoch_date``). Each window gets its own GCP scenario (the month of the seed's plan, starting on
the window's first day) and its own calibration. The calibrations, in time order (each at the
middle of its GCP scenario), make the series that :func:`misrgraph.evaluate.drift.monitor_cameras`
tests -- every camera's ``delta``, ``beta`` and ``epsilon`` in arcseconds, with the 1-sigma of the
calibration's covariance, each camera given the other cameras at each calibration
(:func:`misrgraph.evaluate.drift.conditional_series`) -- with its levels learned from those
series over the first half of the windows (at least two), as ``misrgraph monitor`` does.

Versions (:func:`plan_versions`): version 1 is the first window's calibration, valid from orbit 0.
The monitor runs over the series; its earliest alarm, at window ``a``, makes the calibration of
window ``a`` a new version, valid from the first orbit of that window; the monitor then starts
again from window ``a`` (a new reference model) and runs to the end, and so on. The versions go
into a store (:mod:`misrgraph.io.cgm`) that every repeat pass is adjusted with: each pass gets the
version valid for its orbit.

A pass is **stale** when it was adjusted with a version the monitoring later found out of date:
its date falls after the last calibration that did not see the change (the one before the
estimated onset: the first window of the CUSUM run that raised the alarm) and before the new
version's first window. The calibrations date the change no closer than that, so some of these
passes may predate it.

Orbits count from ``epoch_date``: Terra flies 233 orbits in 16 days, so day ``d`` begins at orbit
``ceil(233 d / 16)`` (the simulator numbers repeat cycle ``k`` of a path as orbit ``233 k``).
"""

from __future__ import annotations

import datetime as _dt
import math
import re
from typing import Any

import numpy as np

from misrgraph.campaign.plan import DAYS_PER_MONTH, REPEAT_DAYS, SIZES, CampaignConfig
from misrgraph.evaluate.drift import monitor_cameras
from misrgraph.model.constants import CAMERAS
from misrgraph.model.orbit import REPEAT_PATHS
from misrgraph.runs.monitor import MONITORED_PARAMETERS, learn_levels, monitored_series

__all__ = [
    "MONITORED",
    "window_days",
    "window_starts",
    "calibration_days",
    "first_orbit_of_day",
    "pass_day",
    "date_of_day",
    "plan_versions",
    "stale_passes",
]

#: The calibrated parameters watched per camera (their values in radians in a summary).
MONITORED = MONITORED_PARAMETERS


def window_days(cfg: CampaignConfig) -> float:
    """The length of a calibration window (days)."""
    return float(cfg.recalibrate_months) * DAYS_PER_MONTH


def window_starts(cfg: CampaignConfig) -> list[float]:
    """The first day (after ``epoch_date``) of every calibration window of the campaign."""
    r = window_days(cfg)
    n = max(1, math.ceil(cfg.months * DAYS_PER_MONTH / r - 1e-9))
    return [w * r for w in range(n)]


def calibration_days(cfg: CampaignConfig) -> list[float]:
    """The time of every window's calibration (days after ``epoch_date``): the middle of its GCP
    scenario (the size's ``month_days`` from the window's first day)."""
    half = 0.5 * float(SIZES[cfg.size]["month"].get("month_days", 30))
    return [s + half for s in window_starts(cfg)]


def first_orbit_of_day(day: float) -> int:
    """The first orbit (counted from ``epoch_date``) that starts on or after ``day``."""
    return int(math.ceil(day * REPEAT_PATHS / REPEAT_DAYS - 1e-9))


def pass_day(pass_id: str) -> float:
    """The day (after ``epoch_date``) of a simulated repeat pass ``P<path>_O<orbit>`` (orbit
    ``233 k``: cycle ``k``, ``16 k`` days)."""
    m = re.fullmatch(r"P\d{3}_O(\d+)", pass_id)
    if m is None:
        raise ValueError(f"not a simulated pass id: {pass_id!r}")
    return int(m.group(1)) / REPEAT_PATHS * REPEAT_DAYS


def date_of_day(cfg: CampaignConfig, day: float) -> str:
    """The ISO date ``day`` days after ``epoch_date``."""
    return (_dt.date.fromisoformat(cfg.epoch_date) + _dt.timedelta(days=int(math.floor(day)))).isoformat()


def plan_versions(
    t_days: list[float], summaries: list[dict[str, Any]], alpha: float = 0.05, view: str = "conditional"
) -> dict[str, Any]:
    """The versions of the module docstring from the calibrations' summaries (``calibrate
    --json`` output, one per window, in time order at days ``t_days``); the monitor tests the
    series of ``view`` (:data:`misrgraph.runs.monitor.MONITOR_VIEWS`: by default each camera given
    the others), with the cameras' levels learned on those series. Returns ``{"series": {camera:
    {parameter: {"value_arcsec", "sigma_arcsec"}}} (the cameras' own), "view", "levels",
    "trained_on", "alarms": [{"camera", "parameter", "window", "onset_window", "kind",
    "direction", "statistic", "threshold"}], "version_windows": [0, a1, ...]}``."""
    n = len(summaries)
    t = np.asarray(t_days, dtype=float)
    series, tested, gains = monitored_series(t, summaries, view)
    cut = max(2, n // 2)
    levels = learn_levels(tested, gains, cut)
    alarms: list[dict[str, Any]] = []
    starts = [0]
    while n - starts[-1] >= 3:
        s0 = starts[-1]
        found = monitor_cameras(
            {k: (a[s0:], b[s0:], c[s0:]) for k, (a, b, c) in tested.items()}, levels, alpha, gains=gains
        )
        if not found:
            break
        first = found[0]
        at = s0 + int(first["index"])
        alarms.append(
            {
                "camera": first["camera"],
                "parameter": first["parameter"],
                "window": at,
                "onset_window": s0 + max(int(first["onset"]), 0),
                "kind": first["kind"],
                "direction": int(first["direction"]),
                "statistic": float(first["statistic"]),
                "threshold": float(first["threshold"]),
                "also": sorted(
                    {(a["camera"], a["parameter"]) for a in found if s0 + int(a["index"]) == at}
                    - {(first["camera"], first["parameter"])}
                ),
            }
        )
        starts.append(at)
    return {
        "series": {
            cam: {
                par: {"value_arcsec": series[(cam, par)][1].tolist(), "sigma_arcsec": series[(cam, par)][2].tolist()}
                for par in MONITORED
            }
            for cam in CAMERAS
        },
        "view": view,
        "levels": {
            "q_level_arcsec2_per_day": levels.q_level,
            "q_slope_arcsec2_per_day3": levels.q_slope,
            "slope_var_arcsec2_per_day2": levels.slope_var,
            "season_var_arcsec2": levels.season_var,
        },
        "trained_on": cut,
        "alarms": alarms,
        "version_windows": starts,
    }


def stale_passes(cfg: CampaignConfig, passes: dict[str, str], alarms: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The passes adjusted with a version the monitoring later found out of date (module
    docstring): ``passes`` maps each adjusted pass id to the version id it was adjusted with.
    Returns ``[{"pass_id", "date", "version", "superseded_by", "change"}]`` in date order."""
    starts, cal = window_starts(cfg), calibration_days(cfg)
    out = []
    for k, a in enumerate(alarms):
        o = a["onset_window"]
        lo, hi = (cal[o - 1] if o >= 1 else starts[0]), starts[a["window"]]
        for pid, version in passes.items():
            day = pass_day(pid)
            if lo < day < hi:
                out.append(
                    {
                        "pass_id": pid,
                        "date": date_of_day(cfg, day),
                        "version": version,
                        "superseded_by": f"v{k + 2:03d}",
                        "change": f"{a['camera']} {a['parameter']} ({a['kind']})",
                    }
                )
    return sorted(out, key=lambda r: (r["date"], r["pass_id"]))
