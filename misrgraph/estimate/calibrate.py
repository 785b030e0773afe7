"""Camera geometric model calibration by space resection over a month of GCP passes (seed 4.1).

One graph holds every GCP pass: the GCP landmarks (shared by the passes that see them, each with
its 30 m ENU prior, eq. 32), the camera corrections (shared by all passes: default delta, beta,
eps per camera and alpha_2, alpha_3 within the focal plane's pre-flight knowledge; optionally
f and other alpha_i, per band, and the common omega), and per pass the
navigation errors as nuisance variables with priors from the navigation accuracy: the ephemeris
error of eq. 19 and the attitude error spline of eqs. 23-27 at the adjustment's knot spacing.

Why this nuisance design: the navigation errors of one pass shift all nine views of that pass
together and change from pass to pass, while a camera error is the same in every pass. With the
nuisance variables carrying honest priors, the only way to explain a residual that repeats in
one camera across many passes is a camera correction -- the averaging over passes is what
separates the two (seed 2: "each GCP seen in at least three passes"). Knots are never removed
here (GCP views are sparse, and merged spline segments would mis-fit them, see
docs/explanation/conventions.md); knots without data are held by their priors. ``misrgraph bench
separation`` measures how the camera error shrinks with the number of passes.

Procedure: robust (Cauchy) solve -> reject observations above ``reject_sigma`` -> least-squares
re-solve; joint marginal covariance of the camera parameters (:func:`misrgraph.estimate.problem.marginal_covariances`,
by a sparse solve of the Schur complement); a
parameter whose posterior sigma is more than ``poorly_determined_ratio`` of its prior sigma is
reported as poorly determined (the data hardly constrain it).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any, Callable

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import keys as K
from factors.collinearity import camera_param_scale
from misrgraph import __version__
from misrgraph.config import Config
from misrgraph.errors import DegenerateProblemError, InputError
from misrgraph.estimate.graph import (
    GraphConfig,
    PassGraph,
    build_pass_graph,
    calibration_prior_sigma,
    check_jitter,
    merge_problems,
)
from misrgraph.estimate.problem import Problem, marginal_covariances, variance_factor
from misrgraph.estimate.solver import SolverParams, check_converged, solve
from misrgraph.io.passes import KIND_GCP, OrbitPass
from misrgraph.io.results import capped_list
from misrgraph.model.camera import CameraModel, TabulatedCameraModel
from misrgraph.model.constants import BANDS, CAMERAS
from misrgraph.model.errormodels import JITTER_PERIODS_S
from misrgraph.model.gcp import GcpDatabase
from misrgraph.model.noise import NoiseModel

__all__ = [
    "CalibrateConfig",
    "CalibrationResult",
    "calibrate_passes",
    "pointing_error_px",
    "temperature_bins",
    "thermal_slopes",
    "slope_estimates",
    "SlopeEstimates",
    "summarise",
    "evaluation_grid",
    "calibrated_models",
    "supplied_models_at",
    "calibrated_bands",
    "camera_keys",
    "decode_camera_key",
    "param_value",
    "camera_variance_components",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
RED = BANDS.index("red")


@dataclass(frozen=True)
class CalibrateConfig(Config):
    """Calibration settings. ``params`` from :data:`factors.collinearity.CAMERA_PARAMS`."""

    #: the three angles, and alpha_2, alpha_3 held by the focal plane's pre-flight knowledge
    #: (``focal_prior_px``): with the angles alone, a month precise enough biases them with the
    #: focal plane's unmodelled error (docs/explanation/design.md, "The calibration's
    #: parameters"). f stays out, as in the pass adjustment: it moves a red-band pixel by a tiny
    #: fraction of a pixel and no month determines it beyond its prior
    params: tuple = ("delta", "beta", "epsilon", "alpha2", "alpha3")
    per_band: bool = False
    estimate_omega: bool = False
    knot_spacing_s: tuple = (60.0, 60.0, 60.0)
    knot_prior: str = "process"
    #: f and alpha_i (when among ``params``) get the prior of a focal plane measured before
    #: flight to this many pixels at the swath edge
    #: (:func:`~misrgraph.estimate.graph.calibration_prior_sigma`); 0: the wide post-launch prior
    #: of :data:`~misrgraph.estimate.graph.CAMERA_PRIOR_SIGMA`
    focal_prior_px: float = 0.05
    robust: str = "cauchy"
    robust_k: float = 3.0
    reject_sigma: float = 5.0
    max_iterations: int = 100
    poorly_determined_ratio: float = 0.5
    temperature_bins: int = 1
    #: keep the result of a solve that did not converge (flagged) instead of failing
    accept_unconverged: bool = False
    #: rounds of variance-component estimation after the least-squares solve: each camera's
    #: observation sigmas are rescaled by its sigma0 (Foerstner: ``sqrt(sum e^2 / sum r)`` over the
    #: camera's image coordinates, ``r`` their redundancy numbers) and the month re-solved, until
    #: every camera is within ``variance_component_tol`` of 1; 0 (default) keeps the stated sigmas.
    #: The residuals show only what the GCP positions and the navigation cannot absorb: on matched
    #: GCPs (error / LSM sigma ~2 against the truth in the D cameras) sigma0 came out 0.64-0.98
    #: and rescaling made the calibration worse (README), so it stays off by default
    variance_component_rounds: int = 0
    variance_component_tol: float = 0.05
    #: 1 sigma (arcsec, per angle) of the GN&C's attitude jitter (periods log-uniform in
    #: ``attitude_jitter_periods_s``, s): the part the knots cannot follow is noise in every GCP
    #: observation, carried into its line and sample sigma by its pointing sensitivity, as in the
    #: pass adjustment (``AdjustConfig.graph.attitude_jitter_arcsec``). 0 (default): the matcher's sigma alone
    attitude_jitter_arcsec: float = 0.0
    attitude_jitter_periods_s: tuple = JITTER_PERIODS_S
    #: the navigation's error levels (attitude process and its knots' spacing, which replaces
    #: ``knot_spacing_s``; ephemeris) of every pass's nuisance variables
    #: (:class:`~misrgraph.model.noise.NoiseModel`, ``--noise-model``); None: the pre-flight
    #: defaults of :class:`~misrgraph.estimate.graph.GraphConfig`
    noise: NoiseModel | None = None

    def __post_init__(self) -> None:
        check_jitter(self.attitude_jitter_arcsec, self.attitude_jitter_periods_s)
        if int(self.temperature_bins) != self.temperature_bins or self.temperature_bins < 1:
            raise InputError("temperature_bins", self.temperature_bins, "an integer >= 1")
        v = self.variance_component_rounds
        if isinstance(v, bool) or int(v) != v or v < 0:
            raise InputError("variance_component_rounds", v, "an integer >= 0")
        if not self.variance_component_tol > 0:
            raise InputError("variance_component_tol", self.variance_component_tol, "a positive fraction")
        if not (np.isfinite(self.focal_prior_px) and self.focal_prior_px >= 0):
            raise InputError(
                "focal_prior_px", self.focal_prior_px, "0 (the wide pre-flight prior) or a positive 1 sigma in pixels"
            )

    def graph_config(self, **kw: Any) -> GraphConfig:
        base = dict(
            knot_spacing_s=self.knot_spacing_s,
            knot_prior=self.knot_prior,
            threshold1=0,
            threshold2=0,
            use_dem=False,
            estimate_camera=True,
            camera_params=tuple(self.params),
            camera_per_band=self.per_band,
            camera_prior_calibration=True,
            calibration_focal_prior_px=self.focal_prior_px,
            estimate_omega=self.estimate_omega,
            attitude_jitter_arcsec=self.attitude_jitter_arcsec,
            attitude_jitter_periods_s=tuple(self.attitude_jitter_periods_s),
        )
        if self.noise is not None:
            base.update(self.noise.navigation_fields())
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
    #: thermal calibration: temperature (deg C) of each bin, the supplied model there, and the
    #: calibrated table (None with one bin); pass temperatures for the valid range
    bin_temperatures_c: Array = dataclasses.field(default_factory=lambda: np.zeros(1))
    supplied_models: list[CameraModel] = dataclasses.field(default_factory=list)
    table: TabulatedCameraModel | None = None
    pass_temperatures_c: Array = dataclasses.field(default_factory=lambda: np.zeros(0))
    supplied_table: TabulatedCameraModel | None = None
    #: how the least-squares solve ended (:data:`misrgraph.estimate.solver.STATUSES`)
    status: str = "converged"

    @property
    def binned(self) -> bool:
        """Corrections estimated per temperature bin (more than one supplied model)."""
        return len(self.supplied_models) > 1

    #: a-posteriori variance factor and its chi-square test (:func:`misrgraph.estimate.problem.variance_factor`)
    variance_factor: dict = dataclasses.field(default_factory=dict)
    #: per round of variance-component estimation, each camera's ``{sigma0, redundancy, rows}``,
    #: and the sigma scale finally applied per camera (empty without ``variance_component_rounds``)
    variance_components: dict = dataclasses.field(default_factory=dict)


def _build(
    passes: list[OrbitPass],
    camera: CameraModel,
    gcps: GcpDatabase,
    cfg: GraphConfig,
    exclude: list[NDArray[np.bool_]] | None,
    progress: Callable[[str], None] | None,
    table: Any = None,
    bins: NDArray[np.int64] | None = None,
) -> tuple[Problem, list[PassGraph]]:
    shared: set[int] = set()
    graphs = []
    for i, p in enumerate(passes):
        if progress and i % 20 == 0:
            progress(f"graph: pass {i + 1}/{len(passes)}")
        pg = build_pass_graph(
            p,
            camera,
            None,
            gcps,
            cfg,
            pass_index=i,
            shared=shared,
            exclude_observations=exclude[i] if exclude else None,
            camera_for_pass=table.at_temperature(p.temperature_c) if table is not None else None,
            temperature_bin=int(bins[i]) if bins is not None else 0,
        )
        shared |= set(pg.problem.initial.keys()) & (set(pg.problem.eliminate_first) | set(pg.problem.eliminate_last))
        graphs.append(pg)
    return merge_problems([g.problem for g in graphs]), graphs


def decode_camera_key(ck: int, cfg: CalibrateConfig) -> tuple[int, int, int | None]:
    """(temperature bin, camera, band or None) of a camera code of ``PassGraph.camera_keys``."""
    code = ck % 1000
    return ck // 1000, *((code // 10, code % 10) if cfg.per_band else (code, None))


def _camera_keys_labels(
    graphs: list[PassGraph], cfg: CalibrateConfig, bin_temps: Array | None = None
) -> tuple[list[int], list[str], list[int]]:
    keys: dict[int, int] = {}
    for g in graphs:
        keys.update(g.camera_keys)
    out_k, labels, cams = [], [], []
    for ck in sorted(keys):
        t_bin, c, b = decode_camera_key(ck, cfg)
        name = CAMERAS[c] + (f"/{BANDS[b]}" if b is not None else "")
        if cfg.temperature_bins > 1 and bin_temps is not None:
            name += f"@{bin_temps[t_bin]:+.1f}C"
        out_k.append(keys[ck])
        cams.append(ck)
        labels += [f"{name}.{p}" for p in cfg.params]
    if cfg.estimate_omega:
        out_k.append(K.omega_key())
        labels += ["omega_x", "omega_y", "omega_z"]
    return out_k, labels, cams


def _apply(
    camera: CameraModel, cams: list[int], cfg: CalibrateConfig, x: Array, temperature_bin: int = 0
) -> CameraModel:
    m = camera.copy()
    n = len(cfg.params)
    for i, ck in enumerate(cams):
        t_bin, c, band = decode_camera_key(ck, cfg)
        if t_bin != temperature_bin:
            continue
        for j, p in enumerate(cfg.params):
            m.add_correction(p, c, band, x[i * n + j])
    if cfg.estimate_omega:
        m.omega += x[len(cams) * n : len(cams) * n + 3]
    return m


def camera_variance_components(
    passes: list[OrbitPass], graphs: list[PassGraph], values: gtsam.Values
) -> dict[int, dict[str, float]]:
    """Each camera's variance component at the solution ``values`` of a month's graphs:
    ``{camera index: {"sigma0", "redundancy", "rows"}}`` over its image coordinates (Foerstner:
    ``sigma0^2 = sum e^2 / sum r`` with ``e`` the whitened residuals and ``r`` the redundancy
    numbers, :func:`misrgraph.estimate.reliability.reliability`), from the passes' problems merged
    into one flat problem. Empty when the problem is outside the flat form."""
    from misrgraph.estimate.graph import merge_flat
    from misrgraph.estimate.problem import NotFlat
    from misrgraph.estimate.reliability import reliability

    try:
        flat = merge_flat([g.problem for g in graphs]).flat()
    except NotFlat as exc:
        log.warning("variance components not estimated: %s", exc)
        return {}
    rel = reliability(flat, flat.from_values(values))
    # the merged batch's image points are the passes' in pass order, each pass's in its batch order
    cams = np.concatenate([p.observations.camera[g.obs_index[g.collinearity.order]] for p, g in zip(passes, graphs)])
    rows_cam = np.repeat(cams, 2)  # line and sample rows
    coll = rel.families["collinearity"]
    out = {}
    for c in np.unique(cams):
        rows = np.zeros(rel.e.size, bool)
        rows[coll] = rows_cam == c
        out[int(c)] = rel.variance_component(rows)
    return out


def calibrate_passes(
    passes: list[OrbitPass],
    camera: CameraModel,
    gcps: GcpDatabase,
    cfg: CalibrateConfig = CalibrateConfig(),
    progress: Callable[[str], None] | None = None,
    table: Any = None,
) -> CalibrationResult:
    """Space resection of the camera model over GCP passes (see the module docstring).

    With ``table`` (a :class:`~misrgraph.model.camera.TabulatedCameraModel`) every pass uses the model
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
    temps = np.array([p.temperature_c for p in passes])
    bins, bin_temps = temperature_bins(passes, cfg.temperature_bins)
    supplied_models = [table.at_temperature(t) if table is not None else camera for t in bin_temps]
    exclude = [np.zeros(len(p.observations), bool) for p in passes]
    rejected: list[tuple[int, int, float]] = []
    if cfg.robust != "none":
        prob, graphs = _build(
            passes,
            camera,
            gcps,
            cfg.graph_config(group_by="observation", robust=cfg.robust, robust_k=cfg.robust_k),
            None,
            progress,
            table,
            bins,
        )
        if progress:
            progress("robust solve")
        res = solve(prob, params)
        check_converged(res, "the robust solve (blunder screening)", cfg.accept_unconverged)
        for i, g in enumerate(graphs):
            r, _ = g.collinearity.residuals(res.values)
            w = np.linalg.norm(r / g.collinearity.sigma_px, axis=1)
            idx = g.obs_index[g.collinearity.order]
            bad = w > cfg.reject_sigma
            exclude[i][idx[bad]] = True
            rejected += [(i, int(j), float(x)) for j, x in zip(idx[bad], w[bad])]
    prob, graphs = _build(passes, camera, gcps, cfg.graph_config(), exclude, progress, table, bins)
    if progress:
        progress("least-squares solve")
    res = solve(prob, params)
    check_converged(res, "the least-squares solve", cfg.accept_unconverged)
    vc: dict[str, Any] = {}
    if cfg.variance_component_rounds:
        stated = [p.observations.sigma_px.copy() for p in passes]
        scale = np.ones(len(CAMERAS))
        vc["rounds"] = []
        for rnd in range(cfg.variance_component_rounds):
            s0 = camera_variance_components(passes, graphs, res.values)
            vc["rounds"].append({CAMERAS[c]: v for c, v in s0.items()})
            moved = {
                c: v["sigma0"]
                for c, v in s0.items()
                if v["redundancy"] >= 10.0 and abs(v["sigma0"] - 1.0) > cfg.variance_component_tol
            }
            if not moved:
                break
            for c, v in moved.items():
                scale[c] *= v
            if progress:
                progress(
                    f"variance components: round {rnd + 1}, sigma scale "
                    + ", ".join(f"{CAMERAS[c]} {scale[c]:.2f}" for c in sorted(moved))
                )
            passes = [
                dataclasses.replace(
                    p, observations=dataclasses.replace(p.observations, sigma_px=st * scale[p.observations.camera])
                )
                for p, st in zip(passes, stated)
            ]
            prob, graphs = _build(passes, camera, gcps, cfg.graph_config(), exclude, progress, table, bins)
            prob.warm_start(res.values)
            res = solve(prob, params)
            check_converged(res, "the least-squares solve after variance-component estimation", cfg.accept_unconverged)
        vc["sigma_scale"] = {name: float(scale[c]) for c, name in enumerate(CAMERAS)}
    keys, labels, cams = _camera_keys_labels(graphs, cfg, bin_temps)
    if progress:
        progress("marginal covariance")
    cov = marginal_covariances(prob, res.values, joint_keys=keys).joint
    x = np.concatenate([res.values.atVector(k) for k in keys])
    # from variable units (CAMERA_PARAM_SCALE) to SI
    unit = np.concatenate(
        [camera_param_scale(cfg.params)] * (len(keys) - cfg.estimate_omega)
        + ([np.ones(3)] if cfg.estimate_omega else [])
    )
    x = x * unit
    cov = cov * np.outer(unit, unit)
    prior = np.concatenate(
        [
            calibration_prior_sigma(
                supplied_models[0], decode_camera_key(ck, cfg)[1], tuple(cfg.params), cfg.focal_prior_px
            )
            for ck in cams
        ]
        + [np.full(3 if cfg.estimate_omega else 0, GraphConfig().omega_prior_rad)]
    )
    prov = {
        "source": "misrgraph calibrate",
        "software": f"misrgraph {__version__}",
        "passes": str(len(passes)),
        "params": ",".join(cfg.params),
    }
    models = []
    for j, (base, t_bin) in enumerate(zip(supplied_models, bin_temps)):
        m = _apply(base, cams, cfg, x, j)
        m.temperature_c = float(t_bin)
        m.provenance = dict(prov)
        models.append(m)
    out = CalibrationResult(
        models[0],
        keys,
        labels,
        x,
        cov,
        prior,
        rejected,
        res.iterations,
        res.final_error,
        time.perf_counter() - t0,
        graphs,
        bin_temps,
        supplied_models,
        None,
        temps,
        table,
        res.status,
        variance_factor(prob, res.final_error),
        vc,
    )
    if len(models) == 1 and table is not None:  # a supplied table: the common correction at every entry
        out.table = TabulatedCameraModel([_apply(m, cams, cfg, x, 0) for m in table.models], table.valid_range_c)
        for m in out.table.models:
            m.provenance = dict(prov)
    elif len(models) > 1:
        out.table = _fit_table(out, cfg, x, table if table is not None else camera)
        for m in out.table.models:
            m.provenance = dict(prov, thermal="GLS line through the temperature bins")
        out.camera = out.table.at_temperature(float(np.median(temps)))
    return out


