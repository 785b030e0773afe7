"""Simultaneous bundle adjustment of one orbit pass (seed section 4.2).

Procedure (:func:`adjust_pass`; files and summary: :func:`misrgraph.runs.adjust.run_adjust`):

1. Build the graph of the pass (:func:`misrgraph.estimate.graph.build_pass_graph`) with the supplied
   (calibrated) camera model held by a tight prior, and solve with a robust (Cauchy) loss per
   observation, so blunders cannot drag the solution.
2. Reject every observation whose whitened residual norm exceeds ``reject_sigma`` (default 5)
   and report it with its normalised residual.
3. Re-solve with plain least squares without the rejected observations (robust weights would
   distort the covariance).
4. Iterated data snooping (:func:`snoop`, up to ``snooping_rounds``): Baarda's statistic of every
   image point from the redundancy numbers (:mod:`misrgraph.estimate.reliability`); per landmark
   the worst point above the critical value (alpha = 0.001) is rejected and the least-squares
   solve repeated, warm-started. This finds the 1-2 px mismatches (5-10 sigma) the robust
   screen's raw residual norm lets through: a residual is an error shrunk by its redundancy.
5. Marginal covariances of every knot, the ephemeris model, the camera corrections and every
   landmark, from the exact Hessian at the optimum (``covariance="hessian"``: ``J^T J`` plus the
   DEM heights' curvature; measured on 45-minute passes it is what makes the landmark NEES
   honest) or from ``J^T J`` (``"gauss_newton"``).

Nothing here sees the simulator's truth; scoring against it is :mod:`misrgraph.evaluate.score`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import gtsam
import numpy as np
from numpy.typing import NDArray

from factors import keys as K
from misrgraph.config import Config
from misrgraph.errors import DegenerateProblemError, InputError
from misrgraph.estimate.graph import GraphConfig, PassGraph, build_pass_graph, check_jitter
from misrgraph.estimate.problem import Marginals, NotFlat, flat_marginals, marginal_covariances, variance_factor
from misrgraph.estimate.reliability import Reliability, class_scale, critical_T, reliability
from misrgraph.estimate.solver import SolverParams, check_converged, solve
from misrgraph.estimate.tieheight import TIE_HEIGHT_MODES, inflate_along, shared_height_variance
from misrgraph.estimate.tieoffset import TIE_OFFSET_MODES, counted_covariance, offset_covariance, offset_response
from misrgraph.io.passes import KIND_GCP, KIND_TIE, OrbitPass
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import ARCSEC, BANDS, CAMERAS
from misrgraph.model.dem import DemTiles
from misrgraph.model.errormodels import AttitudeErrorModel, EphemerisErrorModel, unresolved_attitude
from misrgraph.model.gcp import GcpDatabase
from misrgraph.model.geolocation import PassGeometry
from misrgraph.model.noise import NoiseModel

__all__ = [
    "AdjustConfig",
    "AdjustResult",
    "adjust_pass",
    "observation_classes",
    "learned_sigma_summary",
    "dem_sigma_summary",
    "corrected_geometry",
    "find_blunders",
    "estimated_models",
    "supplied_camera_of",
    "drop_unsupported_landmarks",
    "snoop",
    "attitude_sigma_summary",
    "adjustment_marginals",
    "unresolved_attitude",
    "tie_point_terms",
    "tie_height_term",
    "tie_offset_term",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
RED = BANDS.index("red")


#: The camera corrections a pass adjustment estimates by default: the three angles, and the
#: field-angle distortion alpha_2, alpha_3, which a calibration of the angles alone leaves at
#: their pre-flight values: held by their prior, they carry that knowledge into every covariance
#: the pass reports (the PP's 1 sigma among them). f is left out: it scales both focal-plane
#: components alike, so it moves a red-band pixel only through the band's offset k (3-6 pixels),
#: nothing a pass can see or a product would feel.
CAMERA_PARAMS_ADJUST = ("delta", "beta", "epsilon", "alpha2", "alpha3")

#: The pass graph an adjustment builds by default: :class:`GraphConfig`'s defaults with the
#: camera corrections of :data:`CAMERA_PARAMS_ADJUST` and 1 arcsec of attitude jitter (its
#: unresolved part in the observations' weights and in every geolocation sigma)
ADJUST_GRAPH = GraphConfig(camera_params=CAMERA_PARAMS_ADJUST, attitude_jitter_arcsec=1.0)
_GRAPH_FIELDS = frozenset(f.name for f in dataclasses.fields(GraphConfig))


@dataclass(frozen=True)
class AdjustConfig(Config):
    """Adjustment settings: how the pass becomes a graph (``graph``) and how it is solved.

    ``from_dict`` also takes the graph's fields at the top level (``{"use_dem": false}`` means
    ``{"graph": {"use_dem": false}}``), as ``--config`` files and earlier states write them.
    """

    #: how the pass becomes a graph: knots and their prior, ephemeris segments and prior, camera
    #: corrections and their prior, the DEM factors, the attitude jitter
    #: (``graph.attitude_jitter_arcsec``: 1 sigma per angle, arcsec; its unresolved part is added
    #: to every geolocation sigma derived from the adjustment, and to the observations' weights
    #: unless ``jitter_in_weights`` is off)
    graph: GraphConfig = ADJUST_GRAPH
    #: a camera model written by ``misrgraph calibrate --out`` carries its corrections' joint
    #: covariance: the runs (adjust, update, products, campaign) then give it to the camera
    #: corrections as their prior, in place of ``graph.camera_prior_px`` per camera
    #: (:func:`misrgraph.io.camera.read_calibration_prior`); False: ``camera_prior_px`` always
    camera_prior_from_calibration: bool = True
    robust: str = "cauchy"
    robust_k: float = 3.0
    reject_sigma: float = 5.0
    #: rounds of iterated data snooping after the least-squares solve: each round rejects, per
    #: landmark, the observation with the largest Baarda statistic above the critical value
    #: (alpha = W_TEST_ALPHA) and re-solves; 0 switches it off
    snooping_rounds: int = 4
    #: drop a tie point whole when any of its observations is rejected (robust screen or data
    #: snooping) instead of only that observation: the tie point's other rays were selected by
    #: the same test, and its estimate from them is biased beyond its covariance (see
    #: docs/explanation/design.md, "Rejections and the landmarks' covariance"); GCPs keep their other rays
    drop_rejected_tie_points: bool = False
    #: rounds of variance-component estimation (Foerstner; before data snooping and after each of
    #: its rounds, as snooping's critical value is in sigmas): each observation class
    #: (the tie points seen by each camera, the GCP measurements) whose sigma0 departs from 1 by
    #: more than ``variance_component_tol`` and by more than ``variance_component_z`` of its
    #: standard errors (``sigma0 / sqrt(2 r)``; 3: a class of a pass whose stated sigma is right
    #: moves by chance 0.3 % of the time) has its sigmas rescaled by it, and the pass is
    #: re-solved, until no class moves; 0 keeps the stated sigmas. A class whose redundancy is
    #: below ``variance_component_min_redundancy`` keeps its stated sigma (the guard), and says so.
    #: The DEM heights are a class too, taken in a round where the image classes hold, their
    #: scale on the DEM's stated sigma (:func:`~misrgraph.estimate.reliability.class_scale`)
    variance_component_rounds: int = 3
    variance_component_tol: float = 0.05
    variance_component_z: float = 3.0
    variance_component_min_redundancy: float = 30.0
    #: the unresolved attitude jitter (``graph.attitude_jitter_arcsec``) is also noise in every
    #: image observation, through each observation's pointing sensitivity; False weights the
    #: observations by the matcher's sigma alone (the geolocation sigmas still carry it)
    jitter_in_weights: bool = True
    #: the marginals' information matrix: "hessian" (default: J^T J plus the DEM heights' exact
    #: curvature, the Laplace approximation at the optimum) or "gauss_newton" (J^T J, what
    #: gtsam.Marginals returns); problems outside the flat form always use J^T J
    covariance: str = "hessian"
    #: the height error a matched tie point's rays share (template relief, m, 1 sigma;
    #: :mod:`misrgraph.estimate.tieheight`), added to each tie landmark's covariance along An's
    #: ray: "auto" (default) estimates it from the pass's DEM residuals when the tie points were
    #: measured by image matching (``adjust_pass(..., ties_matched=True)``) and leaves it out for
    #: point measurements (the simulator's own observations); "estimate" always estimates it; a
    #: number (m) fixes it, 0 switches it off
    tie_height_sigma_m: float | str = "auto"
    #: the offset a matched tie point's conjugates share (px, 1 sigma per coordinate;
    #: :mod:`misrgraph.estimate.tieoffset`), its effect added to each tie landmark's covariance:
    #: "auto" (default) takes the matcher's measurement when the tie points were matched
    #: (``adjust_pass(..., tie_offset_px=...)``) and leaves it out otherwise; a number (px) fixes
    #: it, 0 switches it off
    tie_offset_sigma_px: float | str = "auto"
    max_iterations: int = 100
    backend: str = "auto"
    #: keep the result of a solve that did not converge (flagged in the summary and the result
    #: file) instead of failing with a ConvergenceError
    accept_unconverged: bool = False

    def __post_init__(self) -> None:
        for name in ("snooping_rounds", "variance_component_rounds"):
            v = getattr(self, name)
            if int(v) != v or v < 0:
                raise InputError(name, v, "an integer >= 0")
        if self.covariance not in ("hessian", "gauss_newton"):
            raise InputError("covariance", self.covariance, ("hessian", "gauss_newton"))
        if not isinstance(self.graph, GraphConfig):
            raise InputError("graph", self.graph, "a GraphConfig")
        check_jitter(self.graph.attitude_jitter_arcsec, self.graph.attitude_jitter_periods_s)
        if not self.variance_component_tol > 0:
            raise InputError("variance_component_tol", self.variance_component_tol, "a positive fraction")
        if not (np.isfinite(self.variance_component_z) and self.variance_component_z >= 0):
            raise InputError("variance_component_z", self.variance_component_z, "a number of standard errors >= 0")
        if not (np.isfinite(self.variance_component_min_redundancy) and self.variance_component_min_redundancy >= 2):
            raise InputError(
                "variance_component_min_redundancy", self.variance_component_min_redundancy, "a redundancy >= 2"
            )
        for name, modes, unit in (
            ("tie_height_sigma_m", TIE_HEIGHT_MODES, "m"),
            ("tie_offset_sigma_px", TIE_OFFSET_MODES, "px"),
        ):
            v = getattr(self, name)
            if not (
                v in modes
                if isinstance(v, str)
                else isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v >= 0
            ):
                raise InputError(name, v, f"one of {modes} or a finite 1 sigma >= 0 ({unit})")
        self.graph_config()  # the graph's fields (camera_params, priors, knots) checked now, not mid-run

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None = None, **overrides: Any) -> "AdjustConfig":
        """Build from a mapping; the graph's fields may stand at the top level (see the class)."""
        merged = {**dict(data or {}), **overrides}
        graph = merged.pop("graph", None)
        graph = graph.to_dict() if isinstance(graph, GraphConfig) else dict(graph or {})
        own = {f.name for f in dataclasses.fields(cls)}
        for key in [k for k in merged if k in _GRAPH_FIELDS and k not in own]:
            graph[key] = merged.pop(key)
        if graph:
            merged["graph"] = ADJUST_GRAPH.replace(**graph)
        return super().from_dict(merged)

    def with_noise(self, noise: NoiseModel) -> "AdjustConfig":
        """A copy whose graph takes every level of ``noise`` (:class:`~misrgraph.model.noise.NoiseModel`)."""
        return self.replace(graph=self.graph.replace(**noise.graph_fields()))

    def graph_config(self, **overrides: Any) -> GraphConfig:
        """The pass graph's configuration: ``graph``, without the jitter in the weights when
        ``jitter_in_weights`` is off, with ``overrides`` applied."""
        if not self.jitter_in_weights:
            overrides = {"attitude_jitter_arcsec": 0.0, **overrides}
        return self.graph.replace(**overrides) if overrides else self.graph


