"""``misrgraph bench monitor``: how soon the drift monitor (:mod:`misrgraph.evaluate.drift`)
asks for a new camera model, and how often it asks for nothing.

Each campaign is a series of recalibrations of every camera (9 cameras x 3 pointing parameters,
in pixels), one every ``recalibrate_days`` over ``years``. A recalibration's estimate is the
true parameter plus an error of the calibration's own 1-sigma per camera: taken from a
calibration summary (``calibrate --json``) the user gives, or measured in the bench itself by
calibrating a standard simulated window of GCP passes as long as the time between
recalibrations (120 GCPs over ``recalibrate_days`` days: a longer window, a smaller sigma). The
true parameters wander as a random walk with an annual term (the world, which the monitor does
not know) and, per campaign kind:

* **step**: one camera's parameter (chosen at random) jumps by ``step_px`` (random sign) at a
  random recalibration in the middle of the campaign; *detected* when the first alarm comes at
  that recalibration or the next, *right_camera* when it names that camera, *delay_windows*
  the recalibrations from the step to the alarm;
* **drift**: one camera's parameter starts drifting by ``drift_px_per_year`` at a random time
  in the first half; *flagged* when an alarm on it comes before the drift reaches 1/16 px,
  *px_when_flagged* the drift by then;
* **none**: no change; the *false_alarm_rate* is the share of these campaigns with any alarm,
  against the configured ``alpha`` (shared by the 27 series of a campaign).

The monitor's process levels are learned from ``training`` other campaigns of the same world
without changes (fit on some, score on others). Fractions carry Wilson 95 % intervals, means a
Student t interval from the run-to-run scatter.

What this does not do: it draws each recalibration from its 1-sigma rather than calibrating each
window's passes, and keeps no camera-model versions (``bench cgm`` calibrates two windows around
one step and adjusts passes with each version).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.bench.studies import _interval
from misrgraph.errors import FileFormatError, InputError
from misrgraph.evaluate.drift import SEASON_DAYS, fit_process_levels, monitor_cameras
from misrgraph.model.constants import CAMERAS

__all__ = ["run_bench_monitor", "wilson_interval", "WORLD"]

#: The simulated world of the true parameters (px): a random walk of 0.005 px per sqrt(year) and
#: an annual term of 0.01 px amplitude. The monitor learns its levels from training campaigns.
WORLD = {"random_walk_px_per_sqrt_year": 0.005, "annual_px": 0.01}
_PARAMETERS = ("p1", "p2", "p3")
_SIXTEENTH = 1.0 / 16.0


def wilson_interval(k: int, n: int, z: float = 1.96) -> list[float]:
    """The Wilson score interval of a proportion ``k / n`` (95 % by default)."""
    if n == 0:
        return [float("nan"), float("nan")]
    p = k / n
    d = 1 + z**2 / n
    c = (p + z**2 / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n * n)) / d
    return [max(0.0, c - h), min(1.0, c + h)]


def _sigmas_from(
    calibration: str | Path | None, window_days: int, progress: Callable[[str], None] | None
) -> tuple[dict[str, float], str]:
    if calibration is not None:
        p = Path(calibration)
        try:
            summary = json.loads(p.read_text())
            return {c: float(summary["cameras"][c]["sigma_px"]) for c in CAMERAS}, str(p)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise FileFormatError(p, f"not a calibration summary with cameras.<camera>.sigma_px ({exc})") from None
    import tempfile

    from misrgraph.runs.calibrate import run_calibrate
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    if progress:
        progress(f"calibrating a simulated {window_days}-day window for the recalibrations' sigma")
    with tempfile.TemporaryDirectory(prefix="misrgraph-monitor-") as d:
        run_simulate(ScenarioConfig(truth="model", scenario="month", seed=3, month_days=window_days), Path(d) / "m")
        summary = run_calibrate(Path(d) / "m")
    source = f"a standard simulated window of {window_days} days (120 GCPs, seed 3)"
    return {c: float(summary["cameras"][c]["sigma_px"]) for c in CAMERAS}, source


def _campaign(
    rng: np.random.Generator, t: np.ndarray, sig: dict[str, float]
) -> dict[tuple[str, str], list[np.ndarray]]:
    """Every camera's and parameter's true series (no change) and its recalibrations' sigma."""
    q = WORLD["random_walk_px_per_sqrt_year"] ** 2 / 365.25
    out = {}
    for cam in CAMERAS:
        for par in _PARAMETERS:
            walk = np.concatenate([[0.0], np.cumsum(rng.normal(0, np.sqrt(q * np.diff(t))))])
            phase = rng.uniform(0, 2 * np.pi)
            truth = walk + WORLD["annual_px"] * np.cos(2 * np.pi * t / SEASON_DAYS + phase)
            out[(cam, par)] = [truth, np.full(t.size, sig[cam])]
    return out


def _observe(rng: np.random.Generator, t: np.ndarray, truth: dict[tuple[str, str], list[np.ndarray]]) -> dict:
    return {key: (t, tr + rng.normal(0, s), s) for key, (tr, s) in truth.items()}