def temperature_bins(passes: list[OrbitPass], n_bins: int) -> tuple[NDArray[np.int64], Array]:
    """Split passes into ``n_bins`` bins of about equal counts by camera temperature.

    Returns the bin of each pass and each bin's temperature (deg C): the mean of its passes'
    temperatures weighted by their GCP observations, since a bin's correction is the
    least-squares fit of one constant to its passes, about that weighted mean for a parameter
    linear in temperature.
    """
    temps = np.array([p.temperature_c for p in passes], float)
    if n_bins == 1:
        return np.zeros(len(passes), np.int64), np.array([float(np.median(temps))])
    if len(passes) < 2 * n_bins:
        raise DegenerateProblemError(f"{len(passes)} GCP passes cannot fill {n_bins} temperature bins (need >= 2 each)")
    order = np.argsort(temps, kind="stable")
    bins = np.empty(len(passes), np.int64)
    for j, chunk in enumerate(np.array_split(order, n_bins)):
        bins[chunk] = j
    weight = np.array([np.sum(p.landmarks.kind[p.observations.landmark] == KIND_GCP) for p in passes], float)
    bin_temps = np.array([np.average(temps[bins == j], weights=weight[bins == j] + 1e-9) for j in range(n_bins)])
    if np.any(np.diff(bin_temps) <= 0):
        raise DegenerateProblemError(
            f"temperature bins are not distinct ({bin_temps.round(3).tolist()} C); use fewer bins"
        )
    return bins, bin_temps


