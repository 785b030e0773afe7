"""The campaign's tasks: what a worker runs. Plain functions of paths and plain data, so that they
run the same in this process (``workers=0``) and on any Dask worker that sees the campaign
directory (a shared filesystem, as in every Dask deployment on a cluster).

Each task

* names its output by a digest of its inputs' own SHA-256 and its configuration
  (:func:`misrgraph.campaign.plan.digest`) and returns at once when that output exists -- a rerun
  redoes nothing that is done;
* writes its output atomically (a file through :func:`misrgraph.io.h5.atomic_h5`, a directory
  built under a hidden temporary name and renamed), so a SIGKILL at any point leaves either no
  output or a complete one, and two executions of the same task (a worker lost after it wrote,
  its task rescheduled) write the same bytes under the same name;
* never raises: a failure comes back as a record with ``status: "failed"`` and the reason, and
  the tasks that need its output report ``"needs <what>, which failed"`` instead of running.

A record: ``{"stage", "name", "status" ("done" | "failed"), "skipped" (found done), "output",
"seconds", "started"/"ended" (Unix time), "worker_pid", "summary" | "reason"}``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.campaign.plan import SIZES, CampaignConfig, digest
from misrgraph.errors import FileFormatError, MisrGraphError
from misrgraph.io.h5 import make_temp_dir

__all__ = [
    "simulate_month",
    "simulate_path",
    "existing_inputs",
    "calibrate",
    "camera_versions",
    "fit_noise",
    "adjust",
    "path_products",
    "SUMMARY_FILE",
]

log = logging.getLogger(__name__)

#: the summary a path's output directory holds
SUMMARY_FILE = "path.json"


def _task(
    stage: str, name: str, needs: tuple[dict[str, Any], ...], body: Callable[[], tuple[Path, bool, dict[str, Any]]]
) -> dict[str, Any]:
    """Run ``body`` (returning output, skipped, summary) into a record; never raises."""
    t0 = time.perf_counter()
    rec: dict[str, Any] = {
        "stage": stage,
        "name": name,
        "status": "failed",
        "skipped": False,
        "output": None,
        "started": time.time(),
        "worker_pid": os.getpid(),
    }
    failed = [n for n in needs if n.get("status") != "done"]
    if failed:
        rec["reason"] = "needs " + ", ".join(f"{n['stage']} {n['name']}" for n in failed) + ", which failed"
    else:
        try:
            out, skipped, summary = body()
            rec.update(status="done", skipped=skipped, output=str(out), summary=summary)
        except MisrGraphError as exc:
            rec["reason"] = f"{exc.__class__.__name__}: {exc}"
        except Exception as exc:  # a bug or an environment failure: keep its traceback for the report
            rec["reason"] = f"{exc.__class__.__name__}: {exc}"
            rec["traceback"] = traceback.format_exc(limit=8)
            log.exception("%s %s failed", stage, name)
    rec["seconds"] = time.perf_counter() - t0
    rec["ended"] = time.time()
    return rec


def _sha(path: Path) -> str:
    """The content digest a misrgraph file carries (SHA-256 over its datasets and attributes,
    :func:`misrgraph.io.h5.content_digest`). Not the whole-file SHA-256: HDF5 leaves unused bytes
    of its metadata blocks uninitialised, so two writes of the same content may differ byte-wise."""
    import h5py

    from misrgraph.io.h5 import DIGEST_ATTR

    try:
        with h5py.File(path, "r") as f:
            return str(f.attrs[DIGEST_ATTR])
    except (OSError, KeyError):
        raise FileFormatError(path, "not a complete misrgraph file (no content digest)") from None


def _scenario_sha(d: Path) -> dict[str, Any]:
    """The SHA-256 of every file of a scenario directory misrgraph reads."""
    return {
        "passes": {f.name: _sha(f) for f in sorted((d / "passes").glob("*.h5"))},
        **{n: _sha(d / n) for n in ("camera_model.h5", "gcp.h5", "dem.h5") if (d / n).exists()},
    }


@contextlib.contextmanager
def _building(final: Path) -> Any:
    """A hidden temporary sibling directory that becomes ``final`` when the block succeeds (if
    another execution of the same task got there first, its identical output is kept)."""
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = make_temp_dir(f".{final.name}.", final.parent, suffix=".tmp")
    try:
        yield tmp
        try:
            os.rename(tmp, final)
        except OSError:
            if not final.is_dir():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---------------------------------------------------------------------------- inputs
def _scenario_cfg(cfg: CampaignConfig, kind: str, **extra: Any) -> dict[str, Any]:
    change = {**cfg.camera_change, "camera_epoch_date": cfg.epoch_date} if cfg.camera_change else {}
    return {
        "scenario": kind,
        "truth": cfg.truth,
        "epoch_date": cfg.epoch_date,
        **SIZES[cfg.size][kind],
        **change,
        **extra,
    }


def _simulate(out_dir: Path, scfg: dict[str, Any], match: bool = False) -> tuple[Path, bool, dict[str, Any]]:
    """Simulate a scenario into ``out_dir`` (atomically, :func:`misrgraph.sim.simulate.run_simulate`)
    unless it is there; with ``match``, then match every pass that has no matched set yet
    (``misrgraph match``: each pass file is replaced atomically and the matching is deterministic,
    so a run killed part-way matches the rest on the rerun)."""
    from misrgraph.sim.simulate import ScenarioConfig, run_simulate

    skipped = (out_dir / "scenario.json").exists()
    s = (
        json.loads((out_dir / "scenario.json").read_text())
        if skipped
        else run_simulate(ScenarioConfig.from_dict(scfg), out_dir)
    )
    summary = {"passes": s["passes"], "observations": s["observations"]}
    if match:
        skipped = _match_missing(out_dir, summary) and skipped
    return out_dir, skipped, summary


def _match_missing(d: Path, summary: dict[str, Any]) -> bool:
    """Match the scenario's passes when any has no matched set; add the matched counts to
    ``summary``; True when every pass was matched already."""
    from misrgraph.io.imagery import has_matched, read_matched_summary
    from misrgraph.runs.match import run_match

    files = sorted((d / "passes").glob("*.h5"))
    done = all(has_matched(f) for f in files)
    if not done:
        run_match(d)
    counts = {"gcp": 0, "tie": 0}
    for f in files:
        m = read_matched_summary(f) or {}
        for kind in counts:
            counts[kind] += int((m.get(kind) or {}).get("matched", 0))
    summary["matched"] = counts
    return done


def simulate_month(
    out: str, cfg: CampaignConfig, window: int = 0, first: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Simulate the GCP month into ``OUT/inputs/month-<digest>`` (with ``cfg.observations ==
    "matched"``, with its GCP chips and windows, and matched). ``window`` > 0: the GCP scenario of
    that calibration window of a campaign over years (:mod:`misrgraph.campaign.years`), starting
    on the window's first day, with GCPs of its own, flying the instrument of the first window's
    scenario ``first`` (its ``camera_truth.h5``) as it is on each pass's date."""
    matched = cfg.observations == "matched"
    name = "month" if window == 0 else f"month {window + 1}"

    def body() -> tuple[Path, bool, dict[str, Any]]:
        extra: dict[str, Any] = {"seed": cfg.seed}
        if window:
            from misrgraph.campaign.years import date_of_day, window_starts

            if first is None:
                raise MisrGraphError(f"window {window + 1}'s GCP scenario needs the first window's (its instrument)")
            truth = Path(first["output"]) / "camera_truth.h5"
            seed = int.from_bytes(bytes.fromhex(digest("window seed", cfg.seed, window)[:8]), "big")
            extra = {
                "seed": seed,
                "epoch_date": date_of_day(cfg, window_starts(cfg)[window]),
                "camera_truth": str(truth),
            }
        scfg = _scenario_cfg(cfg, "month", **extra, **({"imagery": True} if matched else {}))
        d = Path(out) / "inputs" / f"month-{digest(scfg)[:12]}"
        return _simulate(d, scfg, matched)

    return _task("inputs", name, () if first is None else (first,), body)


