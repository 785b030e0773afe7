"""Camera geometric model calibration by space resection over a month of GCP passes (seed 4.1).

One graph holds every GCP pass: the GCP landmarks (shared by the passes that see them, each with
its 30 m ENU prior, eq. 32), the camera corrections (shared by all passes: default delta, beta,
eps per camera; optionally f, alpha_i, per band, and the common omega), and per pass the
navigation errors as nuisance variables with priors from the navigation accuracy: the ephemeris
error of eq. 19 and the attitude error spline of eqs. 23-27 at the adjustment's knot spacing.

Why this nuisance design: the navigation errors of one pass shift all nine views of that pass
together and change from pass to pass, while a camera error is the same in every pass. With the
nuisance variables carrying honest priors, the only way to explain a residual that repeats in
one camera across many passes is a camera correction -- the averaging over passes is what
separates the two (seed 2: "each GCP seen in at least three passes"). Knots are never removed
here (GCP views are sparse, and merged spline segments would mis-fit them, see
docs/conventions.md); knots without data are held by their priors. ``misrgraph bench
separation`` measures how the camera error shrinks with the number of passes.

Procedure: robust (Cauchy) solve -> reject observations above ``reject_sigma`` -> least-squares
re-solve; marginal covariance of the camera parameters from ``gtsam.Marginals`` (joint); a
parameter whose posterior sigma is more than ``poorly_determined_ratio`` of its prior sigma is
reported as poorly determined (the data hardly constrain it).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import keys as K
from factors.collinearity import CAMERA_PARAM_SCALE, CAMERA_PARAMS
from misrgraph import __version__
from misrgraph.camera import CameraModel
from misrgraph.config import Config
from misrgraph.constants import BANDS, CAMERAS
from misrgraph.errors import DegenerateProblemError, FileFormatError, InputError
from misrgraph.gcp import GcpDatabase
from misrgraph.graph import CAMERA_PRIOR_SIGMA, GraphConfig, PassGraph, Problem, build_pass_graph, merge_problems
from misrgraph.h5io import atomic_h5, write_dataset
from misrgraph.passdata import KIND_GCP, OrbitPass
from misrgraph.solver import SolverParams, linearize, solve

__all__ = ["CalibrateConfig", "CalibrationResult", "calibrate_passes", "run_calibrate", "pointing_error_px"]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
RED = BANDS.index("red")


@dataclass(frozen=True)
class CalibrateConfig(Config):
    """Calibration settings. ``params`` from :data:`factors.collinearity.CAMERA_PARAMS`."""

    params: tuple = ("delta", "beta", "epsilon")
    per_band: bool = False
    estimate_omega: bool = False
    knot_spacing_s: tuple = (120.0, 60.0, 120.0)
    robust: str = "cauchy"
    robust_k: float = 3.0
    reject_sigma: float = 5.0
    max_iterations: int = 100
    poorly_determined_ratio: float = 0.5

    def graph_config(self, **kw: Any) -> GraphConfig:
        base = dict(knot_spacing_s=self.knot_spacing_s, threshold1=0, threshold2=0, use_dem=False,
                    estimate_camera=True, camera_params=tuple(self.params), camera_per_band=self.per_band,
                    camera_prior_calibration=True, estimate_omega=self.estimate_omega)
        base.update(kw)
        return GraphConfig.from_dict(base)


@dataclass
class CalibrationResult:
    camera: CameraModel
    keys: list[int]
    labels: list[str]
    values: Array
    covariance: Array
    prior_sigma: Array
    rejected: list[tuple[int, int, float]]
    iterations: int
    final_cost: float
    seconds: float
    graphs: list[PassGraph]


def _build(passes: list[OrbitPass], camera: CameraModel, gcps: GcpDatabase, cfg: GraphConfig,
           exclude: list[NDArray[np.bool_]] | None, progress: Callable[[str], None] | None,
           table: Any = None) -> tuple[Problem, list[PassGraph]]:
    shared: set[int] = set()
    graphs = []
    for i, p in enumerate(passes):
        if progress and i % 20 == 0:
            progress(f"graph: pass {i + 1}/{len(passes)}")
        pg = build_pass_graph(p, camera, None, gcps, cfg, pass_index=i, shared=shared,
                              exclude_observations=exclude[i] if exclude else None,
                              camera_for_pass=table.at_temperature(p.temperature_c) if table is not None else None)
        shared |= set(pg.problem.initial.keys()) & (set(pg.problem.eliminate_first) | set(pg.problem.eliminate_last))
        graphs.append(pg)
    return merge_problems([g.problem for g in graphs]), graphs


def _camera_keys_labels(graphs: list[PassGraph], cfg: CalibrateConfig) -> tuple[list[int], list[str], list[int]]:
    keys: dict[int, int] = {}
    for g in graphs:
        keys.update(g.camera_keys)
    out_k, labels, cams = [], [], []
    for ck in sorted(keys):
        c, b = (ck // 10, ck % 10) if cfg.per_band else (ck, None)
        name = CAMERAS[c] + (f"/{BANDS[b]}" if b is not None else "")
        out_k.append(keys[ck])
        cams.append(ck)
        labels += [f"{name}.{p}" for p in cfg.params]
    if cfg.estimate_omega:
        out_k.append(K.omega_key())
        labels += ["omega_x", "omega_y", "omega_z"]
    return out_k, labels, cams


def _joint_marginal(problem: Problem, values: gtsam.Values, keys: list[int]) -> Array:
    lin = linearize(problem, values)
    marg = gtsam.Marginals(lin, values)
    jm = marg.jointMarginalCovariance(gtsam.KeyVector(keys))
    return np.asarray(jm.fullMatrix())


def _apply(camera: CameraModel, cams: list[int], cfg: CalibrateConfig, x: Array) -> CameraModel:
    m = camera.copy()
    n = len(cfg.params)
    for i, ck in enumerate(cams):
        c, b = (ck // 10, ck % 10) if cfg.per_band else (ck, slice(None))
        for j, p in enumerate(cfg.params):
            v = x[i * n + j]
            if p in ("delta", "beta", "epsilon"):
                getattr(m, p)[c] += v
            elif p == "f":
                m.focal_length[c, b] += v
            else:
                m.alpha[c, b, int(p[-1])] += v
    if cfg.estimate_omega:
        m.omega += x[len(cams) * n: len(cams) * n + 3]
    return m


def calibrate_passes(
    passes: list[OrbitPass],
    camera: CameraModel,
    gcps: GcpDatabase,
    cfg: CalibrateConfig = CalibrateConfig(),
    progress: Callable[[str], None] | None = None,
    table: Any = None,
) -> CalibrationResult:
    """Space resection of the camera model over GCP passes (see the module docstring).

    With ``table`` (a :class:`~misrgraph.camera.TabulatedCameraModel`) every pass uses the model
    interpolated at its own temperature; the estimated corrections are common to all temperatures
    and are reported relative to ``camera`` (the model at the median pass temperature).
    """
    if not passes:
        raise DegenerateProblemError("no passes to calibrate from")
    t0 = time.perf_counter()
    passes = [p for p in passes if np.any(p.landmarks.kind == KIND_GCP)]
    if not passes:
        raise DegenerateProblemError("none of the passes has GCP observations; calibration needs GCPs")
    params = SolverParams(max_iterations=cfg.max_iterations)
    exclude = [np.zeros(len(p.observations), bool) for p in passes]
    rejected: list[tuple[int, int, float]] = []
    if cfg.robust != "none":
        prob, graphs = _build(passes, camera, gcps, cfg.graph_config(group_by="observation", robust=cfg.robust,
                                                                      robust_k=cfg.robust_k), None, progress, table)
        if progress:
            progress("robust solve")
        res = solve(prob, params)
        for i, g in enumerate(graphs):
            r, _ = g.collinearity.residuals(res.values)
            w = np.linalg.norm(r / g.collinearity.sigma_px[:, None], axis=1)
            idx = g.obs_index[g.collinearity.order]
            bad = w > cfg.reject_sigma
            exclude[i][idx[bad]] = True
            rejected += [(i, int(j), float(x)) for j, x in zip(idx[bad], w[bad])]
    prob, graphs = _build(passes, camera, gcps, cfg.graph_config(), exclude, progress, table)
    if progress:
        progress("least-squares solve")
    res = solve(prob, params)
    keys, labels, cams = _camera_keys_labels(graphs, cfg)
    if progress:
        progress("marginal covariance")
    cov = _joint_marginal(prob, res.values, keys)
    x = np.concatenate([res.values.atVector(k) for k in keys])
    # from variable units (CAMERA_PARAM_SCALE) to SI
    unit = np.concatenate([CAMERA_PARAM_SCALE[[CAMERA_PARAMS.index(p) for p in cfg.params]]] * (len(keys) - cfg.estimate_omega)
                          + ([np.ones(3)] if cfg.estimate_omega else []))
    x = x * unit
    cov = cov * np.outer(unit, unit)
    prior = np.array([CAMERA_PRIOR_SIGMA[p] for _ in cams for p in cfg.params]
                     + ([GraphConfig().omega_prior_rad] * 3 if cfg.estimate_omega else []))
    model = _apply(camera, cams, cfg, x)
    model.provenance = {"source": "misrgraph calibrate", "software": f"misrgraph {__version__}",
                        "passes": str(len(passes)), "params": ",".join(cfg.params)}
    return CalibrationResult(model, keys, labels, x, cov, prior, rejected, res.iterations, res.final_error,
                             time.perf_counter() - t0, graphs)


# ---------------------------------------------------------------------------- scoring
def _directions(m: CameraModel, c: int, b: int, s: Array) -> Array:
    return m.direction_scs(np.full(s.size, c), np.full(s.size, b), np.zeros(s.size), s)


def pointing_error_px(estimated: CameraModel, reference: CameraModel, c: int, b: int = RED, n: int = 48) -> float:
    """RMS over the swath of the angle between two models' pointing, in units of the pixel IFOV."""
    s = np.linspace(0, 1503, n)
    d1, d2 = _directions(estimated, c, b, s), _directions(reference, c, b, s)
    ang = np.arccos(np.clip(np.sum(d1 * d2, axis=1), -1, 1))
    return float(np.sqrt(np.mean((ang / estimated.ifov_cross_rad(c, b, s)) ** 2)))


