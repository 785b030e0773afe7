"""``misrgraph bench monitor``: how soon the drift monitor (:mod:`misrgraph.evaluate.drift`)
asks for a new camera model, and how often it asks for nothing.

Each campaign is a series of recalibrations of every camera (9 cameras x 3 pointing parameters,
``delta``, ``beta``, ``epsilon``, in pixels: the pointing change a parameter's change makes, RMS
over the swath), one every ``recalibrate_days`` over ``years``. A recalibration's estimate is the
true parameter plus an error of the calibration's own 1-sigma of that camera and parameter (its
``sigma_px``: the pointing change when the parameter alone moves by its 1 sigma), the nine
cameras' errors of one parameter correlated as the calibration's covariance says (a calibration's
errors are shared across cameras): taken from a calibration summary (``calibrate --json``) the
user gives, or measured in the bench itself by calibrating a standard simulated window of GCP
passes as long as the time between recalibrations (120 GCPs over ``recalibrate_days`` days: a
longer window, a smaller sigma). The monitor tests the series of ``view``
(:data:`misrgraph.runs.monitor.MONITOR_VIEWS`: by default each camera given the others at each
recalibration, :func:`misrgraph.evaluate.drift.conditional_series`). The
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
without changes (fit on some, score on others), from the series the monitor tests. Fractions
carry Wilson 95 % intervals, means a Student t interval from the run-to-run scatter.

What this does not do: it draws each recalibration from its covariance rather than calibrating
each window's passes (every window with the one calibration's covariance; the three parameters
drawn independently of each other), and keeps no camera-model versions (``bench cgm`` calibrates two windows around
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
from misrgraph.evaluate.drift import SEASON_DAYS, conditional_series, fit_process_levels, monitor_cameras
from misrgraph.model.constants import CAMERAS
from misrgraph.runs.monitor import MONITOR_VIEWS, MONITORED_PARAMETERS, summary_covariance

__all__ = ["run_bench_monitor", "wilson_interval", "WORLD"]

#: The simulated world of the true parameters (px): a random walk of 0.005 px per sqrt(year) and
#: an annual term of 0.01 px amplitude. The monitor learns its levels from training campaigns.
WORLD = {"random_walk_px_per_sqrt_year": 0.005, "annual_px": 0.01}
_PARAMETERS = MONITORED_PARAMETERS
_SIXTEENTH = 1.0 / 16.0
#: per (camera, parameter) the recalibration's 1 sigma (px); per parameter the cameras' covariance (px^2)
_Recalibration = tuple[dict[tuple[str, str], float], dict[str, np.ndarray]]


def wilson_interval(k: int, n: int, z: float = 1.96) -> list[float]:
    """The Wilson score interval of a proportion ``k / n`` (95 % by default)."""
    if n == 0:
        return [float("nan"), float("nan")]
    p = k / n
    d = 1 + z**2 / n
    c = (p + z**2 / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z**2 / (4 * n * n)) / d
    return [max(0.0, c - h), min(1.0, c + h)]


def _parameter_sigmas(summary: dict[str, Any]) -> _Recalibration:
    """Each camera's and monitored parameter's ``sigma_px`` in a calibration summary, and per
    parameter the cameras' joint covariance in px^2 (their correlation from the summary)."""
    sig = {(c, par): float(summary["cameras"][c]["params"][par]["sigma_px"]) for c in CAMERAS for par in _PARAMETERS}
    cov = {}
    for par in _PARAMETERS:
        rad = summary_covariance(summary, par)
        sd = np.sqrt(np.diag(rad))
        px = np.array([sig[c, par] for c in CAMERAS])
        cov[par] = rad / np.outer(sd, sd) * np.outer(px, px)
    return sig, cov


def _sigmas_from(
    calibration: str | Path | None, window_days: int, progress: Callable[[str], None] | None
) -> tuple[_Recalibration, str]:
    if calibration is not None:
        p = Path(calibration)
        try:
            return _parameter_sigmas(json.loads(p.read_text())), str(p)
        except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
            raise FileFormatError(
                p,
                "not a calibration summary with cameras.<camera>.params.<delta|beta|epsilon>.sigma_px and "
                f"correlation.labels/matrix ('misrgraph calibrate --json'; missing or bad: {exc})",
            ) from None
    import tempfile

    from misrgraph.runs.calibrate import run_calibrate
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    if progress:
        progress(f"calibrating a simulated {window_days}-day window for the recalibrations' sigma")
    with tempfile.TemporaryDirectory(prefix="misrgraph-monitor-") as d:
        run_simulate(ScenarioConfig(truth="model", scenario="month", seed=3, month_days=window_days), Path(d) / "m")
        summary = run_calibrate(Path(d) / "m")
    source = f"a standard simulated window of {window_days} days (120 GCPs, seed 3)"
    return _parameter_sigmas(summary), source