# ---------------------------------------------------------------------------- scoring
def _directions(m: CameraModel, c: int, b: int, s: Array) -> Array:
    return m.direction_scs(np.full(s.size, c), np.full(s.size, b), np.zeros(s.size), s)


def pointing_error_px(estimated: CameraModel, reference: CameraModel, c: int, b: int = RED, n: int = 48) -> float:
    """RMS over the swath of the angle between two models' pointing, in units of the pixel IFOV."""
    s = np.linspace(0, 1503, n)
    d1, d2 = _directions(estimated, c, b, s), _directions(reference, c, b, s)
    ang = np.arccos(np.clip(np.sum(d1 * d2, axis=1), -1, 1))
    return float(np.sqrt(np.mean((ang / estimated.ifov_cross_rad(c, b, s)) ** 2)))


def _supplied_model(res: CalibrationResult, supplied: CameraModel) -> CameraModel | TabulatedCameraModel:
    """The model the corrections were estimated against: the supplied table, else the (first
    bin's) supplied model."""
    return res.supplied_table if res.supplied_table is not None else (res.supplied_models or [supplied])[0]


def evaluation_grid(res: CalibrationResult, supplied: CameraModel, thermal: bool = False) -> Array:
    """Temperatures (deg C) at which a calibration is summarised: five across the passes' range
    when anything is thermal (``thermal`` or a temperature-binned or tabulated calibration), else
    the passes' median (every temperature gives the same numbers)."""
    temps = res.pass_temperatures_c if res.pass_temperatures_c.size else np.array([supplied.temperature_c])
    thermal = thermal or res.binned or res.supplied_table is not None
    return (
        np.linspace(temps.min(), temps.max(), 5)
        if thermal and np.ptp(temps) > 0
        else np.array([float(np.median(temps))])
    )