def summarise(res: CalibrationResult, cfg: CalibrateConfig, supplied: CameraModel, truth: CameraModel | None,
              draws: int = 60) -> dict[str, Any]:
    """The JSON summary of the calibration issue (see ``misrgraph calibrate --help``)."""
    sig = np.sqrt(np.diag(res.covariance))
    corr = res.covariance / np.outer(sig, sig)
    rng = np.random.default_rng(0)
    chol = np.linalg.cholesky(0.5 * (res.covariance + res.covariance.T))
    samples = [_apply(supplied, _cams(res, cfg), cfg, res.values + chol @ rng.standard_normal(res.values.size)) for _ in range(draws)]
    cams_out: dict[str, Any] = {}
    poorly = []
    for i, label in enumerate(res.labels):
        if sig[i] > cfg.poorly_determined_ratio * res.prior_sigma[i]:
            poorly.append({"parameter": label, "sigma": float(sig[i]), "prior_sigma": float(res.prior_sigma[i]),
                           "ratio": float(sig[i] / res.prior_sigma[i])})
    for c, name in enumerate(CAMERAS):
        entry: dict[str, Any] = {"params": {}}
        for i, label in enumerate(res.labels):
            if label.startswith(name + ".") or label.startswith(name + "/"):
                entry["params"][label[len(name) + 1:]] = {"value": float(res.values[i]), "sigma": float(sig[i])}
        if not entry["params"]:
            continue
        if truth is not None:
            entry["pointing_error_px"] = pointing_error_px(res.camera, truth, c)
            entry["pointing_error_before_px"] = pointing_error_px(supplied, truth, c)
        entry["sigma_px"] = float(np.sqrt(np.mean([pointing_error_px(sm, res.camera, c) ** 2 for sm in samples])))
        cams_out[name] = entry
    out: dict[str, Any] = {"cameras": cams_out, "iterations": res.iterations, "final_cost": res.final_cost,
                           "seconds": res.seconds, "passes": len(res.graphs),
                           "rejected_observations": len(res.rejected),
                           "rejected": [{"pass": int(p), "observation": int(o), "normalised_residual": r} for p, o, r in res.rejected],
                           "poorly_determined": poorly,
                           "correlation": {"labels": res.labels, "matrix": np.round(corr, 4).tolist()}}
    if truth is not None:
        out["max_pointing_error_px"] = max(v["pointing_error_px"] for v in cams_out.values())
        true_x = _true_corrections(res, cfg, supplied, truth)
        e = res.values - true_x
        out["nees"] = float(e @ np.linalg.solve(res.covariance, e) / e.size)
        out["nees_dim"] = int(e.size)
    return out