def mid_pass_block(scfg: dict[str, Any]) -> int:
    """The SOM block (1.1 km grid) under the nadir point half-way through the pass a path
    scenario configuration ``scfg`` describes."""
    from misrgraph.misr.som import SomGrid
    from misrgraph.model.frames import EarthOrientation, ecef_to_geodetic
    from misrgraph.model.orbit import terra_like_orbit
    from misrgraph.sim.simulate import ScenarioConfig

    sc = ScenarioConfig.from_dict(scfg)
    eph = terra_like_orbit(
        epoch_date=sc.epoch_date, path=sc.path, start_lat_deg=sc.start_lat_deg, duration_s=sc.duration_s
    )
    t = np.array([eph.t[0] + 0.5 * sc.duration_s])
    lat, lon, _ = ecef_to_geodetic(EarthOrientation(eph.epoch_utc).eci_to_ecef(t)[0] @ eph.interpolate(t)[0][0])
    return int(np.ravel(SomGrid(sc.path, 1100).latlon_to_bls(lat, lon)[0])[0])


def simulate_path(
    out: str, cfg: CampaignConfig, path: int, cycles: tuple[int, ...], month: dict[str, Any]
) -> dict[str, Any]:
    """Simulate the chosen repeat passes of ``path`` (the month's instrument: its true camera
    model) into ``OUT/inputs/path_PPP-<digest>``; with ``cfg.roi``, with whole-swath strips of
    ``cfg.roi_blocks`` blocks from the one under the middle of the pass (clouds over 20 % of the
    sky) and the SOM DEM the ROI is made with; with ``cfg.observations == "matched"``, with the
    tie points' and GCPs' windows and chips, and matched."""

    def body() -> tuple[Path, bool, dict[str, Any]]:
        truth = Path(month["output"]) / "camera_truth.h5"
        seed = int.from_bytes(bytes.fromhex(digest("path seed", cfg.seed, path)[:8]), "big")
        scfg = _scenario_cfg(cfg, "path", seed=seed, path=path, repeat_indices=list(cycles), camera_truth=str(truth))
        matched = cfg.observations == "matched"
        if matched:
            scfg.update(imagery=True)
        if cfg.roi:
            b0 = mid_pass_block(scfg)
            scfg.update(
                imagery=True, cloud_fraction=0.2, feature_windows=matched, roi_blocks=[b0, b0 + cfg.roi_blocks - 1]
            )
        d = Path(out) / "inputs" / f"path_{path:03d}-{digest(scfg, _sha(truth))[:12]}"
        return _simulate(d, scfg, matched)

    return _task("inputs", f"path {path}", (month,), body)