def calibrated_models(
    res: CalibrationResult, cfg: CalibrateConfig, supplied: CameraModel, grid: Array, x: Array | None = None
) -> list[CameraModel]:
    """The calibrated model at each temperature of ``grid`` for corrections ``x`` (default: the
    estimate); with temperature bins, through the fitted thermal table."""
    x = res.values if x is None else x
    cams = camera_keys(res, cfg)
    sup_model = _supplied_model(res, supplied)
    if not res.binned:
        return [_apply(sup_model.at_temperature(t), cams, cfg, x, 0) for t in grid]
    tab = _fit_table(res, cfg, x, sup_model)
    return [tab.at_temperature(t) for t in grid]


def supplied_models_at(res: CalibrationResult, supplied: CameraModel, grid: Array) -> list[CameraModel]:
    """The supplied (uncalibrated) model at each temperature of ``grid``."""
    sup_model = _supplied_model(res, supplied)
    return [sup_model.at_temperature(t) for t in grid]


def calibrated_bands(res: CalibrationResult, cfg: CalibrateConfig, c: int) -> list[int]:
    """The bands of camera ``c`` that have their own corrections (``[red]`` for camera-level ones)."""
    return sorted(
        {decode_camera_key(ck, cfg)[2] for ck in camera_keys(res, cfg) if decode_camera_key(ck, cfg)[1] == c} - {None}
    ) or [RED]