@dataclass
class AdjustResult:
    """Everything an adjustment produced."""

    pass_graph: PassGraph
    values: gtsam.Values
    marginals: Marginals
    attitude: AttitudeErrorModel
    ephemeris: EphemerisErrorModel
    camera: CameraModel
    rejected: NDArray[np.int64]
    rejected_norm: Array
    residuals_px: Array
    iterations: int
    final_cost: float
    history: list[float]
    seconds: float
    #: landmark rows dropped whole because most of their rays were rejected (see find_blunders)
    dropped_landmarks: NDArray[np.int64] = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    #: how the least-squares solve ended (:data:`misrgraph.estimate.solver.STATUSES`); the
    #: covariances are those of an optimum only when it is ``"converged"``
    status: str = "converged"
    #: a-posteriori variance factor and its chi-square test (:func:`misrgraph.estimate.problem.variance_factor`)
    variance_factor: dict = dataclasses.field(default_factory=dict)
    #: redundancy numbers, data snooping and variance components (:func:`reliability_summary`)
    reliability: dict = dataclasses.field(default_factory=dict)
    #: 1 sigma (rad, per angle) of the attitude error the knots cannot follow (white at the
    #: scale of the knot spacing); added to every geolocation uncertainty derived from the result
    unresolved_attitude_rad: float = 0.0
    #: the rejected observations (indices) that data snooping found, not the robust screen
    snooped: NDArray[np.int64] = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    #: the height error the tie points' rays share (``AdjustConfig.tie_height_sigma_m``): how it
    #: was set ("estimated", "fixed", "off") and its figures (:func:`tie_height_term`)
    tie_height: dict = dataclasses.field(default_factory=lambda: {"source": "off", "sigma_m": 0.0})
    #: what that term added to each tie landmark's marginal covariance (key -> (3, 3) m^2); the
    #: marginals already include it, scores of the graph's own information add it back
    landmark_extra_cov: dict = dataclasses.field(default_factory=dict)
    #: the offset the matched tie points' conjugates share (``AdjustConfig.tie_offset_sigma_px``):
    #: how it was set ("matched", "fixed", "off") and its figures (:func:`tie_offset_term`); its
    #: covariance is in ``landmark_extra_cov`` too
    tie_offset: dict = dataclasses.field(default_factory=lambda: {"source": "off", "sigma_px": 0.0})


