"""``misrgraph bench worlds``: honesty in worlds the estimator was not tuned for.

Each world is the simulator's independent truth with some of its error levels changed (the files
misstate their accuracy, the attitude error is larger or has another band, the jitter, the
navigation, the once-per-revolution term, the DEM error's correlation). Per world, passes are
simulated with distinct seeds; the first ``fit_passes`` are adjusted with the defaults and give a
noise model (:func:`misrgraph.runs.noise.run_noise_fit`); the other ``passes`` are scored three
ways:

- ``fixed``: the pre-flight levels, stated sigmas taken as they are (no variance components);
- ``learned``: the noise model fitted on the world's unscored passes, variance components on;
- ``oracle``: the world's true levels (:func:`oracle_noise_model`), no variance components.

Per world and way: the landmark, knot and camera NEES/dim and the check points' actual over
predicted RMS, each with a 95 % interval from the run-to-run scatter (Student t; for the check
points the RMS of the runs' ratios), and the check points' RMS error (m). ``acceptance`` applies
the issue's bounds to the learned way: landmark NEES and check points' ratio in 0.8-1.25, knot
NEES in 0.7-1.4, check-point RMS within 5 % of the oracle's.
"""

from __future__ import annotations

import logging
import multiprocessing
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any, Callable

import numpy as np

from misrgraph.bench.studies import _checkpoint_rms_after, _interval, _rms_interval
from misrgraph.errors import InputError, MisrGraphError
from misrgraph.estimate.graph import KNOT_PRIORS
from misrgraph.model.noise import NoiseModel
from misrgraph.sim.simulate import ScenarioConfig, run_simulate

__all__ = [
    "WORLDS",
    "WORLD_SIZES",
    "oracle_noise_model",
    "world_files",
    "run_bench_worlds",
    "levels_recovered",
    "kept_sigma_fraction",
    "RECOVERED_LEVELS",
]

log = logging.getLogger(__name__)

_BASE = ScenarioConfig()
_ATT = tuple(float(s) for s in _BASE.attitude_sigma_arcsec)

#: the worlds: name -> the :class:`ScenarioConfig` fields that differ from the base world
WORLDS: dict[str, dict[str, Any]] = {
    "base": {},
    "tie stated x0.5": {"tie_sigma_true_over_stated": 2.0},
    "tie stated x2": {"tie_sigma_true_over_stated": 0.5},
    "GCP stated x0.5": {"gcp_pixel_sigma_true_over_stated": 2.0, "gcp_sigma_true_over_stated": 2.0},
    "GCP stated x2": {"gcp_pixel_sigma_true_over_stated": 0.5, "gcp_sigma_true_over_stated": 0.5},
    "DEM stated x0.5": {"dem_sigma_true_over_stated": 2.0},
    "DEM stated x2": {"dem_sigma_true_over_stated": 0.5},
    "jitter x0.3": {"jitter_arcsec": 0.3 * _BASE.jitter_arcsec},
    "jitter x2": {"jitter_arcsec": 2.0 * _BASE.jitter_arcsec},
    "attitude sigma x2": {"attitude_sigma_arcsec": tuple(2.0 * s for s in _ATT)},
    "attitude band 30-300 s": {"attitude_periods_s": (30.0, 300.0)},
    "attitude band 2000-10000 s": {"attitude_periods_s": (2000.0, 10000.0)},
    "navigation x3": {
        "nav_sigma_m": 3.0 * _BASE.nav_sigma_m,
        "along_drift_sigma_mps": 3.0 * _BASE.along_drift_sigma_mps,
        "drift_sigma_mps": 3.0 * _BASE.drift_sigma_mps,
    },
    "once-per-rev 100 m": {"once_per_rev_m": 100.0},
    "DEM error fully correlated": {"dem_correlated_fraction": 1.0},
}

#: pass sizes: the issue's reduced passes (20 minutes, 300 tie points) and the suite's tiny ones
WORLD_SIZES: dict[str, dict[str, Any]] = {
    "reduced": {"n_tie_points": 300, "n_check_points": 20, "duration_s": 1200.0},
    "tiny": {"n_tie_points": 100, "n_check_points": 10, "n_gcps": 20, "duration_s": 600.0},
}

WAYS = ("fixed", "learned", "oracle")


def _band_rate_factor(periods_s: tuple[float, float]) -> float:
    """RMS angular frequency (1/s) of a process with equal power per log-period over ``periods_s``:
    the rate's sigma over the value's."""
    w1, w2 = 2 * np.pi / periods_s[1], 2 * np.pi / periods_s[0]
    return float(np.sqrt((w2**2 - w1**2) / (2.0 * np.log(w2 / w1))))