def existing_inputs(name: str, directory: str, observations: str = "simulated") -> dict[str, Any]:
    """A record for a scenario directory the user brought (checked to exist; for ``observations
    == "matched"``, every pass checked to hold what ``misrgraph match`` measured)."""

    def body() -> tuple[Path, bool, dict[str, Any]]:
        from misrgraph.io.imagery import has_matched

        d = Path(directory)
        if not (d / "passes").is_dir():
            raise FileFormatError(d, "not a scenario directory (no passes/); make one with 'misrgraph simulate'")
        files = sorted((d / "passes").glob("*.h5"))
        if observations == "matched":
            bare = [f.name for f in files if not has_matched(f)]
            if bare:
                raise FileFormatError(
                    d / "passes" / bare[0],
                    f"no matched observations ({len(bare)} of {len(files)} passes "
                    "lack them); run 'misrgraph match' on the scenario first",
                )
        return d, True, {"passes": len(files)}

    return _task("inputs", name, (), body)


# ---------------------------------------------------------------------------- calibration
def _noise(noise: dict[str, Any] | None) -> Any:
    """The campaign's noise model, or None: a NoiseModel's fields as tasks carry it, or the record
    of :func:`fit_noise` (the model it learned, read from its file)."""
    from misrgraph.model.noise import NoiseModel

    if noise is None:
        return None
    if _is_record(noise):
        from misrgraph.io.noise import read_noise_model

        return read_noise_model(noise["output"])[0]
    return NoiseModel.from_dict(noise)