def estimated_models(
    pg: PassGraph, values: gtsam.Values, camera: CameraModel
) -> tuple[AttitudeErrorModel, EphemerisErrorModel, CameraModel]:
    att = AttitudeErrorModel(
        [t.copy() for t in pg.attitude_model.knot_times],
        [np.array([values.atVector(k) for k in pg.knot_keys(a)]) for a in range(3)],
    )
    eph = EphemerisErrorModel(
        pg.ephemeris_model.boundaries.copy(), np.array([values.atVector(k) for k in pg.ephemeris_keys()])
    )
    cam = camera.corrected(pg.camera_corrections(values), pg.camera_params)
    cam.provenance = dict(camera.provenance, adjusted="camera corrections estimated by misrgraph adjust")
    return att, eph, cam


def corrected_geometry(
    orbit_pass: OrbitPass,
    att: AttitudeErrorModel,
    eph: EphemerisErrorModel,
    camera: CameraModel,
    attitude_extra: Callable[[Array], Array] | None = None,
) -> PassGeometry:
    """Pass geometry with the estimated error models removed (true = measured - error);
    ``attitude_extra(t)`` (rad, ``(N, 3)``) is a further attitude error removed with them."""
    if attitude_extra is None:
        delta = lambda t: -att.evaluate(t)  # noqa: E731
    else:
        delta = lambda t: -(att.evaluate(t) + attitude_extra(t))  # noqa: E731
    return PassGeometry(
        orbit_pass.ephemeris,
        orbit_pass.attitude,
        camera,
        t0=orbit_pass.t0,
        attitude_delta=delta,
        position_delta=lambda t: -eph.evaluate(t),
    )