def summarise(res: CalibrationResult, cfg: CalibrateConfig, supplied: CameraModel) -> dict[str, Any]:
    """The JSON summary of a calibration from the estimate alone (see ``misrgraph calibrate --help``):
    corrections with sigma and, per parameter, ``sigma_px``: the pointing change (px, RMS over the
    swath and the temperature grid of :func:`evaluation_grid`) when that parameter alone moves by
    its 1 sigma -- the unit in which a change of the parameter shows in the images; each camera's
    posterior pointing spread ``sigma_px`` (the same RMS of the pointing's 1 sigma, propagated
    linearly from the posterior ``C = L L^T``: the sum over the columns ``l_i`` of ``L`` of the
    squared pointing change when the corrections move by ``l_i``; no sampling error: all its
    parameters together), poorly determined parameters,
    the correlation matrix, and with temperature bins the thermal slopes (:func:`thermal_slopes`). Scores against a
    simulated truth are added by :func:`misrgraph.evaluate.calibration.score_calibration`.
    """
    sig = np.sqrt(np.diag(res.covariance))
    corr = res.covariance / np.outer(sig, sig)
    chol = np.linalg.cholesky(0.5 * (res.covariance + res.covariance.T))
    grid = evaluation_grid(res, supplied)
    est_at = calibrated_models(res, cfg, supplied, grid)
    moved = [calibrated_models(res, cfg, supplied, grid, res.values + chol[:, i]) for i in range(res.values.size)]
    cams_out: dict[str, Any] = {}
    poorly = []
    for i, label in enumerate(res.labels):
        if sig[i] > cfg.poorly_determined_ratio * res.prior_sigma[i]:
            poorly.append(
                {
                    "parameter": label,
                    "sigma": float(sig[i]),
                    "prior_sigma": float(res.prior_sigma[i]),
                    "ratio": float(sig[i] / res.prior_sigma[i]),
                }
            )
    for c, name in enumerate(CAMERAS):
        entry: dict[str, Any] = {"params": {}}
        bands = calibrated_bands(res, cfg, c)
        for i, label in enumerate(res.labels):
            if label.startswith(name + ".") or label.startswith(name + "/") or label.startswith(name + "@"):
                entry["params"][label[len(name) + 1 :] if label[len(name)] in "./" else label[len(name) :]] = {
                    "value": float(res.values[i]),
                    "sigma": float(sig[i]),
                    "sigma_px": _parameter_pointing_px(res, cfg, supplied, grid, est_at, i, sig[i], c, bands),
                }
        if not entry["params"]:
            continue
        entry["sigma_px"] = float(np.sqrt(np.sum([_mean_square_pointing(m, est_at, c, bands) for m in moved])))
        cams_out[name] = entry
    out: dict[str, Any] = {
        "cameras": cams_out,
        "solver_status": res.status,
        "variance_factor": res.variance_factor,
        **({"variance_components": res.variance_components} if res.variance_components else {}),
        "iterations": res.iterations,
        "final_cost": res.final_cost,
        "seconds": res.seconds,
        "passes": len(res.graphs),
        "rejected_observations": capped_list(
            [{"pass": int(p), "observation": int(o), "normalised_residual": float(r)} for p, o, r in res.rejected], None
        ),
        "poorly_determined": poorly,
        "correlation": {"labels": res.labels, "matrix": np.round(corr, 6).tolist()},
    }
    if res.binned:
        out["temperature_bins_c"] = [float(t) for t in res.bin_temperatures_c]
        out["thermal"] = thermal_slopes(res, cfg)
    return out