def _cams(res: CalibrationResult, cfg: CalibrateConfig) -> list[int]:
    keys: dict[int, int] = {}
    for g in res.graphs:
        keys.update(g.camera_keys)
    return sorted(keys)


def _true_corrections(res: CalibrationResult, cfg: CalibrateConfig, supplied: CameraModel, truth: CameraModel) -> Array:
    out = []
    for ck in _cams(res, cfg):
        c, b = (ck // 10, ck % 10) if cfg.per_band else (ck, RED)
        for p in cfg.params:
            if p in ("delta", "beta", "epsilon"):
                out.append(getattr(truth, p)[c] - getattr(supplied, p)[c])
            elif p == "f":
                out.append(truth.focal_length[c, b] - supplied.focal_length[c, b])
            else:
                out.append(truth.alpha[c, b, int(p[-1])] - supplied.alpha[c, b, int(p[-1])])
    if cfg.estimate_omega:
        out += list(truth.omega - supplied.omega)
    return np.array(out)


def run_calibrate(
    scenario_dir: str | os.PathLike[str],
    camera_model: str | os.PathLike[str] | None = None,
    gcp_file: str | os.PathLike[str] | None = None,
    out: str | os.PathLike[str] | None = None,
    cfg: CalibrateConfig = CalibrateConfig(),
    max_passes: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Calibrate from every pass of a scenario directory; write the recalibrated model when ``out``."""
    d = Path(scenario_dir)
    if not d.is_dir():
        raise InputError("SCENARIO_DIR", str(d), "a directory written by 'misrgraph simulate --scenario month'")
    files = sorted((d / "passes").glob("*.h5"))
    if not files:
        raise FileFormatError(d / "passes", "no pass files (*.h5)")
    if max_passes is not None:
        files = files[:max_passes]
    cam_path = Path(camera_model) if camera_model else d / "camera_model.h5"
    from misrgraph.camera import load_camera_model

    table = load_camera_model(cam_path)
    gcps = GcpDatabase.load(gcp_file or d / "gcp.h5")
    passes = []
    for i, f in enumerate(files):
        if progress and i % 25 == 0:
            progress(f"reading pass {i + 1}/{len(files)}")
        passes.append(OrbitPass.load(f))
    supplied = table if isinstance(table, CameraModel) else table.at_temperature(
        float(np.median([p.temperature_c for p in passes])))
    truth_path = d / "camera_truth.h5"
    truth = CameraModel.load(truth_path) if truth_path.exists() else None
    res = calibrate_passes(passes, supplied, gcps, cfg, progress, table=None if isinstance(table, CameraModel) else table)
    summary = summarise(res, cfg, supplied, truth)
    if out is not None:
        with atomic_h5(out, "camera_model") as f:
            res.camera.provenance.update({"scenario": str(d), "camera_model_in": str(cam_path),
                                          "config": json.dumps(dataclasses.asdict(cfg))})
            res.camera.write_group(f.create_group("camera_model"))
            g = f.create_group("calibration")
            g.create_dataset("labels", data=np.array(res.labels, dtype=object), dtype=__import__("h5py").string_dtype())
            write_dataset(g, "corrections", res.values, units="rad (angles), m (f), pixel^-i (alpha_i)")
            write_dataset(g, "covariance", res.covariance)
            write_dataset(g, "correlation", np.asarray(summary["correlation"]["matrix"]))
            g.attrs["summary_json"] = json.dumps({k: v for k, v in summary.items() if k != "correlation"})
    return summary