def adjust_pass(
    orbit_pass: OrbitPass,
    camera: CameraModel,
    dem: DemTiles | None,
    gcps: GcpDatabase | None,
    cfg: AdjustConfig = AdjustConfig(),
    progress: Callable[[str], None] | None = None,
    ties_matched: bool = False,
    tie_offset_px: float | None = None,
    tie_offset_own_ratio: dict[str, float] | None = None,
    camera_prior: tuple[list[str], Array] | None = None,
) -> AdjustResult:
    """Robust solve, blunder rejection, least-squares re-solve and marginals (module docstring).
    ``ties_matched``: the tie points were measured by image matching (``misrgraph match``), so
    ``tie_height_sigma_m="auto"`` estimates their shared height error; ``tie_offset_px``: the
    offset their conjugates share as the matcher measured it (px, 1 sigma; None: not measured),
    which ``tie_offset_sigma_px="auto"`` uses, with ``tie_offset_own_ratio`` (camera name ->
    ``rho``, :mod:`misrgraph.estimate.tieoffset`; None or a missing camera: 1). ``camera_prior``:
    the camera model's calibration covariance (:func:`misrgraph.io.camera.read_calibration_prior`),
    the joint prior of the camera corrections of the cameras it covers (None: ``camera_prior_px``
    each; :func:`misrgraph.estimate.graph.build_pass_graph`)."""
    t0 = time.perf_counter()
    params = SolverParams(max_iterations=cfg.max_iterations)
    obs = orbit_pass.observations
    if progress and cfg.robust != "none":
        progress("robust solve")
    rejected, norm = find_blunders(orbit_pass, camera, dem, gcps, cfg, camera_prior)
    blunder_mask = rejected
    rejected, dropped = drop_unsupported_landmarks(orbit_pass, rejected, cfg.drop_rejected_tie_points)
    if progress:
        progress("least-squares solve")
    pg = build_pass_graph(
        orbit_pass, camera, dem, gcps, cfg.graph_config(), exclude_observations=rejected, camera_prior=camera_prior
    )
    res = solve(pg.problem, params.replace(backend=cfg.backend))
    check_converged(res, "the least-squares solve", cfg.accept_unconverged)

    dem_scale = 1.0  # the variance components' factor on the configured DEM scale

    def resolve(op: OrbitPass, excluded: NDArray[np.bool_], previous: gtsam.Values, after: str):
        """Rebuild (with the DEM scale the variance components reached) and re-solve, warm-started
        from the previous optimum."""
        gcfg = cfg.graph_config(dem_sigma_scale=cfg.graph.dem_sigma_scale * dem_scale)
        g = build_pass_graph(op, camera, dem, gcps, gcfg, exclude_observations=excluded, camera_prior=camera_prior)
        g.problem.warm_start(previous)
        r = solve(g.problem, params.replace(backend=cfg.backend))
        check_converged(r, f"the least-squares solve after {after}", cfg.accept_unconverged)
        return g, r

    # the reliability at the current optimum serves snooping, variance components and the summary.
    # Variance components come first and after each snooping round: data snooping's critical value
    # is in sigmas, so a class whose stated sigma is too small would lose its good observations
    at = _reliability_at(orbit_pass, pg, res.values)
    snooped = np.zeros(len(obs), bool)
    obs_class = observation_classes(orbit_pass)
    vc_scale: dict[str, float] = {}
    stated = obs.sigma_px.copy()
    rounds = snoop_rounds = 0
    while True:
        if rounds < cfg.variance_component_rounds:
            comps = _variance_components(at, obs_class)
            moved = _departed(comps, cfg)
            # the DEM heights once the image classes hold: their residuals are the landmarks'
            # heights against the DEM, which over-weighted image observations pull away from it
            dem_vc = _dem_component(at, pg) if not moved else None
            if dem_vc is not None:
                moved = _departed({"DEM": dem_vc}, cfg)
            if moved:
                rounds += 1
                if "DEM" in moved:  # class_scale: the scale on the DEM's stated sigma
                    assert dem_vc is not None
                    k0 = cfg.graph.dem_sigma_scale
                    dem_scale = class_scale(k0 * dem_scale, moved.pop("DEM"), dem_vc["stated_share"])[0] / k0
                for k, v in moved.items():
                    vc_scale[k] = vc_scale.get(k, 1.0) * v
                if progress:
                    progress(
                        f"variance components: round {rounds}, sigma scale "
                        + ", ".join(f"{k} {v:.3f}" for k, v in sorted({**vc_scale, "DEM": dem_scale}.items()))
                    )
                orbit_pass = _with_sigma_scale(orbit_pass, stated, obs_class, vc_scale)
                pg, res = resolve(orbit_pass, rejected, res.values, "variance-component estimation")
                at = _reliability_at(orbit_pass, pg, res.values)
                continue
        if snoop_rounds >= cfg.snooping_rounds:
            break
        worst = snoop(orbit_pass, pg, res.values, at)
        if worst.size == 0:
            break
        snoop_rounds += 1
        if progress:
            progress(f"data snooping: round {snoop_rounds}, {worst.size} observations rejected")
        snooped[worst] = True
        rejected, more = drop_unsupported_landmarks(orbit_pass, rejected | snooped, cfg.drop_rejected_tie_points)
        dropped = np.union1d(dropped, more)
        pg, res = resolve(orbit_pass, rejected, res.values, "data snooping")
        at = _reliability_at(orbit_pass, pg, res.values)
    blunder_mask = blunder_mask | snooped
    if progress:
        progress("marginal covariances")
    marg, cov_used = adjustment_marginals(pg, res.values, cfg.covariance)
    tie_height, offset, extra = tie_point_terms(
        orbit_pass, camera, pg, res.values, marg, cfg, ties_matched, tie_offset_px, tie_offset_own_ratio, at
    )
    if progress and tie_height["source"] == "estimated":
        progress(f"tie points' shared height error: {tie_height['sigma_m']:.1f} m")
    r, _ = pg.collinearity.residuals(res.values)
    resid = np.full((len(obs), 2), np.nan)
    resid[pg.obs_index[pg.collinearity.order]] = r
    att, eph, cam = estimated_models(pg, res.values, camera)
    rej = np.flatnonzero(blunder_mask)
    rel = reliability_summary(orbit_pass, pg, res.values, at)
    rel["observation_sigma"] = learned_sigma_summary(
        _variance_components(at, obs_class), vc_scale, cfg, rounds, stated, obs_class
    )
    rel["sigma_scale_applied"] = {k: vc_scale.get(k, 1.0) for k in rel["observation_sigma"]["classes"]}
    rel["dem_sigma"] = dem_sigma_summary(_dem_component(at, pg), dem_scale, cfg)
    rel["covariance"] = cov_used
    return AdjustResult(
        pass_graph=pg,
        values=res.values,
        marginals=marg,
        attitude=att,
        ephemeris=eph,
        camera=cam,
        rejected=rej,
        rejected_norm=norm[rej],
        residuals_px=resid,
        iterations=res.iterations,
        final_cost=res.final_error,
        history=res.history,
        seconds=time.perf_counter() - t0,
        dropped_landmarks=dropped,
        status=res.status,
        variance_factor=variance_factor(pg.problem, res.final_error),
        reliability=rel,
        unresolved_attitude_rad=cfg.graph.unresolved_attitude_rad(pg.attitude_model.knot_times),
        snooped=np.flatnonzero(snooped),
        tie_height=tie_height,
        landmark_extra_cov=extra,
        tie_offset=offset,
    )


def tie_point_terms(
    orbit_pass: OrbitPass,
    camera: CameraModel,
    pg: PassGraph,
    values: gtsam.Values,
    marginals: Marginals,
    cfg: AdjustConfig,
    ties_matched: bool,
    tie_offset_px: float | None = None,
    tie_offset_own_ratio: dict[str, float] | None = None,
    at: "_ReliabilityAt | None" = None,
) -> tuple[dict[str, Any], dict[str, Any], dict[int, Array]]:
    """The tie points' shared height error (:func:`tie_height_term`) and their conjugates' shared
    offset (:func:`tie_offset_term`), each set by ``cfg``, added to the tie landmarks' blocks of
    ``marginals`` in place (m^2). Returns the two terms' summaries and, per tie landmark key, the
    covariance added. ``ties_matched``, ``tie_offset_px``, ``tie_offset_own_ratio``: as
    :func:`adjust_pass`. ``at``: the reliability at ``values`` when already computed; otherwise it
    is computed here if the height term is to be estimated. Used by ``adjust`` and by ``update``
    (on the pass's standalone graph at the joint estimate)."""
    if at is None and _tie_height_mode(cfg.tie_height_sigma_m, ties_matched) == "estimate":
        at = _reliability_at(orbit_pass, pg, values)
    tie_height, extra = tie_height_term(orbit_pass, camera, pg, values, at, cfg.tie_height_sigma_m, ties_matched)
    offset, extra_o = tie_offset_term(
        orbit_pass, pg, values, cfg.tie_offset_sigma_px, tie_offset_px if ties_matched else None, tie_offset_own_ratio
    )
    extra = {k: extra.get(k, 0) + extra_o.get(k, 0) for k in set(extra) | set(extra_o)}
    for k, c in extra.items():
        marginals.cov[k] = marginals.cov[k] + c
    return tie_height, offset, extra