def _campaign(
    rng: np.random.Generator, t: np.ndarray, sig: dict[tuple[str, str], float]
) -> dict[tuple[str, str], list[np.ndarray]]:
    """Every camera's and parameter's true series (no change) and its recalibrations' sigma."""
    q = WORLD["random_walk_px_per_sqrt_year"] ** 2 / 365.25
    out = {}
    for cam in CAMERAS:
        for par in _PARAMETERS:
            walk = np.concatenate([[0.0], np.cumsum(rng.normal(0, np.sqrt(q * np.diff(t))))])
            phase = rng.uniform(0, 2 * np.pi)
            truth = walk + WORLD["annual_px"] * np.cos(2 * np.pi * t / SEASON_DAYS + phase)
            out[(cam, par)] = [truth, np.full(t.size, sig[cam, par])]
    return out


def _observe(
    rng: np.random.Generator,
    t: np.ndarray,
    truth: dict[tuple[str, str], list[np.ndarray]],
    cov: dict[str, np.ndarray],
) -> dict:
    """The recalibrations: every parameter's nine cameras with errors drawn jointly from ``cov``."""
    out = {}
    for par in _PARAMETERS:
        err = rng.standard_normal((t.size, len(CAMERAS))) @ np.linalg.cholesky(cov[par]).T
        for i, cam in enumerate(CAMERAS):
            tr, s = truth[cam, par]
            out[cam, par] = (t, tr + err[:, i], s)
    return out


def _tested(series: dict, cov: dict[str, np.ndarray], view: str) -> tuple[dict, dict[tuple[str, str], float] | None]:
    """The series the monitor tests in ``view`` and their gains."""
    if view == "marginal":
        return series, None
    n = next(iter(series.values()))[0].size
    return conditional_series(series, {p: np.broadcast_to(c, (n, *c.shape)) for p, c in cov.items()}, CAMERAS)


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
    view: str = "conditional",
) -> dict[str, Any]:
    """The study of the module docstring over ``campaigns`` campaigns of each kind. Returns
    ``{"campaigns", "years", "recalibrate_days", "alpha", "sigma_px" (camera -> parameter -> px),
    "view", "sigma_source", "levels",
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
    if view not in MONITOR_VIEWS:
        raise InputError("view", view, " or ".join(MONITOR_VIEWS))
    (sig, cov), source = _sigmas_from(calibration, max(1, int(round(recalibrate_days))), progress)

    def alarms_of(truth: dict[tuple[str, str], list[np.ndarray]]) -> list[dict[str, Any]]:
        tested, gains = _tested(_observe(rng, t, truth, cov), cov, view)
        return monitor_cameras(tested, levels, alpha, gains=gains)

    t = np.arange(0.0, years * 365.25, recalibrate_days)
    if t.size < 12:
        raise InputError("years / recalibrate_days", t.size, "at least 12 recalibrations")
    rng = np.random.default_rng(seed)
    if progress:
        progress("learning the monitor's levels from training campaigns")
    train = []
    train_gains: list[float] = []
    for _ in range(training):
        tested, gains = _tested(_observe(rng, t, _campaign(rng, t, sig), cov), cov, view)
        for key, one in tested.items():
            train.append(one)
            train_gains.append(1.0 if gains is None else gains[key])
    every = max(1, len(train) // 27)
    levels = fit_process_levels(train[::every], gains=train_gains[::every])
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
        after = [a for a in alarms_of(truth) if a["index"] >= at]
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
        alarms = [a for a in alarms_of(truth) if a["camera"] == key[0]]
        alarms = [a for a in alarms if a["parameter"] == key[1] and a["t"] >= start]
        if alarms and abs(drift[int(alarms[0]["index"])]) < _SIXTEENTH:
            drift_hits += 1
            drift_px.append(float(abs(drift[int(alarms[0]["index"])])))
        # no change
        false_alarms += bool(alarms_of(_campaign(rng, t, sig)))
    delay_iv = _interval(delays) if delays else {"mean": float("nan"), "ci95": [float("nan")] * 2}
    px_iv = _interval(drift_px) if drift_px else {"mean": float("nan"), "ci95": [float("nan")] * 2}
    return {
        "campaigns": campaigns,
        "years": years,
        "recalibrate_days": recalibrate_days,
        "recalibrations": int(n),
        "alpha": alpha,
        "sigma_px": {c: {par: sig[c, par] for par in _PARAMETERS} for c in CAMERAS},
        "view": view,
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