def oracle_noise_model(cfg: ScenarioConfig) -> NoiseModel:
    """The noise model holding a simulated world's true levels: the files' true-over-stated sigma
    as the observation and DEM scales, the truth's attitude sigma (its rate from the band's RMS
    frequency, its damping fitted to the band's correlation), jitter, navigation sigmas and
    once-per-revolution amplitude. The camera prior stays pre-flight (the truth's camera residual
    is the pre-flight one). A process faster than the pre-flight one gets the knots the noise fit
    would give it (:func:`~misrgraph.estimate.noisefit.knot_spacing_for`)."""
    from misrgraph.estimate.noisefit import knot_spacing_for, spacing_tolerance
    from misrgraph.model.errormodels import ATTITUDE_RATE_FACTOR, fit_damping

    base = NoiseModel()
    factor = _band_rate_factor(tuple(cfg.attitude_periods_s))
    att = tuple(float(s) for s in cfg.attitude_sigma_arcsec)
    model = base.replace(
        attitude=base.attitude.replace(
            value_sigma_arcsec=att,
            rate_sigma_arcsec_per_s=tuple(s * factor for s in att),
            damping=fit_damping(lam=factor, periods_s=tuple(cfg.attitude_periods_s)),
        ),
        jitter=base.jitter.replace(sigma_arcsec=float(cfg.jitter_arcsec), periods_s=tuple(cfg.jitter_periods_s)),
        ephemeris=base.ephemeris.replace(
            offset_sigma_m=float(cfg.nav_sigma_m),
            drift_sigma_mps=(float(cfg.along_drift_sigma_mps), float(cfg.drift_sigma_mps), float(cfg.drift_sigma_mps)),
            once_per_rev_m=float(cfg.once_per_rev_m),
        ),
        dem=base.dem.replace(sigma_scale=float(cfg.dem_sigma_true_over_stated)),
        observations=base.observations.replace(
            tie_sigma_scale=float(cfg.tie_sigma_true_over_stated),
            gcp_pixel_sigma_scale=float(cfg.gcp_pixel_sigma_true_over_stated),
            gcp_sigma_scale=float(cfg.gcp_sigma_true_over_stated),
        ),
    )
    if factor <= ATTITUDE_RATE_FACTOR:
        return model
    a, tol = model.attitude, spacing_tolerance(base.replace(jitter=model.jitter))
    spacing = tuple(
        min(h, knot_spacing_for(v, factor, a.damping, h, tol)) for h, v in zip(a.knot_spacing_s, a.value_sigma_arcsec)
    )
    return model.replace(attitude=a.replace(knot_spacing_s=spacing))


#: The learned levels compared with the world's own (``noise fit`` name -> (section, field, axis or
#: None, the acceptance's relative bound)): the stated-sigma scales within 10 %, the attitude
#: sigmas within 20 %.
RECOVERED_LEVELS: dict[str, tuple[str, str, int | None, float]] = {
    "observations.tie_sigma_scale": ("observations", "tie_sigma_scale", None, 0.10),
    "observations.gcp_pixel_sigma_scale": ("observations", "gcp_pixel_sigma_scale", None, 0.10),
    "observations.gcp_sigma_scale": ("observations", "gcp_sigma_scale", None, 0.10),
    "dem.sigma_scale": ("dem", "sigma_scale", None, 0.10),
    "attitude.value_sigma_arcsec.roll": ("attitude", "value_sigma_arcsec", 0, 0.20),
    "attitude.value_sigma_arcsec.pitch": ("attitude", "value_sigma_arcsec", 1, 0.20),
    "attitude.value_sigma_arcsec.yaw": ("attitude", "value_sigma_arcsec", 2, 0.20),
}


def kept_sigma_fraction(dof: float, critical: float, draws: int = 400_000, seed: int = 0) -> float:
    """The 1 sigma of the matching errors data snooping keeps, over the sigma they are drawn with:
    each observation's two errors unit-variance Student-t with ``dof`` degrees of freedom (0:
    Gaussian; :func:`misrgraph.sim.simulate.matching_noise`), kept when their squared norm is
    below ``critical`` (the snooping's statistic, chi-square with 2 dof under the stated sigma).
    Heavy tails hold variance that the snooping removes, so a class's variance component reads
    below the drawn scale by this factor (Monte Carlo, ``draws`` observations)."""
    from misrgraph.sim.simulate import matching_noise

    rng = np.random.default_rng(seed)
    x = np.stack([matching_noise(rng, draws, dof), matching_noise(rng, draws, dof)], axis=1)
    keep = np.sum(x**2, axis=1) < critical
    return float(np.sqrt(np.mean(x[keep] ** 2)))