def _tie_height_mode(setting: float | str, ties_matched: bool) -> float | str:
    """``AdjustConfig.tie_height_sigma_m`` resolved: "auto" estimates for matched tie points and is 0 otherwise."""
    return ("estimate" if ties_matched else 0.0) if setting == "auto" else setting


def tie_height_term(
    orbit_pass: OrbitPass,
    camera: CameraModel,
    pg: PassGraph,
    values: gtsam.Values,
    at: "_ReliabilityAt | None",
    setting: float | str,
    ties_matched: bool,
) -> tuple[dict[str, Any], dict[int, Array]]:
    """The shared height error of the tie points (:mod:`misrgraph.estimate.tieheight`): its summary
    and, per tie landmark key, ``s^2 u u^T`` (m^2) with ``u`` along An's ray (the local vertical
    for a tie point An does not see). ``setting``: ``AdjustConfig.tie_height_sigma_m``.

    Estimated from the DEM factors' residuals and redundancy numbers at the optimum (``at``); a
    problem outside the flat form has none, and the term is then left out and says so."""
    mode = _tie_height_mode(setting, ties_matched)
    if mode == "estimate":
        if at is None:
            return {
                "source": "off",
                "sigma_m": 0.0,
                "reason": "no redundancy numbers (problem outside the flat form)",
            }, {}
        flat = pg.problem.flat()
        fam = at[0].families["dem"]
        if flat.dem is None or fam.stop <= fam.start:
            return {"source": "off", "sigma_m": 0.0, "reason": "no DEM factors"}, {}
        e, q = at[0].e[fam], at[0].r[fam]
        est = shared_height_variance(e * flat.dem.sigma_m, flat.dem.sigma_m, np.clip(q, 1e-9, 1.0))
        s2 = est.variance_m2
        info: dict[str, Any] = {
            "source": "estimated",
            "sigma_m": est.sigma_m,
            "variance_m2": s2,
            "unclipped_variance_m2": est.unclipped_m2,
            "standard_error_m2": est.standard_error_m2,
            "dem_factors": est.n,
        }
    else:
        s2 = float(mode) ** 2
        info = {"source": "fixed" if s2 > 0 else "off", "sigma_m": float(mode)}
    if s2 <= 0:
        return info, {}
    obs = orbit_pass.observations
    tie = orbit_pass.landmarks.kind[pg.landmark_rows] == KIND_TIE
    keys, rows = pg.landmark_keys[tie], pg.landmark_rows[tie]
    x = np.array([values.atVector(int(k)) for k in keys]).reshape(-1, 3)
    u = x / np.linalg.norm(x, axis=1, keepdims=True)  # geocentric up: the fallback, within 0.2 deg of the normal
    an = np.flatnonzero(obs.camera == CAMERAS.index("An"))
    seen, first = np.unique(obs.landmark[an], return_index=True)  # each landmark's first An observation
    has = np.isin(rows, seen)
    if has.any():
        idx = an[first[np.searchsorted(seen, rows[has])]]
        _, d = orbit_pass.geometry(camera).pixel_rays(
            obs.camera[idx], obs.band[idx], obs.line[idx], obs.sample[idx], exposure=obs.exposure_index[idx]
        )
        u[has] = -d
    cov = inflate_along(np.zeros((keys.size, 3, 3)), u, s2)
    info["tie_points"] = int(keys.size)
    return info, {int(k): c for k, c in zip(keys, cov)}


def tie_offset_term(
    orbit_pass: OrbitPass,
    pg: PassGraph,
    values: gtsam.Values,
    setting: float | str,
    measured_px: float | None,
    own_ratio: dict[str, float] | None = None,
) -> tuple[dict[str, Any], dict[int, Array]]:
    """The offset a matched tie point's conjugates share (:mod:`misrgraph.estimate.tieoffset`): its
    summary and, per tie landmark key, ``s_o^2 R R^T - sum_c a_c R_c R_c^T`` (m^2). ``setting``:
    ``AdjustConfig.tie_offset_sigma_px``; ``measured_px``: the matcher's ``s_o`` (None: none);
    ``own_ratio``: camera name -> ``rho_c`` (the share of each conjugate's sigma that is its own;
    None or a missing camera: 1, nothing counted). The response needs the flat form; outside it
    the term is left out and says so."""
    if setting == "auto":
        if measured_px is None:
            return {"source": "off", "sigma_px": 0.0}, {}
        s_o, info = float(measured_px), {"source": "matched", "sigma_px": float(measured_px)}
    else:
        s_o = float(setting)
        info = {"source": "fixed" if s_o > 0 else "off", "sigma_px": s_o}
    if s_o <= 0:
        return info, {}
    try:
        flat = pg.problem.flat()
    except NotFlat as exc:
        return {"source": "off", "sigma_px": 0.0, "reason": f"problem outside the flat form ({exc})"}, {}
    x = flat.from_values(values)
    jac, sigma, lm = flat.landmark_jacobians(x)
    obs = orbit_pass.observations
    rows = pg.obs_index[pg.collinearity.order]
    if rows.size != lm.size:
        raise DegenerateProblemError("tie offset: the collinearity rows do not match the pass's observations")
    tie_lm = np.zeros(len(pg.problem.eliminate_first), bool)
    index = {int(k): i for i, k in enumerate(pg.problem.eliminate_first)}
    tie = orbit_pass.landmarks.kind[pg.landmark_rows] == KIND_TIE
    keys = [int(k) for k in pg.landmark_keys[tie]]
    tie_lm[[index[k] for k in keys]] = True
    shared = (obs.camera[rows] != CAMERAS.index("An")) & tie_lm[lm]
    blk = flat.normal_equations(x)[0]
    rho = np.array([(own_ratio or {}).get(c, 1.0) for c in CAMERAS])[obs.camera[rows]]
    counted = np.where(shared, np.minimum(obs.sigma_px[rows] ** 2 * np.clip(1.0 - rho**2, 0.0, None), s_o**2), 0.0)
    cov = offset_covariance(offset_response(blk, jac, sigma, lm, shared), s_o) - counted_covariance(
        blk, jac, sigma, lm, counted
    )
    info["tie_points"] = len(keys)
    if own_ratio:
        info["own_scale_ratio"] = dict(own_ratio)
    return info, {k: cov[index[k]] for k in keys}


