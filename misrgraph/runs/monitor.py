"""``misrgraph monitor``: a series of calibrations tested for a change of the camera model.

The series is a CSV table with a header row and two columns: ``utc`` (the time of a calibration,
ISO 8601, e.g. the middle of its window of GCP passes) and ``calibration`` (the path of that
calibration's summary, ``misrgraph calibrate --json`` output, relative to the table). Each
camera's ``delta``, ``beta`` and ``epsilon`` (the pointing angles; their values and 1-sigma from
the summary, in arcseconds) make one series; :func:`misrgraph.evaluate.drift.monitor_cameras`
tests them all, the false-alarm probability shared among them, with process levels learned from
the calibrations before ``train_until`` (default: the first half of the series).

``view``: ``"conditional"`` (the default) tests each camera's value *given the other cameras'* at
each calibration (:func:`misrgraph.evaluate.drift.conditional_series`, from the summary's
correlation matrix and sigmas): a calibration's errors are shared across cameras, a camera that
moves moves alone, so the change stands out against the error the other cameras do not
predict. ``"marginal"`` tests each camera's own series.
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
from misrgraph.evaluate.drift import TrendLevels, conditional_series, fit_process_levels, monitor_cameras
from misrgraph.misr.orbits import format_utc, parse_utc
from misrgraph.model.constants import CAMERAS

__all__ = [
    "run_monitor",
    "summary_covariance",
    "monitored_series",
    "learn_levels",
    "MONITORED_PARAMETERS",
    "MONITOR_VIEWS",
]

#: The calibrated parameters watched per camera (radians in a summary, arcseconds here).
MONITORED_PARAMETERS = ("delta", "beta", "epsilon")
#: What the monitor tests (module docstring).
MONITOR_VIEWS = ("conditional", "marginal")
_ARCSEC = 180.0 / math.pi * 3600.0


def summary_covariance(summary: dict[str, Any], parameter: str, cameras: tuple[str, ...] = CAMERAS) -> np.ndarray:
    """The cameras' joint covariance ``(C, C)`` (rad^2) of one parameter in a calibration summary
    (``misrgraph calibrate --json``: ``cameras.<camera>.params.<parameter>.sigma`` and
    ``correlation.labels``/``matrix``, labels ``"<camera>.<parameter>"``).

    Raises
    ------
    KeyError, ValueError
        When the summary lacks one of those fields or a camera's label."""
    labels = list(summary["correlation"]["labels"])
    corr = np.asarray(summary["correlation"]["matrix"], dtype=float)
    idx = [labels.index(f"{cam}.{parameter}") for cam in cameras]
    sd = np.array([float(summary["cameras"][cam]["params"][parameter]["sigma"]) for cam in cameras])
    return corr[np.ix_(idx, idx)] * np.outer(sd, sd)


def monitored_series(
    t: np.ndarray, summaries: list[dict[str, Any]], view: str
) -> tuple[
    dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]],
    dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]],
    dict[tuple[str, str], float] | None,
]:
    """The cameras' own series (arcsec) of calibration summaries at days ``t``, the series the
    monitor tests in ``view`` (:data:`MONITOR_VIEWS`) and their gains (None for ``"marginal"``).

    Raises
    ------
    KeyError, ValueError
        When a summary lacks a field (the caller names the file)."""
    if view not in MONITOR_VIEWS:
        raise InputError("view", view, " or ".join(MONITOR_VIEWS))
    own = {
        (cam, par): (
            t,
            np.array([float(s["cameras"][cam]["params"][par]["value"]) for s in summaries]) * _ARCSEC,
            np.array([float(s["cameras"][cam]["params"][par]["sigma"]) for s in summaries]) * _ARCSEC,
        )
        for cam in CAMERAS
        for par in MONITORED_PARAMETERS
    }
    if view == "marginal":
        return own, own, None
    covs = {par: np.stack([summary_covariance(s, par) for s in summaries]) * _ARCSEC**2 for par in MONITORED_PARAMETERS}
    tested, gains = conditional_series(own, covs, CAMERAS)
    return own, tested, gains


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


def learn_levels(
    tested: dict[tuple[str, str], tuple[np.ndarray, np.ndarray, np.ndarray]],
    gains: dict[tuple[str, str], float] | None,
    cut: int,
    seasonal: bool = True,
) -> TrendLevels:
    """The cameras' process levels learned on the first ``cut`` calibrations of the series the
    monitor tests, each divided by the square root of its gain (:func:`monitored_series`)."""
    keys = list(tested)
    return fit_process_levels(
        [(tested[k][0][:cut], tested[k][1][:cut], tested[k][2][:cut]) for k in keys],
        seasonal,
        gains=None if gains is None else [gains[k] for k in keys],
    )


def _read_summary(path: Path, view: str) -> dict[str, Any]:
    try:
        s = json.loads(path.read_text())
        monitored_series(np.zeros(1), [s], view)  # every field the view needs is there
        return s
    except OSError as exc:
        raise FileFormatError(path, f"cannot read ({exc.strerror})") from None
    except (ValueError, KeyError, TypeError, IndexError, InputError) as exc:
        need = " and correlation.labels/matrix (or --view marginal)" if view == "conditional" else ""
        raise FileFormatError(
            path, f"not a calibration summary with cameras.<camera>.params.<delta|beta|epsilon>{need} ({exc!r})"
        ) from None


def run_monitor(
    table: str | os.PathLike[str],
    train_until: str | None = None,
    alpha: float = 0.05,
    seasonal: bool = True,
    view: str = "conditional",
) -> dict[str, Any]:
    """Test a table of calibrations for a change (module docstring). Return
    ``{"calibrations", "from", "to", "trained_on", "levels": {"q_level_arcsec2_per_day",
    "q_slope_arcsec2_per_day3", "slope_var_arcsec2_per_day2", "season_var_arcsec2"} (the
    cameras' levels, learned on the series tested), "alpha", "view", "alarms": [{"camera",
    "parameter", "utc", "onset_utc", "kind", "direction", "statistic", "threshold", "level_before_arcsec",
    "level_sigma_before_arcsec"}] (the levels of the series tested: in the conditional view the
    camera's given the others), "new_cgm_needed"}``."""
    if view not in MONITOR_VIEWS:
        raise InputError("--view", view, " or ".join(MONITOR_VIEWS))
    p = Path(table)
    rows = _read_table(p)
    if len(rows) < 8:
        raise InputError(f"{p.name}: calibrations", len(rows), "at least 8 (the model's start and some to test)")
    t0 = rows[0][0]
    t = np.array([(r[0] - t0).total_seconds() / 86400.0 for r in rows])
    if np.any(np.diff(t) <= 0):
        raise InputError(f"{p.name}: utc", "repeated", "one calibration per time")
    _, tested, gains = monitored_series(t, [_read_summary(r[1], view) for r in rows], view)
    cut = (
        len(rows) // 2
        if train_until is None
        else int(np.searchsorted(t, (parse_utc(train_until, "--train-until") - t0).total_seconds() / 86400.0))
    )
    if cut < 7:
        raise InputError("--train-until", train_until, "a time with at least 7 calibrations before it")
    levels = learn_levels(tested, gains, cut, seasonal)
    alarms = monitor_cameras(tested, levels, alpha, seasonal=seasonal, gains=gains)
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
        "view": view,
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
