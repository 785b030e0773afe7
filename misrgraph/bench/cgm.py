"""``misrgraph bench cgm``: passes after a camera step adjusted with the new camera-model version
against the stale one, paired pass by pass.

One instrument (its true camera drawn once) is flown through four stretches of time:

1. a window of GCP passes (``window_days``, ``gcps`` GCPs) calibrated from the simulated
   supplied model: version 1;
2. ``passes`` repeat passes of one path (one every 16 days) before the step;
3. the step: ``step_camera``'s ``delta`` moves by ``step_px`` (its pointing, RMS over the swath,
   red band), then a second window calibrated starting from version 1: version 2;
4. ``passes`` repeat passes after the step, drawn with the same seed as those before it: pass by
   pass the same path and the same attitude and navigation error draws, on later dates (the
   instrument after the step; the landmarks within a few km of the earlier ones, where the later
   date's ground track puts them).

Both versions go into a camera-model store (:mod:`misrgraph.io.cgm`) with their orbit ranges,
each pass is adjusted with the version the store picks for it and, after the step, also with
the stale version 1 (its file given directly). Per pass: the check points' geolocation RMS (m),
the stepped camera's co-registration with An (px RMS over the check points) and the camera
corrections' NEES. The figures: means with 95 % intervals over the passes (Student t), and
differences paired pass by pass with theirs: stale minus new version after the step, and each of
them minus the same pass before the step ("as good as before" is a difference near zero).

Every level comes from the calibrations and the simulator's defaults; the scenarios use the
independent truth.
"""

from __future__ import annotations

import datetime as _dt
import math
import shutil
import time
from pathlib import Path
from typing import Any, Callable

from misrgraph.bench.studies import _checkpoint_rms_after, _interval
from misrgraph.bench.work import bench_workdir
from misrgraph.errors import InputError
from misrgraph.model.constants import CAMERAS

__all__ = ["run_bench_cgm", "step_arcsec", "ROWS"]

#: The study's rows (result key, label) in the order the CLI and the results page show them.
ROWS = (
    ("before", "before the step (version 1)"),
    ("after_new", "after the step, the new version"),
    ("after_stale", "after the step, the stale version"),
    ("stale_minus_new", "stale minus new, paired"),
    ("new_minus_before", "new version minus the same pass before the step"),
    ("stale_minus_before", "stale version minus the same pass before the step"),
)

_EPOCH = _dt.date(2003, 1, 1)
_REPEAT_DAYS = 16


def step_arcsec(camera: str, step_px: float) -> float:
    """The change of ``camera``'s ``delta`` (arcsec) that moves its pointing by ``step_px``
    (RMS over the swath, red band, in the nominal model; linear in the step)."""
    from misrgraph.estimate.calibrate import pointing_error_px
    from misrgraph.model.constants import ARCSEC
    from misrgraph.model.nominal import nominal_camera_model

    m = nominal_camera_model()
    c = CAMERAS.index(camera)
    moved = m.copy()
    moved.add_correction("delta", c, None, 1.0 * ARCSEC)
    return float(step_px / pointing_error_px(moved, m, c))


def _pass_scores(summary: dict[str, Any], camera: str) -> dict[str, float]:
    co = summary.get("coregistration_px") or {}
    return {
        "checkpoint_rms_m": float(_checkpoint_rms_after(summary) or math.nan),
        "coregistration_px": float(co.get(camera, math.nan)),
        "camera_nees": float(summary.get("nees", {}).get("camera", math.nan)),
    }


def _summary(rows: list[dict[str, float]]) -> dict[str, Any]:
    return {k: _interval([r[k] for r in rows]) for k in rows[0]} if rows else {}