def adjustment_marginals(pg: PassGraph, values: gtsam.Values, covariance: str = "hessian") -> tuple[Marginals, str]:
    """Marginal covariances of an adjusted pass (see ``AdjustConfig.covariance``) and which
    information matrix gave them: ``"hessian"``, or ``"gauss_newton"`` (asked for, outside the flat
    form, or where the curvature left the reduced system indefinite)."""
    if covariance == "hessian":
        try:
            flat = pg.problem.flat()
            return flat_marginals(flat, flat.from_values(values), second_order=True), "hessian"
        except NotFlat:
            pass
        except DegenerateProblemError as exc:  # the curvature made the reduced system indefinite
            log.warning("Hessian marginals not positive definite (%s); using J^T J", exc)
    return marginal_covariances(pg.problem, values), "gauss_newton"


def observation_classes(orbit_pass: OrbitPass) -> NDArray[np.str_]:
    """Each observation's variance-component class: ``"tie-point <camera>"`` or ``"GCP"``."""
    obs = orbit_pass.observations
    kind = orbit_pass.landmarks.kind[obs.landmark]
    tie = np.array([f"tie-point {c}" for c in CAMERAS])[np.asarray(obs.camera, int)]
    return np.where(kind == KIND_GCP, "GCP", np.where(kind == KIND_TIE, tie, "other"))


def _variance_components(at: "_ReliabilityAt | None", obs_class: NDArray[np.str_]) -> dict[str, dict[str, float]]:
    """Per observation class (:func:`observation_classes`, observations in the solve): ``sigma0``,
    its standard error ``sigma0_sd = sigma0 / sqrt(2 r)``, the redundancy ``r`` and the rows, from
    :func:`_reliability_at`."""
    if at is None:
        return {}
    rel, obs_of_row, _ = at
    cls_row = np.repeat(obs_class[obs_of_row], 2)
    coll = np.arange(rel.e.size)[rel.families["collinearity"]]
    out = {}
    for name in sorted(set(cls_row.tolist()) - {"other"}):
        rows = np.zeros(rel.e.size, bool)
        rows[coll[cls_row == name]] = True
        vc = rel.variance_component(rows)
        r = vc["redundancy"]
        vc["sigma0_sd"] = float(vc["sigma0"] / np.sqrt(2.0 * r)) if r > 0 else float("inf")
        out[name] = vc
    return out


def _departed(comps: dict[str, dict[str, float]], cfg: AdjustConfig) -> dict[str, float]:
    """The classes whose ``sigma0`` departs from 1 by more than the tolerance and by more than
    ``variance_component_z`` of its standard error, with enough redundancy: class -> sigma0."""
    return {
        k: v["sigma0"]
        for k, v in comps.items()
        if v["redundancy"] >= cfg.variance_component_min_redundancy
        and abs(v["sigma0"] - 1.0) > max(cfg.variance_component_tol, cfg.variance_component_z * v["sigma0_sd"])
    }


def _dem_component(at: "_ReliabilityAt | None", pg: PassGraph) -> dict[str, float] | None:
    """The DEM factors' variance component (``sigma0``, ``sigma0_sd``, ``redundancy``, ``rows``) and
    ``stated_share``, the part of their variance that is the DEM's stated sigma (by redundancy;
    the rest is the surface fit's residual, which the DEM scale does not touch: what a misstated
    DEM sigma moves). None without DEM factors or outside the flat form."""
    if at is None:
        return None
    rel = at[0]
    fam = rel.families["dem"]
    flat_dem = pg.problem.flat().dem
    if fam.stop <= fam.start or flat_dem is None:
        return None
    vc = rel.variance_component(fam)
    r = rel.r[fam]
    vc["sigma0_sd"] = float(vc["sigma0"] / np.sqrt(2.0 * vc["redundancy"])) if vc["redundancy"] > 0 else float("inf")
    share = (flat_dem.stated_m / flat_dem.sigma_m) ** 2 if flat_dem.stated_m is not None else np.ones(r.size)
    vc["stated_share"] = float(np.sum(r * share) / np.sum(r)) if np.sum(r) > 0 else float(np.mean(share))
    return vc


def _vc_status(cfg: AdjustConfig, redundancy: float, scale: float) -> str:
    """What the variance components did to a class: ``"off"`` (no rounds), ``"guard"`` (too little
    redundancy to learn from; the stated sigma is kept), ``"learned"`` (rescaled) or ``"stated"``."""
    if not cfg.variance_component_rounds:
        return "off"
    if redundancy < cfg.variance_component_min_redundancy:
        return "guard"
    return "learned" if scale != 1.0 else "stated"


def learned_sigma_summary(
    comps: dict[str, dict[str, float]],
    scale: dict[str, float],
    cfg: AdjustConfig,
    rounds: int,
    stated: Array,
    obs_class: NDArray[np.str_],
) -> dict[str, Any]:
    """What the variance components did: per class the scale applied to the stated sigmas, the
    learned sigma (px, median over the class: stated x scale) with its 1 sigma, the final sigma0,
    the redundancy, and ``status``: ``"learned"`` (rescaled), ``"stated"`` (sigma0 within the
    tolerance) or ``"guard"`` (too little redundancy to learn from; the stated sigma is kept)."""
    classes = {}
    for name, v in comps.items():
        k = scale.get(name, 1.0)
        med = float(np.median(stated[obs_class == name])) if np.any(obs_class == name) else float("nan")
        classes[name] = {
            "status": _vc_status(cfg, v["redundancy"], k),
            "scale": k,
            "scale_sd": k * v["sigma0_sd"],
            "sigma_px": med * k,
            "stated_sigma_px": med,
            "sigma0": v["sigma0"],
            "redundancy": v["redundancy"],
        }
    return {
        "rounds": rounds,
        "min_redundancy": cfg.variance_component_min_redundancy,
        "tolerance": cfg.variance_component_tol,
        "classes": classes,
    }