def run_bench_monitor(
    campaigns: int = 20,
    years: float = 5.0,
    recalibrate_days: float = 30.0,
    calibration: str | Path | None = None,
    step_px: float = 0.1,
    drift_px_per_year: float = 0.05,
    alpha: float = 0.05,
    training: int = 5,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The study of the module docstring over ``campaigns`` campaigns of each kind. Returns
    ``{"campaigns", "years", "recalibrate_days", "alpha", "sigma_px", "sigma_source", "levels",
    "step": {"detected", "right_camera", "delay_windows", "interval"}, "drift": {"flagged",
    "px_when_flagged", "interval"}, "false_alarm_rate", "interval", "seconds"}``."""
    for name, v, ok in (
        ("campaigns", campaigns, isinstance(campaigns, int) and campaigns >= 1),
        ("years", years, years > 0.5),
        ("recalibrate_days", recalibrate_days, recalibrate_days > 0),
        ("alpha", alpha, 0 < alpha < 1),
        ("training", training, isinstance(training, int) and training >= 1),
    ):
        if not ok:
            raise InputError(
                name, v, "a positive value (campaigns, training: whole numbers; years > 0.5; alpha in (0, 1))"
            )
    t0 = time.perf_counter()
    sig, source = _sigmas_from(calibration, max(1, int(round(recalibrate_days))), progress)
    t = np.arange(0.0, years * 365.25, recalibrate_days)
    if t.size < 12:
        raise InputError("years / recalibrate_days", t.size, "at least 12 recalibrations")
    rng = np.random.default_rng(seed)
    if progress:
        progress("learning the monitor's levels from training campaigns")
    train = []
    for _ in range(training):
        for tt, yy, ss in _observe(rng, t, _campaign(rng, t, sig)).values():
            train.append((tt, yy, ss))
    levels = fit_process_levels(train[:: max(1, len(train) // 27)])
    n = t.size
    step_hits = right = 0
    delays: list[float] = []
    drift_hits = 0
    drift_px: list[float] = []
    false_alarms = 0
    for c in range(campaigns):
        if progress:
            progress(f"campaign {c + 1}/{campaigns}")
        # a step
        truth = _campaign(rng, t, sig)
        key = (CAMERAS[rng.integers(len(CAMERAS))], _PARAMETERS[rng.integers(3)])
        at = int(rng.integers(int(0.4 * n), int(0.8 * n)))
        truth[key][0] = truth[key][0] + np.where(np.arange(n) >= at, step_px * rng.choice([-1.0, 1.0]), 0.0)
        after = [a for a in monitor_cameras(_observe(rng, t, truth), levels, alpha) if a["index"] >= at]
        if after and after[0]["index"] <= at + 1:
            step_hits += 1
            delays.append(float(after[0]["index"] - at))
            right += after[0]["camera"] == key[0]
        # a drift
        truth = _campaign(rng, t, sig)
        key = (CAMERAS[rng.integers(len(CAMERAS))], _PARAMETERS[rng.integers(3)])
        start = float(rng.uniform(0.1, 0.5) * t[-1])
        drift = np.clip(t - start, 0.0, None) / 365.25 * drift_px_per_year * rng.choice([-1.0, 1.0])
        truth[key][0] = truth[key][0] + drift
        alarms = [a for a in monitor_cameras(_observe(rng, t, truth), levels, alpha) if a["camera"] == key[0]]
        alarms = [a for a in alarms if a["parameter"] == key[1] and a["t"] >= start]
        if alarms and abs(drift[int(alarms[0]["index"])]) < _SIXTEENTH:
            drift_hits += 1
            drift_px.append(float(abs(drift[int(alarms[0]["index"])])))
        # no change
        false_alarms += bool(monitor_cameras(_observe(rng, t, _campaign(rng, t, sig)), levels, alpha))
    delay_iv = _interval(delays) if delays else {"mean": float("nan"), "ci95": [float("nan")] * 2}
    px_iv = _interval(drift_px) if drift_px else {"mean": float("nan"), "ci95": [float("nan")] * 2}
    return {
        "campaigns": campaigns,
        "years": years,
        "recalibrate_days": recalibrate_days,
        "recalibrations": int(n),
        "alpha": alpha,
        "sigma_px": sig,
        "sigma_source": source,
        "world": WORLD,
        "levels": {
            "q_level_px2_per_day": levels.q_level,
            "q_slope_px2_per_day3": levels.q_slope,
            "slope_var_px2_per_day2": levels.slope_var,
            "season_var_px2": levels.season_var,
        },
        "step": {
            "step_px": step_px,
            "detected": step_hits / campaigns,
            "right_camera": right / campaigns,
            "delay_windows": delay_iv["mean"],
            "interval": {
                "detected": wilson_interval(step_hits, campaigns),
                "right_camera": wilson_interval(right, campaigns),
                "delay_windows": delay_iv["ci95"],
            },
        },
        "drift": {
            "drift_px_per_year": drift_px_per_year,
            "flagged": drift_hits / campaigns,
            "px_when_flagged": px_iv["mean"],
            "interval": {"flagged": wilson_interval(drift_hits, campaigns), "px_when_flagged": px_iv["ci95"]},
        },
        "false_alarm_rate": false_alarms / campaigns,
        "interval": {"false_alarm_rate": wilson_interval(false_alarms, campaigns)},
        "seconds": time.perf_counter() - t0,
    }