def _mean_square_pointing(models: list[CameraModel], est_at: list[CameraModel], c: int, bands: list[int]) -> float:
    """Mean over the temperature grid and ``bands`` of camera ``c``'s squared pointing change
    (px^2, each RMS over the swath) from the estimate's models ``est_at`` to ``models``."""
    return float(np.mean([pointing_error_px(m, e, c, b) ** 2 for m, e in zip(models, est_at) for b in bands]))


def _parameter_pointing_px(
    res: CalibrationResult,
    cfg: CalibrateConfig,
    supplied: CameraModel,
    grid: Array,
    est_at: list[CameraModel],
    i: int,
    sigma: float,
    c: int,
    bands: list[int],
) -> float:
    """Camera ``c``'s pointing change (px, RMS over the swath, ``grid`` and ``bands``) when
    correction ``i`` alone moves by ``sigma`` from the estimate (``est_at``: the estimate's models
    on ``grid``)."""
    x = res.values.copy()
    x[i] += sigma
    return float(np.sqrt(_mean_square_pointing(calibrated_models(res, cfg, supplied, grid, x), est_at, c, bands)))


def param_value(m: CameraModel, p: str, c: int, b: int) -> float:
    """A parameter's value for camera ``c`` and band ``b`` (angles include the band's offset)."""
    if p in ("delta", "beta", "epsilon"):
        return float(getattr(m, p)[c] + getattr(m, "band_" + p)[c, b])
    if p == "f":
        return float(m.focal_length[c, b])
    return float(m.alpha[c, b, int(p[-1])])