def dem_sigma_summary(comp: dict[str, float] | None, scale: float, cfg: AdjustConfig) -> dict[str, Any]:
    """What the variance components did to the DEM factors: ``scale`` the factor they put on the
    configured DEM scale (on the DEM's stated sigma), ``sigma_scale`` the DEM scale used in the
    end, the final ``sigma0`` with its redundancy and the stated sigma's share of the factors'
    variance, and ``status`` as for the image classes (:func:`learned_sigma_summary`); ``{"status":
    "none"}`` without DEM factors."""
    if comp is None:
        return {"status": "none"}
    return {
        "status": _vc_status(cfg, comp["redundancy"], scale),
        "scale": float(scale),
        "sigma_scale": float(cfg.graph.dem_sigma_scale * scale),
        "sigma0": comp["sigma0"],
        "redundancy": comp["redundancy"],
        "stated_share": comp["stated_share"],
    }


def _with_sigma_scale(
    orbit_pass: OrbitPass, stated: Array, obs_class: NDArray[np.str_], scale: dict[str, float]
) -> OrbitPass:
    """The pass with the ``stated`` observation sigmas multiplied by their class's ``scale`` (1 for
    a class not in it)."""
    obs = orbit_pass.observations
    factor = np.ones(len(obs))
    for name, k in scale.items():
        factor[obs_class == name] = k
    sig = stated * factor
    return dataclasses.replace(orbit_pass, observations=dataclasses.replace(obs, sigma_px=sig))


def attitude_sigma_summary(res: AdjustResult, prior_arcsec: tuple, step_s: float = 5.0) -> dict[str, Any]:
    """Per angle: the largest a-posteriori attitude 1 sigma over the pass (sampled every
    ``step_s`` s), its time and its ratio to the a-priori sigma (arcsec). With the process prior
    the ratio stays at or below 1 (up to the Hermite interpolant's 0.01 % at 60 s knots, 0.3 % at 120 s)."""
    from misrgraph.model.constants import ANGLES

    pg = res.pass_graph
    t0 = min(kt[0] for kt in pg.attitude_model.knot_times)
    out: dict[str, Any] = {}
    for a, name in enumerate(ANGLES):
        kt = pg.attitude_model.knot_times[a]
        t = np.arange(kt[0], kt[-1] + step_s / 2, step_s)  # the spline's own span (no extrapolation)
        sig = pg.attitude_sigma(res.marginals, a, t) / ARCSEC
        i = int(np.argmax(sig))
        out[name] = {
            "max_sigma_arcsec": float(sig[i]),
            "at_s": float(t[i] - t0),
            "prior_sigma_arcsec": float(prior_arcsec[a]),
            "max_over_prior": float(sig[i] / prior_arcsec[a]),
            "unresolved_sigma_arcsec": float(res.unresolved_attitude_rad / ARCSEC),
        }
    return out


#: :func:`reliability` at a solution, the observation index and the landmark kind per image point
_ReliabilityAt = tuple[Reliability, NDArray[np.int64], NDArray[np.int64]]


def _reliability_at(orbit_pass: OrbitPass, pg: PassGraph, values: gtsam.Values) -> _ReliabilityAt | None:
    """:func:`reliability` at ``values`` with, per image point of it, the observation index and
    the landmark kind; None outside the flat form."""
    try:
        flat = pg.problem.flat()
    except NotFlat:
        return None
    rel = reliability(flat, flat.from_values(values))
    obs_of_row = pg.obs_index[pg.collinearity.order]
    return rel, obs_of_row, orbit_pass.landmarks.kind[orbit_pass.observations.landmark[obs_of_row]]


def snoop(
    orbit_pass: OrbitPass, pg: PassGraph, values: gtsam.Values, at: _ReliabilityAt | None = None
) -> NDArray[np.int64]:
    """One round of iterated data snooping (Baarda): the observation indices whose statistic
    ``T`` exceeds the critical value at :data:`W_TEST_ALPHA`, at most one per landmark (its
    largest: a mismatch also inflates its landmark's other residuals). ``at``: the reliability at
    ``values`` when already computed (:func:`_reliability_at`)."""
    at = at if at is not None else _reliability_at(orbit_pass, pg, values)
    if at is None:
        return np.zeros(0, np.int64)
    rel, obs_of_row, _ = at
    bad = np.flatnonzero(rel.T > critical_T())
    if bad.size == 0:
        return np.zeros(0, np.int64)
    lm = orbit_pass.observations.landmark[obs_of_row[bad]]
    order = np.lexsort((-rel.T[bad], lm))
    first = np.r_[True, lm[order][1:] != lm[order][:-1]]
    return np.sort(obs_of_row[bad[order[first]]]).astype(np.int64)


def _gcp_position_rows(pg: PassGraph) -> NDArray[np.bool_]:
    """Which rows of the flat problem's prior family are the GCP positions' priors (a GCP's own,
    its scene's offset, or the two together): the class whose variance component says how the
    GCP catalogue's stated sigma holds (``gcp_sigma_scale``)."""
    flat = pg.problem.flat()
    gcp_chr = {ord(K.GCP), ord(K.GCP_SCENE)}
    mask = [np.full(p.b.size, any(gtsam.Symbol(k).chr() in gcp_chr for k in p.keys), bool) for p in flat.priors]
    return np.concatenate(mask) if mask else np.zeros(0, bool)