def _is_record(x: Any) -> bool:
    return isinstance(x, dict) and "stage" in x and "status" in x


def _needs_noise(noise: dict[str, Any] | None) -> tuple[dict[str, Any], ...]:
    """The noise-fit record a task waits for (none when the levels are given)."""
    return (noise,) if _is_record(noise) else ()


def _adjust_config(noise: dict[str, Any] | None) -> Any:
    from misrgraph.estimate.adjust import AdjustConfig

    model = _noise(noise)
    return AdjustConfig() if model is None else AdjustConfig().with_noise(model)


def calibrate(
    out: str,
    month: dict[str, Any],
    observations: str = "simulated",
    noise: dict[str, Any] | None = None,
    name: str = "month",
) -> dict[str, Any]:
    """Calibrate the cameras on the GCP month into ``OUT/calibration/camera_model-<digest>.h5``,
    from the ``observations`` set, with the navigation levels of the ``noise`` model (None: the
    pre-flight levels); ``name``: the record's (a window's, in a campaign over years)."""
    from misrgraph.estimate.calibrate import CalibrateConfig

    def body() -> tuple[Path, bool, dict[str, Any]]:
        from misrgraph.runs.calibrate import run_calibrate

        d = Path(month["output"])
        cfg = CalibrateConfig(noise=_noise(noise))
        key = digest("calibrate", _scenario_sha(d), cfg.to_dict(), {"observations": observations})
        f = Path(out) / "calibration" / f"camera_model-{key[:12]}.h5"
        if f.exists():
            return f, True, _calibration_summary(_stored_calibration_summary(f))
        return f, False, _calibration_summary(run_calibrate(d, out=f, cfg=cfg, observations=observations))

    return _task("calibration", name, (month,), body)


def _stored_calibration_summary(f: Path) -> dict[str, Any]:
    """The summary (``calibrate --json``) a calibrated camera-model file holds, with its
    ``correlation`` block from the file's covariance (the file's summary leaves it out) when the
    file holds a camera-level one."""
    from misrgraph.io.camera import read_calibration_prior
    from misrgraph.io.h5 import open_h5

    with open_h5(f, "camera_model") as h:
        summary = json.loads(h["calibration"].attrs["summary_json"])
    prior = read_calibration_prior(f)
    if prior is not None and "correlation" not in summary:
        labels, cov = prior
        sd = np.sqrt(np.diag(cov))
        summary["correlation"] = {"labels": labels, "matrix": (cov / np.outer(sd, sd)).tolist()}
    return summary


def _calibration_summary(s: dict[str, Any]) -> dict[str, Any]:
    keep = ("status", "max_pointing_error_px", "nees", "passes", "observations", "observation_set")
    out = {k: s[k] for k in keep if k in s}
    if "cameras" in s:
        out["pointing_error_px"] = {c: v.get("pointing_error_px") for c, v in s["cameras"].items()}
        out["sigma_px"] = {c: v.get("sigma_px") for c, v in s["cameras"].items()}
    return out