def levels_recovered(result: dict[str, Any]) -> dict[str, Any]:
    """Each world's learned levels (:data:`RECOVERED_LEVELS`) against its own: ``{"rows": [{"world",
    "level", "learned", "sigma", "true", "true_kept", "ratio", "z", "within", "applied", "reason"}],
    "within": k,
    "rows_counted": n,
    "covered": c, "with_sigma": m}`` -- ``within``: rows inside the acceptance's bound; ``covered``:
    rows with a 1 sigma whose 95 % interval (+-1.96 sigma) holds the truth, of ``with_sigma``. The
    attitude rows of the band worlds are left out: their truth is a band, not the process's
    sigma. The image-observation scales (tie points, GCP measurements) are compared with the drawn
    scale times :func:`kept_sigma_fraction` for the world's matching noise and the snooping's
    critical value: the sigma of the observations an adjustment keeps (``true_kept``)."""
    from misrgraph.estimate.reliability import critical_T

    rows = []
    fractions: dict[float, float] = {}
    for world, w in result["worlds"].items():
        learned, true = w.get("learned_levels") or {}, w.get("true_levels") or {}
        for name, (section, field, axis, bound) in RECOVERED_LEVELS.items():
            if name not in learned or section not in true or ("band" in world and section == "attitude"):
                continue
            t = true[section][field]
            t = float(t[axis] if axis is not None else t)
            drawn = t
            if field in ("tie_sigma_scale", "gcp_pixel_sigma_scale"):
                dof = float((w.get("overrides") or {}).get("noise_tail_dof", ScenarioConfig().noise_tail_dof))
                if dof not in fractions:
                    fractions[dof] = kept_sigma_fraction(dof, critical_T())
                t = drawn * fractions[dof]
            v, sd = float(learned[name]["value"]), learned[name].get("sigma")
            z = (v - t) / float(sd) if sd else float("nan")
            rows.append(
                {
                    "world": world,
                    "level": name,
                    "learned": v,
                    "sigma": None if sd is None else float(sd),
                    "true": drawn,
                    "true_kept": t,
                    "ratio": v / t,
                    "z": z,
                    "within": abs(v / t - 1.0) <= bound,
                    "applied": learned[name].get("applied"),
                    "reason": learned[name].get("reason"),
                }
            )
    finite = [r for r in rows if r["sigma"] is not None and r["sigma"] > 0]
    return {
        "rows": rows,
        "within": sum(r["within"] for r in rows),
        "rows_counted": len(rows),
        "covered": sum(abs(r["z"]) <= 1.96 for r in finite),
        "with_sigma": len(finite),
    }


def _score(summary: dict[str, Any]) -> dict[str, float]:
    nees = summary.get("nees", {})
    out = {k: float(nees[k]) for k in ("landmarks", "knots", "camera") if k in nees}
    if "checkpoint_rms_over_predicted" in summary:
        out["checkpoint_ratio"] = float(summary["checkpoint_rms_over_predicted"])
    cp = _checkpoint_rms_after(summary)
    if cp is not None:
        out["checkpoint_rms_m"] = cp
    if "seconds" in summary:
        out["seconds"] = float(summary["seconds"])
    return out