def reliability_summary(
    orbit_pass: OrbitPass, pg: PassGraph, values: gtsam.Values, at: _ReliabilityAt | None = None
) -> dict[str, Any]:
    """Redundancy, Baarda's data snooping and variance components per observation class (tie
    points, GCPs), DEM and priors at the least-squares optimum (:mod:`misrgraph.estimate.reliability`);
    ``flagged``: the observations whose statistic exceeds the critical value, largest first.
    ``at``: the reliability at ``values`` when already computed."""
    at = at if at is not None else _reliability_at(orbit_pass, pg, values)
    if at is None:
        return {}
    rel, obs_of_row, kind = at
    out = rel.summary(kind, {KIND_TIE: "tie-point", KIND_GCP: "GCP"})
    dem = _dem_component(at, pg)
    if dem is not None:
        out["variance_components"]["dem"]["stated_share"] = dem["stated_share"]
    gcp_rows = _gcp_position_rows(pg)
    if gcp_rows.any():
        prior_rows = np.zeros(rel.e.size, bool)
        prior_rows[rel.families["priors"]] = gcp_rows
        out["variance_components"]["GCP positions"] = rel.variance_component(prior_rows)
    crit = out["data_snooping"]["critical_T"]
    bad = np.flatnonzero(rel.T > crit)
    bad = bad[np.argsort(-rel.T[bad])]
    out["data_snooping"]["flagged_observations"] = [
        {
            "index": int(obs_of_row[i]),
            "camera": CAMERAS[int(orbit_pass.observations.camera[obs_of_row[i]])],
            "T": float(rel.T[i]),
            "redundancy": float(np.trace(rel.R_obs[i]) / 2),
        }
        for i in bad[:20]
    ]
    return out


#: the largest robust scale the blunder screen gives a class of observations whose residuals say
#: its file understates its sigma (the screen's threshold is ``reject_sigma`` times it)
ROBUST_SCALE_MAX = 3.0


def find_blunders(
    orbit_pass: OrbitPass,
    camera: CameraModel,
    dem: DemTiles | None,
    gcps: GcpDatabase | None,
    cfg: AdjustConfig,
    camera_prior: tuple[list[str], Array] | None = None,
) -> tuple[NDArray[np.bool_], Array]:
    """Robust (per-observation) solve of one pass; observations whose whitened residual norm
    exceeds ``reject_sigma`` are blunders. Returns (rejected mask, normalised residual) per
    observation. ``camera_prior``: as :func:`adjust_pass`."""
    obs = orbit_pass.observations
    rejected = np.zeros(len(obs), bool)
    norm = np.zeros(len(obs))
    if cfg.robust == "none":
        return rejected, norm
    pg_r = build_pass_graph(
        orbit_pass,
        camera,
        dem,
        gcps,
        cfg.graph_config(group_by="observation", robust=cfg.robust, robust_k=cfg.robust_k),
        camera_prior=camera_prior,
    )
    res_r = solve(pg_r.problem, SolverParams(max_iterations=cfg.max_iterations))
    check_converged(res_r, "the robust solve (blunder screening)", cfg.accept_unconverged)
    r, _ = pg_r.collinearity.residuals(res_r.values)
    whit = np.linalg.norm(r / pg_r.collinearity.sigma_px, axis=1)
    idx = pg_r.obs_index[pg_r.collinearity.order]
    # each class's robust scale (the median of a 2-D unit normal's norm is sqrt(2 ln 2)): a file
    # that understates its sigma must not have its good observations screened out as blunders,
    # so the threshold grows with a scale above 1, up to ROBUST_SCALE_MAX (a class further off is
    # a class of blunders: GCPs shifted whole, say); one below 1 keeps it (the screen is for blunders)
    cls = observation_classes(orbit_pass)[idx]
    scale = np.ones(idx.size)
    for name in np.unique(cls):
        m = cls == name
        if m.sum() >= 30:
            s_c = float(np.median(whit[m])) / np.sqrt(2.0 * np.log(2.0))
            scale[m] = min(max(1.0, s_c), ROBUST_SCALE_MAX)
    norm[idx] = whit / scale
    rejected[idx] = whit > cfg.reject_sigma * scale
    log.info(
        "robust solve: %d iterations; %d observations rejected (> %.1f sigma, robust scale up to %.2f)",
        res_r.iterations,
        int(rejected.sum()),
        cfg.reject_sigma,
        float(scale.max()) if scale.size else 1.0,
    )
    return rejected, norm


def drop_unsupported_landmarks(
    orbit_pass: OrbitPass, rejected: NDArray[np.bool_], any_rejection: bool = False
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Exclude every observation of a tie point that the blunder test left unsupported.

    A landmark is dropped when more than half of its observations were rejected, or when fewer
    than two cameras still see it. Then the landmark, not its rays, is what the robust solve got
    wrong: typically a wrong terrain intersection, where the good rays look like blunders. One
    ray plus the DEM would give it a confident position that may be kilometres off. GCPs keep
    their ground prior and are never dropped; check points are not in the graph. ``any_rejection``:
    drop every tie point with a rejected observation (``AdjustConfig.drop_rejected_tie_points``).
    Returns the new exclusion mask and the dropped rows.
    """
    obs = orbit_pass.observations
    kinds = orbit_pass.landmarks.kind
    n_lm = len(kinds)
    total = np.bincount(obs.landmark, minlength=n_lm)
    n_rej = np.bincount(obs.landmark[rejected], minlength=n_lm)
    keep = ~rejected
    pairs = np.unique(np.stack([obs.landmark[keep], obs.camera[keep]], 1), axis=0)
    cams_left = np.bincount(pairs[:, 0], minlength=n_lm) if pairs.size else np.zeros(n_lm, np.int64)
    unsupported = (n_rej > 0) if any_rejection else ((2 * n_rej > total) | (cams_left < 2))
    drop = (kinds == KIND_TIE) & (total > 0) & unsupported
    rows = np.flatnonzero(drop)
    if rows.size:
        log.info(
            "dropped %d tie points %s (rows %s)",
            rows.size,
            "with a rejected ray" if any_rejection else "whose rays were mostly rejected",
            rows[:20].tolist(),
        )
    return rejected | drop[obs.landmark], rows.astype(np.int64)


def supplied_camera_of(res: AdjustResult) -> CameraModel:
    """The camera model before this adjustment's corrections (corrections are stored in values)."""
    pg = res.pass_graph
    return res.camera.corrected(pg.camera_corrections(res.values), pg.camera_params, sign=-1.0)
