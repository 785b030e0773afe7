"""``misrgraph monitor``: a series of calibrations tested for a change of the camera model.

The series is a CSV table with a header row and two columns: ``utc`` (the time of a calibration,
ISO 8601, e.g. the middle of its window of GCP passes) and ``calibration`` (the path of that
calibration's summary, ``misrgraph calibrate --json`` output, relative to the table). Each
camera's ``delta``, ``beta`` and ``epsilon`` (the pointing angles; their values and 1-sigma from
the summary, in arcseconds) make one series; :func:`misrgraph.evaluate.drift.monitor_cameras`
tests them all, the false-alarm probability shared among them, with process levels learned from
the calibrations before ``train_until`` (default: the first half of the series).
"""

from __future__ import annotations

import csv
import datetime as _dt
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from misrgraph.errors import FileFormatError, InputError
from misrgraph.evaluate.drift import fit_process_levels, monitor_cameras
from misrgraph.misr.orbits import format_utc, parse_utc
from misrgraph.model.constants import CAMERAS

__all__ = ["run_monitor", "MONITORED_PARAMETERS"]

#: The calibrated parameters watched per camera (radians in a summary, arcseconds here).
MONITORED_PARAMETERS = ("delta", "beta", "epsilon")
_ARCSEC = 180.0 / math.pi * 3600.0


def _read_table(path: Path) -> list[tuple[_dt.datetime, Path]]:
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise FileFormatError(path, f"cannot read ({exc.strerror})") from None
    if not rows or not {"utc", "calibration"} <= set(rows[0]):
        raise FileFormatError(path, "not a table with the columns utc, calibration (header row)")
    out = []
    for i, r in enumerate(rows, start=2):
        t = parse_utc(r["utc"], f"{path.name} line {i}: utc")
        out.append((t, (path.parent / r["calibration"]).resolve()))
    return sorted(out)


def _read_summary(path: Path) -> dict[str, Any]:
    try:
        s = json.loads(path.read_text())
        cams = s["cameras"]
        return {
            (cam, p): (float(cams[cam]["params"][p]["value"]), float(cams[cam]["params"][p]["sigma"]))
            for cam in CAMERAS
            for p in MONITORED_PARAMETERS
        }
    except OSError as exc:
        raise FileFormatError(path, f"cannot read ({exc.strerror})") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise FileFormatError(
            path, f"not a calibration summary with cameras.<camera>.params.<delta|beta|epsilon> ({exc!r})"
        ) from None


def run_monitor(
    table: str | os.PathLike[str],
    train_until: str | None = None,
    alpha: float = 0.05,
    seasonal: bool = True,
) -> dict[str, Any]:
    """Test a table of calibrations for a change (module docstring). Return
    ``{"calibrations", "from", "to", "trained_on", "levels": {"q_level_arcsec2_per_day",
    "q_slope_arcsec2_per_day3", "slope_var_arcsec2_per_day2", "season_var_arcsec2"},
    "alpha", "alarms": [{"camera", "parameter", "utc", "onset_utc", "kind",
    "direction", "statistic", "threshold", "level_before_arcsec", "level_sigma_before_arcsec"}],
    "new_cgm_needed"}``."""
    p = Path(table)
    rows = _read_table(p)
    if len(rows) < 8:
        raise InputError(f"{p.name}: calibrations", len(rows), "at least 8 (the model's start and some to test)")
    t0 = rows[0][0]
    t = np.array([(r[0] - t0).total_seconds() / 86400.0 for r in rows])
    if np.any(np.diff(t) <= 0):
        raise InputError(f"{p.name}: utc", "repeated", "one calibration per time")
    values = [_read_summary(r[1]) for r in rows]
    series = {
        key: (t, np.array([v[key][0] for v in values]) * _ARCSEC, np.array([v[key][1] for v in values]) * _ARCSEC)
        for key in values[0]
    }
    cut = (
        len(rows) // 2
        if train_until is None
        else int(np.searchsorted(t, (parse_utc(train_until, "--train-until") - t0).total_seconds() / 86400.0))
    )
    if cut < 7:
        raise InputError("--train-until", train_until, "a time with at least 7 calibrations before it")
    levels = fit_process_levels([(s[0][:cut], s[1][:cut], s[2][:cut]) for s in series.values()], seasonal)
    alarms = monitor_cameras(series, levels, alpha, seasonal=seasonal)
    return {
        "calibrations": len(rows),
        "from": format_utc(rows[0][0]),
        "to": format_utc(rows[-1][0]),
        "trained_on": cut,
        "levels": {
            "q_level_arcsec2_per_day": levels.q_level,
            "q_slope_arcsec2_per_day3": levels.q_slope,
            "slope_var_arcsec2_per_day2": levels.slope_var,
            "season_var_arcsec2": levels.season_var,
        },
        "alpha": alpha,
        "alarms": [
            {
                "camera": a["camera"],
                "parameter": a["parameter"],
                "utc": format_utc(rows[int(a["index"])][0]),
                "onset_utc": format_utc(rows[max(int(a["onset"]), 0)][0]),
                "kind": a["kind"],
                "direction": a["direction"],
                "statistic": a["statistic"],
                "threshold": a["threshold"],
                "level_before_arcsec": a["level_before"],
                "level_sigma_before_arcsec": a["level_sigma_before"],
            }
            for a in alarms
        ],
        "new_cgm_needed": bool(alarms),
    }