def camera_versions(out: str, cfg: CampaignConfig, *calibrations: dict[str, Any]) -> dict[str, Any]:
    """The camera-model versions of a campaign over years (:mod:`misrgraph.campaign.years`): the
    windows' calibrations (in window order) watched by the monitor, the versions it calls for in a
    store ``OUT/cgm/versions-<digest>/store`` (:mod:`misrgraph.io.cgm`), and what the monitor saw
    in ``monitor.json`` beside it (the record's summary)."""

    def body() -> tuple[Path, bool, dict[str, Any]]:
        from misrgraph.campaign.years import (
            calibration_days,
            date_of_day,
            first_orbit_of_day,
            plan_versions,
            window_starts,
        )
        from misrgraph.io.cgm import add_version

        files = [Path(c["output"]) for c in calibrations]
        starts = window_starts(cfg)
        key = digest("versions", [_sha(f) for f in files], starts, cfg.monitor_alpha)
        final = Path(out) / "cgm" / f"versions-{key[:12]}"
        if (final / "monitor.json").exists():
            return final / "store", True, json.loads((final / "monitor.json").read_text())
        summaries = [_stored_calibration_summary(f) for f in files]
        # each camera given the others where every calibration has its covariance (per-band or
        # per-temperature calibrations do not hold a camera-level one)
        view = "conditional" if all("correlation" in x for x in summaries) else "marginal"
        if view == "marginal":
            log.warning("the calibrations hold no camera-level covariance: the monitor tests each camera's own series")
        plan = plan_versions(calibration_days(cfg), summaries, cfg.monitor_alpha, view)
        versions = []
        with _building(final) as tmp:
            for k, w in enumerate(plan["version_windows"]):
                if k == 0:
                    reason = f"calibration window 1 (GCP scenario from {date_of_day(cfg, starts[0])})"
                else:
                    a = plan["alarms"][k - 1]
                    reason = (
                        f"monitor: {a['camera']} {a['parameter']} {a['kind']} at window {w + 1} "
                        f"({date_of_day(cfg, starts[w])}), onset window {a['onset_window'] + 1}"
                    )
                v = add_version(tmp / "store", files[w], first_orbit_of_day(starts[w]) if k else 0, None, reason)
                versions.append({"id": v.id, "window": w, "first_orbit": v.first_orbit, "reason": reason})
            summary = {
                **plan,
                "windows": [
                    {"window": w + 1, "start": date_of_day(cfg, d), "calibration": str(f)}
                    for w, (d, f) in enumerate(zip(starts, files))
                ],
                "versions": versions,
            }
            (tmp / "monitor.json").write_text(json.dumps(summary, indent=2))
        return final / "store", False, summary

    return _task("versions", "camera model", tuple(calibrations), body)


def fit_noise(out: str, base: dict[str, Any] | None, *results: dict[str, Any]) -> dict[str, Any]:
    """The noise levels learned on the campaign's first adjusted passes (``results``, their records)
    into ``OUT/noise/noise-<digest>.json`` (:func:`misrgraph.estimate.noisefit.fit_noise_model`; the
    levels the passes do not carry from ``base``, or the pre-flight ones), a file
    ``--noise-model`` reads."""

    def body() -> tuple[Path, bool, dict[str, Any]]:
        from misrgraph.io.noise import SECTIONS
        from misrgraph.model.noise import NoiseModel
        from misrgraph.runs.noise import fit_and_save, read_pass_levels

        files = [Path(r["output"]) for r in results]
        key = digest("noise fit", [_sha(f) for f in files], base)
        f = Path(out) / "noise" / f"noise-{key[:12]}.json"
        found = f.exists()
        if not found:
            passes = [read_pass_levels(x) for x in files]
            for p, r in zip(passes, results):
                p.name = r["name"]  # the file records the passes by the campaign's names
            f.parent.mkdir(parents=True, exist_ok=True)
            fit_and_save(passes, f, _noise(base) or NoiseModel(), {s: "input" for s in SECTIONS} if base else {})
        return f, found, json.loads(f.read_text())["fit"]

    return _task("noise", "fit", tuple(results), body)