def _summarise(runs: list[dict[str, float]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k in ("landmarks", "knots", "camera", "checkpoint_rms_m", "seconds"):
        v = [r[k] for r in runs if k in r]
        if v:
            out[k] = _interval(v)
    v = [r["checkpoint_ratio"] for r in runs if "checkpoint_ratio" in r]
    if v:
        out["checkpoint_ratio"] = _rms_interval(v)
    return out


def _accept(ways: dict[str, dict[str, Any]]) -> dict[str, bool]:
    learned, oracle = ways["learned"], ways["oracle"]
    ok: dict[str, bool] = {"every_pass_adjusted": not learned["failed"]}
    if "landmarks" in learned:
        ok["landmarks_0.8_1.25"] = 0.8 <= learned["landmarks"]["mean"] <= 1.25
    if "checkpoint_ratio" in learned:
        ok["checkpoint_ratio_0.8_1.25"] = 0.8 <= learned["checkpoint_ratio"]["rms"] <= 1.25
    if "knots" in learned:
        ok["knots_0.7_1.4"] = 0.7 <= learned["knots"]["mean"] <= 1.4
    if "checkpoint_rms_m" in learned and "checkpoint_rms_m" in oracle:
        ok["checkpoint_rms_within_5pct_of_oracle"] = (
            learned["checkpoint_rms_m"]["mean"] <= 1.05 * oracle["checkpoint_rms_m"]["mean"]
        )
    return ok


def world_files(wd: Path, name: str, size: str, knot_prior: str = "process") -> tuple[Callable[[int], Path], str, Path]:
    """Where a worlds run keeps world ``name``'s files in ``wd``: the directory of its simulated
    pass of seed ``s`` (a function of ``s``), the name of a fitted pass's result in it, and the
    fitted noise model (``knot_prior`` other than ``"process"``: that prior's, beside the
    default's)."""
    stem = f"world{list(WORLDS).index(name):02d}_{size}"
    tag = "" if knot_prior == "process" else f"-{knot_prior}"
    return (lambda s: wd / f"{stem}_{s}"), f"fit_result{tag}.h5", wd / f"{stem}_noise{tag}.json"


def _run_world(
    name: str,
    passes: int,
    fit_passes: int,
    seed: int,
    size: str,
    wd: Path,
    progress: Callable[[str], None] | None = None,
    knot_prior: str = "process",
) -> dict[str, Any]:
    """One world of :func:`run_bench_worlds`: simulate (or reuse) its passes in ``wd``, fit the
    noise model on the first ``fit_passes``, score the other ``passes`` three ways."""
    from misrgraph.estimate.adjust import AdjustConfig
    from misrgraph.io.noise import read_noise_model
    from misrgraph.runs.adjust import run_adjust
    from misrgraph.runs.noise import run_noise_fit

    over = WORLDS[name]
    w_index = list(WORLDS).index(name)
    cfgs = [
        ScenarioConfig.from_dict(
            {
                **WORLD_SIZES[size],
                "scenario": "pass",
                "start_lat_deg": 50.0,
                **over,
                "seed": seed + 100 * w_index + i,
            }
        )
        for i in range(fit_passes + passes)
    ]
    pass_dir, fit_result, noise_file = world_files(wd, name, size, knot_prior)
    dirs = []
    for i, cfg in enumerate(cfgs):
        d = pass_dir(cfg.seed)
        if not (d / "scenario.json").exists():
            if progress:
                progress(f"{name}: simulating pass {i + 1}/{len(cfgs)}")
            run_simulate(cfg, d)
        dirs.append(d)

    def adjust_config(**fields: Any) -> AdjustConfig:
        return AdjustConfig.from_dict(knot_prior=knot_prior, **fields)

    results = []
    for i, d in enumerate(dirs[:fit_passes]):
        if progress:
            progress(f"{name}: adjusting fit pass {i + 1}/{fit_passes}")
        r = d / fit_result
        run_adjust(d, out=r, cfg=adjust_config())
        results.append(r)
    fit = run_noise_fit(results, out=noise_file)
    learned_model, _ = read_noise_model(noise_file)  # as a user's --noise-model would read it
    oracle = oracle_noise_model(cfgs[0])
    configs = {
        "fixed": adjust_config(variance_component_rounds=0),
        "learned": adjust_config().with_noise(learned_model),
        "oracle": adjust_config(variance_component_rounds=0).with_noise(oracle),
    }
    per_way: dict[str, list[dict[str, float]]] = {w: [] for w in WAYS}
    failures: dict[str, list[str]] = {w: [] for w in WAYS}
    for i, d in enumerate(dirs[fit_passes:]):
        for way in WAYS:
            if progress:
                progress(f"{name}: scoring pass {i + 1}/{passes} ({way})")
            try:
                per_way[way].append(_score(run_adjust(d, cfg=configs[way])))
            except MisrGraphError as exc:  # a way that cannot adjust a pass is a finding, not a crash
                log.warning("%s, %s, pass %d: %s", name, way, i + 1, exc)
                failures[way].append(f"pass {i + 1}: {str(exc).splitlines()[0][:200]}")
    ways = {w: {**_summarise(per_way[w]), "passes": len(per_way[w]), "failed": failures[w]} for w in WAYS}
    # the adjustment's time with the learned levels over the fixed ones', pass by pass (the same
    # pass, one after the other in this run)
    paired = [
        a["seconds"] / b["seconds"]
        for a, b in zip(per_way["learned"], per_way["fixed"])
        if a.get("seconds") and b.get("seconds")
    ]
    return {
        "overrides": {k: (list(v) if isinstance(v, tuple) else v) for k, v in over.items()},
        "ways": ways,
        "per_pass": per_way,
        "learned_levels": {
            k: {key: v.get(key) for key in ("value", "sigma", "applied", "reason")} for k, v in fit["levels"].items()
        },
        "true_levels": oracle.to_dict(),
        "acceptance": _accept(ways),
        "cost_ratio": _interval(paired) if paired else None,
    }


def run_bench_worlds(
    passes: int = 4,
    fit_passes: int = 2,
    worlds: list[str] | None = None,
    seed: int = 20000,
    size: str = "reduced",
    workdir: str | Path | None = None,
    progress: Callable[[str], None] | None = None,
    workers: int = 1,
    knot_prior: str = "process",
) -> dict[str, Any]:
    """Score the three ways in each world (module docstring). ``worlds``: names of :data:`WORLDS`
    (default all); ``passes`` scored and ``fit_passes`` fitted per world, seeds from ``seed`` (world
    ``w`` uses ``seed + 100 w + i``); ``size``: :data:`WORLD_SIZES`; ``workdir`` keeps the
    simulated passes (a rerun reuses them); ``workers``: worlds run at once, each in a process of
    its own (1: one after the other in this process). The worlds' figures do not depend on
    ``workers``; the cost ratio is timed within one process, beside the other workers' load.
    ``knot_prior``: every adjustment's (:data:`~misrgraph.estimate.graph.KNOT_PRIORS`); another
    than ``"process"`` writes its fitted passes and noise models beside the default's in
    ``workdir`` (``fit_result-<prior>.h5``, ``..._noise-<prior>.json``), on the same simulated passes.

    Returns ``{"passes", "fit_passes", "size", "seed", "workers", "knot_prior", "seconds",
    "worlds": {name: {"overrides", "ways": {way: summary}, "per_pass", "learned_levels",
    "true_levels", "acceptance", "cost_ratio"}}, "acceptance": {"worlds_passing", "worlds",
    "passing"}}``."""
    names = list(WORLDS) if worlds is None else list(worlds)
    for n in names:
        if n not in WORLDS:
            raise InputError("worlds", n, tuple(WORLDS))
    if size not in WORLD_SIZES:
        raise InputError("size", size, tuple(WORLD_SIZES))
    if passes < 1 or fit_passes < 1:
        raise InputError("passes", (passes, fit_passes), "at least 1 scored and 1 fitted pass per world")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InputError("workers", workers, "an integer >= 1")
    if knot_prior not in KNOT_PRIORS:
        raise InputError("knot_prior", knot_prior, KNOT_PRIORS)
    t0 = time.perf_counter()
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="misrgraph-worlds-")
        workdir = tmp.name
    wd = Path(workdir)
    out: dict[str, Any] = {}
    try:
        if workers == 1 or len(names) == 1:
            for w_i, name in enumerate(names):
                out[name] = _run_world(name, passes, fit_passes, seed, size, wd, progress, knot_prior)
                log.info("world %d/%d (%s) done", w_i + 1, len(names), name)
        else:
            got: dict[str, Any] = {}
            ctx = multiprocessing.get_context("spawn")  # a fresh interpreter per worker: no forked GTSAM state
            with ProcessPoolExecutor(max_workers=min(workers, len(names)), mp_context=ctx) as pool:
                jobs = {
                    pool.submit(_run_world, n, passes, fit_passes, seed, size, wd, None, knot_prior): n for n in names
                }
                if progress:
                    progress(f"{len(names)} worlds on {min(workers, len(names))} workers")
                for k, job in enumerate(as_completed(jobs)):
                    got[jobs[job]] = job.result()
                    log.info("world %d/%d (%s) done", k + 1, len(names), jobs[job])
                    if progress:
                        progress(f"{k + 1}/{len(names)} worlds done (last: {jobs[job]})")
            out = {n: got[n] for n in names}
    finally:
        if tmp is not None:
            tmp.cleanup()
    passing = [n for n, v in out.items() if v["acceptance"] and all(v["acceptance"].values())]
    return {
        "passes": passes,
        "fit_passes": fit_passes,
        "size": size,
        "seed": seed,
        "workers": workers,
        "knot_prior": knot_prior,
        "seconds": time.perf_counter() - t0,
        "worlds": out,
        "acceptance": {"worlds_passing": len(passing), "worlds": len(out), "passing": passing},
    }