def run_bench_cgm(
    passes: int = 6,
    window_days: int = 30,
    gcps: int = 120,
    step_camera: str = "Da",
    step_px: float = 0.1,
    tie_points: int = 40,
    pass_duration_s: float = 600.0,
    seed: int = 0,
    workdir: str | Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The study of the module docstring. Returns ``{"passes", "window_days", "gcps",
    "step": {"camera", "px", "arcsec", "date"}, "versions", "before", "after_new",
    "after_stale", "stale_minus_new", "new_minus_before", "stale_minus_before", "seconds"}``; each
    figure ``{"mean", "ci95"}``."""
    from misrgraph.io.cgm import open_store
    from misrgraph.io.passes import OrbitPass
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.runs.calibrate import run_calibrate
    from misrgraph.runs.cgm import run_cgm_add
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    for name, v, ok in (
        ("passes", passes, isinstance(passes, int) and passes >= 2),
        ("window_days", window_days, isinstance(window_days, int) and window_days >= 1),
        ("gcps", gcps, isinstance(gcps, int) and gcps >= 10),
        ("step_px", step_px, step_px > 0),
    ):
        if not ok:
            raise InputError(name, v, "passes >= 2, window_days >= 1, gcps >= 10 (whole numbers); step_px > 0")
    if step_camera not in CAMERAS:
        raise InputError("step_camera", step_camera, CAMERAS)
    t0 = time.perf_counter()
    arcsec = step_arcsec(step_camera, step_px)
    before_start = _EPOCH + _dt.timedelta(days=window_days + 5)
    step_day = before_start + _dt.timedelta(days=_REPEAT_DAYS * passes + 5)
    window2 = step_day + _dt.timedelta(days=5)
    after_start = window2 + _dt.timedelta(days=window_days + 5)
    step = ((step_day.isoformat(), step_camera, "delta", arcsec),)
    with bench_workdir(workdir, "misrgraph-bench-cgm-") as wd:

        def simulate(name: str, **kw: Any) -> Path:
            d = wd / name
            if not (d / "scenario.json").exists():
                if progress:
                    progress(f"simulating {name}")
                run_simulate(ScenarioConfig.from_dict({"start_lat_deg": 50.0, **kw}), d)
            return d

        w1 = simulate("window1", scenario="month", seed=seed, n_gcps=gcps, month_days=window_days,
                      epoch_date=_EPOCH.isoformat())  # fmt: skip
        truth = str(w1 / "camera_truth.h5")  # the instrument, before the step
        common = {"camera_truth": truth, "camera_steps": step, "camera_epoch_date": _EPOCH.isoformat()}
        # one path's repeat cycles counted from before_start (cycle k: 16 k days on, orbit 233 k),
        # so that the passes after the step have later orbits than those before it
        k0 = -(-(after_start - before_start).days // _REPEAT_DAYS)
        path = {"scenario": "path", "n_tie_points": tie_points, "n_check_points": 10, "duration_s": pass_duration_s,
                "epoch_date": before_start.isoformat()}  # fmt: skip
        before = simulate("before", seed=seed + 1, repeat_indices=tuple(range(passes)), **path, **common)
        w2 = simulate("window2", scenario="month", seed=seed + 2, n_gcps=gcps, month_days=window_days,
                      epoch_date=window2.isoformat(), **common)  # fmt: skip
        after = simulate("after", seed=seed + 1, repeat_indices=tuple(range(k0, k0 + passes)), **path, **common)
        if progress:
            progress("calibrating window 1")
        v1, v2 = wd / "cgm_v1.h5", wd / "cgm_v2.h5"
        cal1 = run_calibrate(w1, out=v1)
        if progress:
            progress("calibrating window 2 (from version 1)")
        cal2 = run_calibrate(w2, camera_model=v1, out=v2)
        before_files = sorted((before / "passes").glob("*.h5"))
        after_files = sorted((after / "passes").glob("*.h5"))
        first_after = min(OrbitPass.load(f).orbit for f in after_files)
        store = wd / "cgm"
        if store.exists():
            shutil.rmtree(store)
        run_cgm_add(store, v1, 0, reason="window 1")
        run_cgm_add(store, v2, first_after, reason=f"window 2, after the step in {step_camera}")
        rows: dict[str, list[dict[str, float]]] = {"before": [], "after_new": [], "after_stale": []}
        used = []
        for i, f in enumerate(before_files):
            if progress:
                progress(f"adjusting pass {i + 1}/{passes} before the step")
            s = run_adjust(before, camera_model=store, pass_file=f)
            used.append(("before", s["camera_model_version"]["id"]))
            rows["before"].append(_pass_scores(s, step_camera))
        for i, f in enumerate(after_files):
            if progress:
                progress(f"adjusting pass {i + 1}/{passes} after the step (the store's version and the stale one)")
            s_new = run_adjust(after, camera_model=store, pass_file=f)
            used.append(("after", s_new["camera_model_version"]["id"]))
            rows["after_new"].append(_pass_scores(s_new, step_camera))
            rows["after_stale"].append(_pass_scores(run_adjust(after, camera_model=v1, pass_file=f), step_camera))

        def minus(a: str, b: str) -> list[dict[str, float]]:
            return [{k: x[k] - y[k] for k in x} for x, y in zip(rows[a], rows[b])]

        versions = [v.id + " " + v.orbits_text() for v in open_store(store).versions]
    return {
        "passes": passes,
        "window_days": window_days,
        "gcps": gcps,
        "step": {"camera": step_camera, "px": step_px, "arcsec": arcsec, "date": step_day.isoformat()},
        "calibration_sigma_px": {
            "version1": cal1["cameras"][step_camera]["sigma_px"],
            "version2": cal2["cameras"][step_camera]["sigma_px"],
        },
        "versions": versions,
        "versions_used": {k: sorted({v for w, v in used if w == k}) for k in ("before", "after")},
        "before": _summary(rows["before"]),
        "after_new": _summary(rows["after_new"]),
        "after_stale": _summary(rows["after_stale"]),
        "stale_minus_new": _summary(minus("after_stale", "after_new")),
        "new_minus_before": _summary(minus("after_new", "before")),
        "stale_minus_before": _summary(minus("after_stale", "before")),
        "per_pass": rows,
        "seconds": time.perf_counter() - t0,
    }