def _gls_groups(
    res: CalibrationResult, cfg: CalibrateConfig
) -> list[tuple[int, int | None, int, list[int], Array, Array]]:
    """Per (camera, band, parameter): (camera, band, param index, indices into ``res.values``,
    bin temperatures, GLS weights (2, k)) of the line ``a + s (T - mean T)`` through the bins."""
    cams = camera_keys(res, cfg)
    n = len(cfg.params)
    col = {ck: i for i, ck in enumerate(cams)}
    groups: dict[tuple[int, int | None], list[int]] = {}
    for ck in cams:
        _, c, band = decode_camera_key(ck, cfg)
        groups.setdefault((c, band), []).append(ck)
    out = []
    for (c, band), cks in sorted(groups.items(), key=lambda kv: (kv[0][0], -1 if kv[0][1] is None else kv[0][1])):
        t = res.bin_temperatures_c[[decode_camera_key(ck, cfg)[0] for ck in cks]]
        a = np.stack([np.ones(len(t)), t - t.mean()], 1)
        for j in range(n):
            idx = [col[ck] * n + j for ck in cks]
            w = np.linalg.inv(res.covariance[np.ix_(idx, idx)])
            out.append((c, band, j, idx, t, np.linalg.solve(a.T @ w @ a, a.T @ w)))
    return out