# ---------------------------------------------------------------------------- per pass
def adjust(
    out: str,
    path: int,
    pass_id: str,
    inputs: dict[str, Any],
    calibration: dict[str, Any],
    observations: str = "simulated",
    noise: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Adjust one pass with the calibrated model into ``OUT/adjusted/path_PPP/<pass id>-<digest>.h5``
    (RESULT.h5), from the ``observations`` set, with the levels of the ``noise`` model; the graph
    is built and solved here, on the worker."""

    def body() -> tuple[Path, bool, dict[str, Any]]:
        from misrgraph.io.h5 import open_h5
        from misrgraph.runs.adjust import run_adjust

        d = Path(inputs["output"])
        pass_file = d / "passes" / f"{pass_id}.h5"
        if not pass_file.exists():
            raise FileFormatError(pass_file, "the planned pass is not in the scenario")
        cam = _model_for(Path(calibration["output"]), pass_file)
        cfg = _adjust_config(noise)
        key = digest(
            "adjust",
            _sha(pass_file),
            _sha(cam),
            _sha(d / "gcp.h5"),
            _sha(d / "dem.h5"),
            cfg.to_dict(),
            {"observations": observations},
        )
        f = Path(out) / "adjusted" / f"path_{path:03d}" / f"{pass_id}-{key[:12]}.h5"
        if f.exists():
            with open_h5(f, "adjustment_result") as h:
                return f, True, _pass_summary(json.loads(h.attrs["summary_json"]))
        f.parent.mkdir(parents=True, exist_ok=True)
        s = run_adjust(
            d,
            camera_model=calibration["output"],
            pass_file=pass_file,
            out=f,
            cfg=cfg,
            score_points=True,
            observations=observations,
        )
        return f, False, _pass_summary(s)

    return _task("adjust", pass_id, (inputs, calibration, *_needs_noise(noise)), body)


def _model_for(cam: Path, pass_file: Path) -> Path:
    """The camera-model file a pass is adjusted with: ``cam`` itself, or the version of the store
    ``cam`` valid for the pass's orbit."""
    from misrgraph.io.cgm import is_cgm_store

    if not is_cgm_store(cam):
        return cam
    from misrgraph.runs.cgm import resolve_camera_model
    from misrgraph.runs.update import _pass_orbit

    return Path(resolve_camera_model(cam, _pass_orbit(pass_file))[0])


def _current_version_passes(cam: Path, files: list[Path]) -> list[Path]:
    """``files`` themselves, or with a store ``cam`` the passes of its last version (a path's
    state and products use one camera model: the current one)."""
    from misrgraph.io.cgm import is_cgm_store, open_store

    if not is_cgm_store(cam):
        return files
    last = open_store(cam).versions[-1]
    from misrgraph.runs.update import _pass_orbit

    keep = [f for f in files if last.covers(_pass_orbit(f))]
    if not keep:
        raise MisrGraphError(
            f"no planned pass of this path falls in the current camera model {last.id} ({last.orbits_text()})"
        )
    return keep


def _pass_summary(s: dict[str, Any]) -> dict[str, Any]:
    out = {
        k: s[k]
        for k in (
            "pass_id",
            "camera_model_version",
            "observation_set",
            "solver_status",
            "iterations",
            "seconds",
            "variance_factor",
            "coregistration_px",
            "checkpoint_points",
            "checkpoint_rms_over_predicted",
        )
        if k in s
    }
    if "checkpoint_geolocation_m" in s:
        out["checkpoint_m"] = {
            c: {
                "n": v["n"],
                "rms": v["after"].get("rms"),
                "before_mean": v["before"]["mean"],
                "predicted_rms": v["after"].get("predicted_rms"),
            }
            for c, v in s["checkpoint_geolocation_m"].items()
        }
    if "nees" in s:
        out["nees"] = {k: s["nees"][k] for k in ("knots", "landmarks", "camera", "camera_dim") if k in s["nees"]}
    out["rejected_observations"] = s.get("rejected_observations", {}).get("count")
    return out


# ---------------------------------------------------------------------------- per path
def path_products(
    out: str,
    path: int,
    pass_ids: tuple[str, ...],
    inputs: dict[str, Any],
    calibration: dict[str, Any],
    blocks: int,
    roi: bool = False,
    observations: str = "simulated",
    noise: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The path's incremental state over its passes (``misrgraph update``, one pass at a time)
    and the Projection Parameters of its first pass (``misrgraph products``) into
    ``OUT/paths/path_PPP-<digest>/{state/, products/, path.json}``, both from the
    ``observations`` set; with ``roi``, the Reference Orbit Imagery of the blocks its strips
    cover, from every pass of the state with the state's estimate (``misrgraph products STATE
    --roi``), into ``products/roi/``."""

    def body() -> tuple[Path, bool, dict[str, Any]]:
        from misrgraph.runs.products import run_products
        from misrgraph.runs.update import run_update

        d = Path(inputs["output"])
        files = [d / "passes" / f"{p}.h5" for p in pass_ids]
        missing = [str(f) for f in files if not f.exists()]
        if missing:
            raise FileFormatError(d / "passes", f"planned passes missing: {', '.join(missing)}")
        files = _current_version_passes(Path(calibration["output"]), files)
        cam = _model_for(Path(calibration["output"]), files[0])
        cfg = _adjust_config(noise)
        key = digest(
            "path",
            [_sha(f) for f in files],
            _sha(cam),
            _sha(d / "gcp.h5"),
            _sha(d / "dem.h5"),
            cfg.to_dict(),
            blocks,
            {"roi": True} if roi else {},
            {"observations": observations},
        )
        final = Path(out) / "paths" / f"path_{path:03d}-{key[:12]}"
        if (final / SUMMARY_FILE).exists():
            return final, True, json.loads((final / SUMMARY_FILE).read_text())
        with _building(final) as tmp:
            t0 = time.perf_counter()
            upd = run_update(
                tmp / "state",
                [str(f) for f in files],
                camera_model=cam,
                gcp_file=d / "gcp.h5",
                dem_file=d / "dem.h5",
                cfg=cfg,
                observations=observations,
            )
            t_update = time.perf_counter() - t0
            prod = run_products(
                d,
                tmp / "products",
                pass_file=files[0],
                camera_model=cam,
                default_blocks=blocks,
                cfg=cfg,
                observations=observations,
            )
            pp_name = Path(prod["files"]["pp"]).name
            prod["files"]["pp"] = str(final / "products" / pp_name)  # where it will be after the rename
            (tmp / "products" / "products.json").write_text(json.dumps(prod, indent=2))
            roi_summary = None
            if roi:
                from misrgraph.runs.products import RoiOptions

                r = run_products(
                    tmp / "state", tmp / "products" / "roi", roi=True, roi_options=RoiOptions(quicklooks=True)
                )
                roi_summary = {
                    "file": f"products/roi/{Path(r['roi']['file']).name}",
                    "blocks": r["blocks"],
                    "passes": r["roi"]["passes"],
                    "chosen_pass": r["roi"]["chosen_pass"],
                    "coregistration_px": r["roi_coregistration_px"],
                    "truth_px": r.get("roi_truth"),
                    "obscured_fraction": r["roi"]["obscured_fraction"],
                    "seconds": r["seconds"]["total"],
                }
            summary = {
                "path": path,
                "passes": list(pass_ids),
                "observation_set": observations,
                "update": [
                    {k: u.get(k) for k in ("pass_id", "status", "update_seconds", "rejected_observations")}
                    | (
                        {
                            "checkpoint_rms_m": {
                                c: v["after"].get("rms") for c, v in u["checkpoint_geolocation_m"].items()
                            }
                        }
                        if "checkpoint_geolocation_m" in u
                        else {}
                    )
                    for u in upd["updates"]
                ],
                "update_seconds": t_update,
                "products": {
                    "pass_id": prod["pass_id"],
                    "blocks": prod["blocks"],
                    "pp_file": f"products/{pp_name}",
                    "pp_error_m": prod.get("pp_error_m"),
                    "roi": roi_summary,
                    "seconds": prod["seconds"],
                },
            }
            (tmp / SUMMARY_FILE).write_text(json.dumps(summary, indent=2))
        return final, False, summary

    return _task("path", f"path {path}", (inputs, calibration, *_needs_noise(noise)), body)