def _fit_table(
    res: CalibrationResult, cfg: CalibrateConfig, x: Array, supplied: "CameraModel | TabulatedCameraModel"
) -> TabulatedCameraModel:
    """The calibrated thermal table: the supplied model at each end of the passes' temperature
    range plus the GLS line of the corrections through the bins, evaluated there (exact
    between the ends for corrections linear in temperature)."""
    t_lo, t_hi = float(res.pass_temperatures_c.min()), float(res.pass_temperatures_c.max())
    if t_hi - t_lo < 1e-6:
        raise DegenerateProblemError(f"all passes at {t_lo:.3f} C: no temperature range to tabulate")
    models = []
    for t_end in (t_lo, t_hi):
        m = supplied.at_temperature(t_end).copy()
        for c, band, j, idx, t, gls in _gls_groups(res, cfg):
            a, slope = gls @ x[idx]
            v = a + slope * (t_end - t.mean())
            m.add_correction(cfg.params[j], c, band, v)
        m.temperature_c = t_end
        models.append(m)
    return TabulatedCameraModel(models)


@dataclass
class SlopeEstimates:
    """Slopes (per deg C) of the estimated parameters across the temperature bins: ``names``
    (camera label, parameter), ``groups`` (camera, band or None, parameter index, bin
    temperatures) in the same order, ``slope (S,)``, covariance ``cov (S, S)``, and the linearity
    chi-square with its degrees of freedom."""

    names: list[tuple[str, str]]
    groups: list[tuple[int, int | None, int, Array]]
    slope: Array
    cov: Array
    chi2: float
    dof: int


def slope_estimates(res: CalibrationResult, cfg: CalibrateConfig) -> SlopeEstimates:
    """For each camera (and band) and parameter, the bins' corrections ``x_j`` fitted with
    ``a + s (T_j - T_mean)`` by generalised least squares with their joint covariance; the slope
    of the parameter is that ``s`` plus the supplied model's own slope across the bins. ``s`` is a
    linear function ``L x`` of the corrections, so the slopes' covariance is ``L C L^T``; the
    chi-square of the bins about their lines (dof: bins - 2 per line) tests linearity."""
    rows, names, offsets, groups = [], [], [], []
    chi2, dof = 0.0, 0
    for c, band, j, idx, t, gls in _gls_groups(res, cfg):
        p = cfg.params[j]
        row = np.zeros(res.values.size)
        row[idx] = gls[1]
        b = RED if band is None else band
        bins_here = [int(np.argmin(np.abs(res.bin_temperatures_c - tt))) for tt in t]
        sup = np.array([param_value(res.supplied_models[k], p, c, b) for k in bins_here])
        rows.append(row)
        offsets.append(float(gls[1] @ sup))
        names.append((CAMERAS[c] + (f"/{BANDS[band]}" if band is not None else ""), p))
        groups.append((c, band, j, t))
        if len(t) > 2:
            xa = res.values[idx]
            r = xa - np.stack([np.ones(len(t)), t - t.mean()], 1) @ (gls @ xa)
            chi2 += float(r @ np.linalg.solve(res.covariance[np.ix_(idx, idx)], r))
            dof += len(t) - 2
    lmat = np.array(rows)
    return SlopeEstimates(
        names, groups, lmat @ res.values + np.array(offsets), lmat @ res.covariance @ lmat.T, chi2, dof
    )


def thermal_slopes(res: CalibrationResult, cfg: CalibrateConfig) -> dict[str, Any]:
    """Slope (per deg C) of every estimated parameter across the temperature bins, with its sigma
    (:func:`slope_estimates`); ``linearity``: the chi-square test (only with >= 3 bins). Angles are
    also given in arcsec per deg C."""
    from misrgraph.model.constants import ARCSEC

    est = slope_estimates(res, cfg)
    sig_s = np.sqrt(np.diag(est.cov))
    out: dict[str, Any] = {"bins_c": [float(x) for x in res.bin_temperatures_c], "slopes": {}}
    if est.dof:
        from scipy import stats

        out["linearity"] = {"chi2": est.chi2, "dof": est.dof, "p_value": float(stats.chi2.sf(est.chi2, est.dof))}
    for i, (cam, p) in enumerate(est.names):
        e: dict[str, Any] = {"slope_per_c": float(est.slope[i]), "sigma_per_c": float(sig_s[i])}
        if p in ("delta", "beta", "epsilon"):
            e.update(slope_arcsec_per_c=float(est.slope[i] / ARCSEC), sigma_arcsec_per_c=float(sig_s[i] / ARCSEC))
        out["slopes"].setdefault(cam, {})[p] = e
    return out


def camera_keys(res: CalibrationResult, cfg: CalibrateConfig) -> list[int]:
    keys: dict[int, int] = {}
    for g in res.graphs:
        keys.update(g.camera_keys)
    return sorted(keys)
