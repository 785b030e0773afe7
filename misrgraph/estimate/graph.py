"""Graph builder: one orbit pass (+ camera model, DEM, GCPs) -> variables, factors, initial values.

Variables (keys in :mod:`factors.keys`): a landmark per tie point and GCP, attitude knots per
angle (spacing per angle, knots removed by eqs. 28-29), one ephemeris-error ``Vector6`` per
segment, and optionally camera corrections. Factors: collinearity (one ``CustomFactor`` per
landmark holding all its views, or per observation), DEM height for tie points, GCP priors
(eq. 32), and priors on knots, ephemeris and camera from the navigation / calibration accuracy.
Check points (kind 2) are never put in the graph.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors import keys as K
from factors.collinearity import (
    CAMERA_PARAMS,
    CollinearityBatch,
    CollinearityConstants,
    camera_param_scale,
    collinearity_residual,
)
from factors.dem_height import DemBatch
from factors.geometry import enu_covariance
from factors.priors import (
    gcp_prior,
    gcp_scene_prior,
    joint_prior_factor,
    linear_factor,
    process_covariance,
    process_prior_factors,
    scene_offset_prior,
    vector_prior,
)
from misrgraph.config import Config
from misrgraph.errors import DegenerateProblemError, InputError
from misrgraph.estimate.problem import Problem
from misrgraph.io.passes import KIND_CHECK, KIND_GCP, KIND_TIE, OrbitPass
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import ARCSEC, BANDS, CAMERAS
from misrgraph.model.dem import DemTiles, Geoid, fit_local_surface
from misrgraph.model.errormodels import (
    ATTITUDE_RATE_FACTOR,
    AttitudeErrorModel,
    EphemerisErrorModel,
    ephemeris_prior_covariance,
    interval_counts,
    knots_to_remove,
    projected_band_covariance,
    unresolved_attitude,
)
from misrgraph.model.frames import ecef_to_geodetic
from misrgraph.model.gcp import GcpDatabase
from misrgraph.model.noise import NoiseModel

__all__ = [
    "GraphConfig",
    "calibrated_camera_sigma",
    "calibration_rows",
    "observation_sigma",
    "check_jitter",
    "KNOT_PRIORS",
    "PROCESS_KNOT_PRIORS",
    "PassGraph",
    "build_pass_graph",
    "camera_parameter_matrix",
    "CAMERA_PRIOR_SIGMA",
    "calibration_prior_sigma",
    "merge_problems",
    "merge_flat",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
RED = BANDS.index("red")


#: Default a-priori 1 sigma of each camera parameter correction when calibrating (pre-flight
#: knowledge after launch and gravity release): angles 0.1 deg, f 0.2 mm, alpha_i ~ 1e-3 of the
#: field-angle polynomial at the swath edge (|s - c_y| = 752 px).
CAMERA_PRIOR_SIGMA = dict(
    zip(CAMERA_PARAMS, (1.745e-3, 1.745e-3, 1.745e-3, 2e-4) + tuple(1e-3 / 752.0**i for i in range(6)))
)


#: How the attitude knots are held a priori: ``"process"`` (default) ties consecutive knots by the
#: attitude error process (:func:`factors.priors.process_prior_factors`, a damped-oscillator process
#: with the navigation's value and rate sigmas) and keeps every knot; ``"process+jitter"`` adds the
#: jitter's share of the knots (``attitude_jitter_arcsec`` over ``attitude_jitter_periods_s``
#: projected onto the spline, :func:`~misrgraph.model.errormodels.projected_band_covariance`) to
#: the process's covariance, one joint prior per angle; ``"independent"`` is the seed's rule: an
#: independent prior per knot and eqs. 28-29's knot removal where data are scarce.
KNOT_PRIORS = ("process", "process+jitter", "independent")
#: the knot priors that tie the knots by the process (every knot kept)
PROCESS_KNOT_PRIORS = ("process", "process+jitter")


def check_jitter(jitter_arcsec: float, periods_s: Any) -> None:
    """Refuse a jitter 1 sigma (arcsec) that is not a number >= 0, or periods (s) that are not two
    numbers ``0 < min < max``, naming the setting (``attitude_jitter_arcsec``/``_periods_s``)."""
    if not (np.isfinite(jitter_arcsec) and jitter_arcsec >= 0):
        raise InputError("attitude_jitter_arcsec", jitter_arcsec, "a number >= 0 (1 sigma, arcsec)")
    if not (
        isinstance(periods_s, (tuple, list))
        and len(periods_s) == 2
        and all(isinstance(x, (int, float)) for x in periods_s)
        and 0 < periods_s[0] < periods_s[1] < np.inf
    ):
        raise InputError("attitude_jitter_periods_s", periods_s, "two periods 0 < min < max in s")


#: the pre-flight levels the graph's configuration defaults to
_PRE_FLIGHT = NoiseModel()


@dataclass(frozen=True)
class GraphConfig(Config):
    """How a pass becomes a graph (units in the names). ``knot_prior``: see :data:`KNOT_PRIORS`
    (``threshold1``/``threshold2``/``knot_rule`` apply to ``"independent"`` only)."""

    knot_spacing_s: tuple = (60.0, 60.0, 60.0)
    threshold1: int = 1
    threshold2: int = 1
    knot_rule: str = "support"
    knot_prior: str = "process"
    #: damping ratio of the ``"process"`` knot prior (1: Matern-3/2); the default fits the
    #: correlation of an attitude error with periods of 200-2000 s
    #: (:data:`~misrgraph.model.errormodels.ATTITUDE_DAMPING`)
    knot_prior_damping: float = _PRE_FLIGHT.attitude.damping
    ephemeris_segments: int = 1
    #: the levels below default to the pre-flight noise model (:class:`~misrgraph.model.noise.NoiseModel`,
    #: their one home; ``--noise-model`` replaces them)
    attitude_sigma_arcsec: tuple = _PRE_FLIGHT.attitude.value_sigma_arcsec
    #: the attitude error rate's 1 sigma per angle (arcsec/s); empty: the value's sigma times
    #: :data:`~misrgraph.model.errormodels.ATTITUDE_RATE_FACTOR` (:class:`~misrgraph.model.noise.AttitudeNoise`)
    attitude_rate_sigma_arcsec_per_s: tuple = _PRE_FLIGHT.attitude.rate_sigma_arcsec_per_s
    ephemeris_b_sigma_m: float = _PRE_FLIGHT.ephemeris.offset_sigma_m
    ephemeris_a_sigma_mps: tuple = _PRE_FLIGHT.ephemeris.drift_sigma_mps
    #: 1 sigma amplitude (m, per orbital axis) of a once-per-revolution ephemeris error (orbit
    #: determination's periodic term). With it the segments get one joint prior: the covariance
    #: of their least-squares fit to the offset, the drift and the term
    #: (:func:`~misrgraph.model.errormodels.ephemeris_prior_covariance`; 1 or 2 segments, 2
    #: follow the term's curvature over a long pass); 0: independent offset and drift priors
    ephemeris_once_per_rev_m: float = _PRE_FLIGHT.ephemeris.once_per_rev_m
    #: 1 sigma (arcsec, per angle) of attitude jitter with periods log-uniform in
    #: ``attitude_jitter_periods_s`` (s). The part the knots cannot follow, with the part of the
    #: slow process between the knots (:meth:`unresolved_attitude_rad`, on this pass's knots), is
    #: noise in every image observation: its pointing sensitivity (``d(line, sample) / d(roll,
    #: pitch, yaw)`` at the start values) carries it into the observation's line and sample sigma,
    #: ``sigma_line^2 = sigma_px^2 + sigma_u^2 |d line / d angles|^2`` (likewise the sample).
    #: 0: the matcher's sigma alone (the knots are taken to follow the whole attitude error)
    attitude_jitter_arcsec: float = 0.0
    attitude_jitter_periods_s: tuple = _PRE_FLIGHT.jitter.periods_s
    estimate_camera: bool = True
    camera_params: tuple = ("delta", "beta", "epsilon")
    camera_per_band: bool = False
    camera_prior_px: float = _PRE_FLIGHT.camera.angle_prior_px
    #: 1 sigma of a calibrated model's f and alpha_i among ``camera_params``, in pixels moved at
    #: the swath edge (|s - c_y| = 752) by an alpha_i; f to the same relative amount
    #: (:func:`calibrated_camera_sigma`)
    camera_focal_prior_px: float = _PRE_FLIGHT.camera.focal_prior_px
    camera_prior_calibration: bool = False
    #: with ``camera_prior_calibration``: 0 gives f and alpha_i the wide pre-flight prior of
    #: :data:`CAMERA_PRIOR_SIGMA`; a positive value gives them the prior of a measured focal plane
    #: known to this many pixels at the swath edge (:func:`calibrated_camera_sigma`), the angles
    #: keeping their wide prior
    calibration_focal_prior_px: float = 0.0
    estimate_omega: bool = False
    omega_prior_rad: float = 1.745e-3
    use_dem: bool = True
    #: the DEM height factors' sigma is the DEM's stated 1 sigma (posting or quality class) times
    #: this, combined with the local surface fit's residual RMS (which this does not scale); 1
    #: weights the DEM as stated (the posting-level roughness that would make the term
    #: pull too hard is removed by ``dem_smoothing_postings``; docs, "The DEM weight")
    dem_sigma_scale: float = _PRE_FLIGHT.dem.sigma_scale
    #: every tie point's image sigma, every GCP's image sigma and every GCP's position sigma (and
    #: its scene's) are their files' stated sigma times these (:class:`~misrgraph.model.noise.ObservationNoise`)
    tie_sigma_scale: float = _PRE_FLIGHT.observations.tie_sigma_scale
    gcp_pixel_sigma_scale: float = _PRE_FLIGHT.observations.gcp_pixel_sigma_scale
    gcp_sigma_scale: float = _PRE_FLIGHT.observations.gcp_sigma_scale
    #: 1 sigma (DEM postings) of the Gaussian low-pass applied to the DEM before the height
    #: factors read it (:meth:`DemTiles.smoothed`; their sigma keeps the raw DEM's local
    #: roughness). Posting-level roughness (DEM noise, relief the posting aliases) curves the
    #: surface at the scale of a landmark's horizontal uncertainty, and summed over a pass's
    #: landmarks it makes the DEM term non-quadratic in the pass's horizontal position: at 0 the
    #: pass's mean horizontal error is 1.8x its predicted variance even under the model truth.
    #: 0: the DEM as it is
    dem_smoothing_postings: float = 1.0
    #: give each source scene of the GCP database (``GcpDatabase.scene``) one offset variable that
    #: its GCPs share (:func:`factors.priors.gcp_scene_prior`); False treats every GCP's error as
    #: its own (what a database without scenes gets anyway)
    gcp_scenes: bool = True
    dem_method: str = "bicubic"
    group_by: str = "landmark"
    robust: str = "none"
    robust_k: float = 3.0

    def __post_init__(self) -> None:
        if self.group_by not in ("landmark", "observation"):
            raise InputError("group_by", self.group_by, ("landmark", "observation"))
        if self.robust not in ("none", "huber", "cauchy"):
            raise InputError("robust", self.robust, ("none", "huber", "cauchy"))
        bad = [p for p in self.camera_params if p not in CAMERA_PARAMS]
        if bad or not self.camera_params:
            raise InputError("camera_params", bad or self.camera_params, CAMERA_PARAMS)
        if self.knot_prior not in KNOT_PRIORS:
            raise InputError("knot_prior", self.knot_prior, KNOT_PRIORS)
        if self.knot_rule not in ("interval", "support"):
            raise InputError("knot_rule", self.knot_rule, ("interval", "support"))
        if not (np.isfinite(self.knot_prior_damping) and self.knot_prior_damping > 0):
            raise InputError("knot_prior_damping", self.knot_prior_damping, "a positive damping ratio (1: Matern-3/2)")
        if not (np.isfinite(self.ephemeris_once_per_rev_m) and self.ephemeris_once_per_rev_m >= 0):
            raise InputError("ephemeris_once_per_rev_m", self.ephemeris_once_per_rev_m, "a 1 sigma amplitude >= 0 (m)")
        if int(self.ephemeris_segments) != self.ephemeris_segments or self.ephemeris_segments < 1:
            raise InputError("ephemeris_segments", self.ephemeris_segments, "an integer >= 1")
        if self.ephemeris_once_per_rev_m > 0 and self.ephemeris_segments > 2:
            raise InputError(
                "ephemeris_segments",
                self.ephemeris_segments,
                "1 or 2 with ephemeris_once_per_rev_m > 0 (an offset, a drift and the once-per-revolution "
                "term are 4 variables per axis)",
            )
        check_jitter(self.attitude_jitter_arcsec, self.attitude_jitter_periods_s)
        if not (np.isfinite(self.dem_sigma_scale) and self.dem_sigma_scale > 0):
            raise InputError("dem_sigma_scale", self.dem_sigma_scale, "a positive factor on the DEM's stated sigma")
        if not (np.isfinite(self.dem_smoothing_postings) and 0 <= self.dem_smoothing_postings <= 2):
            raise InputError("dem_smoothing_postings", self.dem_smoothing_postings, "a sigma in DEM postings, 0 to 2")
        if len(self.attitude_sigma_arcsec) != 3 or not min(self.attitude_sigma_arcsec) > 0:
            raise InputError(
                "attitude_sigma_arcsec",
                self.attitude_sigma_arcsec,
                "three positive sigmas (roll, pitch, yaw) in arcsec",
            )
        for name in ("tie_sigma_scale", "gcp_pixel_sigma_scale", "gcp_sigma_scale"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise InputError(name, getattr(self, name), "a positive factor on the stated sigma")
        rate = self.attitude_rate_sigma_arcsec_per_s
        if len(rate) not in (0, 3) or (len(rate) and not min(rate) > 0):
            raise InputError(
                "attitude_rate_sigma_arcsec_per_s",
                rate,
                "empty or three positive sigmas (roll, pitch, yaw) in arcsec/s",
            )
        if len(self.knot_spacing_s) != 3 or min(self.knot_spacing_s) <= 0:
            raise InputError("knot_spacing_s", self.knot_spacing_s, "three positive spacings (roll, pitch, yaw) in s")
        if len(set(self.camera_params)) != len(self.camera_params):
            raise InputError("camera_params", self.camera_params, "distinct parameter names")
        for name in ("camera_prior_px", "camera_focal_prior_px"):
            if not getattr(self, name) > 0:
                raise InputError(name, getattr(self, name), "a positive 1 sigma in pixels")
        if not (np.isfinite(self.calibration_focal_prior_px) and self.calibration_focal_prior_px >= 0):
            raise InputError(
                "calibration_focal_prior_px",
                self.calibration_focal_prior_px,
                "0 (the wide pre-flight prior) or a positive 1 sigma in pixels",
            )

    def attitude_process(self) -> tuple[tuple, tuple, float]:
        """The slow attitude process per angle: ``(value sigma arcsec (3,), rate sigma arcsec/s
        (3,), damping)``, the rate's sigma the value's times
        :data:`~misrgraph.model.errormodels.ATTITUDE_RATE_FACTOR` unless stated."""
        value = tuple(float(x) for x in self.attitude_sigma_arcsec)
        rate = tuple(float(x) for x in self.attitude_rate_sigma_arcsec_per_s) or tuple(
            v * ATTITUDE_RATE_FACTOR for v in value
        )
        return value, rate, float(self.knot_prior_damping)

    def unresolved_attitude_rad(self, knot_times: list[Array]) -> float:
        """1 sigma (rad) of the attitude error the knots on ``knot_times`` (per angle, s) cannot
        follow (:func:`~misrgraph.model.errormodels.unresolved_attitude`): the jitter's share and,
        under the ``"process"`` knot prior, the slow process's between the knots (0.027 of its sigma
        for the pre-flight process on knots every 60 s). 0 without jitter
        (``attitude_jitter_arcsec`` 0: the knots are taken to follow the whole attitude error)."""
        if self.attitude_jitter_arcsec == 0:
            return 0.0
        process = self.attitude_process() if self.knot_prior in PROCESS_KNOT_PRIORS else None
        return unresolved_attitude(
            knot_times, self.attitude_jitter_arcsec, tuple(self.attitude_jitter_periods_s), process
        )


@dataclass
class PassGraph:
    """The graph of one pass plus what is needed to interpret the solution."""

    problem: Problem
    pass_index: int
    attitude_model: AttitudeErrorModel
    removed_knots: list[NDArray[np.int64]]
    ephemeris_model: EphemerisErrorModel
    landmark_rows: NDArray[np.int64]
    landmark_keys: NDArray[np.int64]
    obs_index: NDArray[np.int64]
    collinearity: CollinearityBatch
    camera_keys: dict[int, int] = field(default_factory=dict)
    #: the camera-correction parameters of every camera variable, in order (:data:`CAMERA_PARAMS`)
    camera_params: tuple[str, ...] = ("delta", "beta", "epsilon")

    def camera_corrections(self, values: gtsam.Values) -> dict[int, Array]:
        """Every camera variable's corrections in SI (rad for the angles, m for f, alpha_i as
        the model stores them), keyed by its camera code, in the order of ``camera_params``."""
        scale = camera_param_scale(self.camera_params)
        return {c: values.atVector(k) * scale for c, k in self.camera_keys.items()}

    def knot_keys(self, angle: int) -> list[int]:
        return [K.knot_key(angle, self.pass_index, i) for i in range(self.attitude_model.knot_times[angle].size)]

    def ephemeris_keys(self) -> list[int]:
        return [K.ephemeris_key(self.pass_index, s) for s in range(self.ephemeris_model.n_segments)]

    def attitude_sigma(self, marginals: Any, angle: int, t: ArrayLike) -> Array:
        """A-posteriori 1 sigma (rad) of the attitude error ``E(t)`` of one angle at times ``t``
        (s): ``sqrt(w S w^T)`` with ``w`` the Hermite weights and ``S`` the joint covariance of the
        two bracketing knots (``marginals``: a :class:`~misrgraph.estimate.problem.Marginals`)."""
        i, w = self.attitude_model.bracket(angle, t)
        keys = self.knot_keys(angle)
        out = np.empty(i.size)
        for j in np.unique(i):
            sel = i == j
            s = marginals.joint_of([keys[j], keys[j + 1]])
            out[sel] = np.einsum("ni,ij,nj->n", w[sel], s, w[sel])
        return np.sqrt(np.maximum(out, 0.0))


def camera_parameter_matrix(camera: CameraModel, cam: NDArray[np.int64], band: NDArray[np.int64]) -> Array:
    """Per-observation 10-vector (delta, beta, eps, f, alpha_0..5) of the supplied model; the angles
    include each observation's band offsets."""
    d, b_, e = camera.angles(cam, band)
    return np.concatenate(
        [d[:, None], b_[:, None], e[:, None], camera.focal_length[cam, band][:, None], camera.alpha[cam, band]], axis=1
    )


def dem_surface(dem: DemTiles, geoid: Geoid, method: str):
    """Callable ``(lat, lon) -> (h_ellipsoid, dh/dlat, dh/dlon)`` for the DEM factor.

    It passes the tiles of its last call as the hint of the next (the solver evaluates the same
    landmarks again and again; a hint of another length is ignored), which skips most tile
    searches; the heights do not depend on it.
    """
    last: list[NDArray[np.int64] | None] = [None]

    def surface(lat: Array, lon: Array) -> tuple[Array, Array, Array]:
        """NaN where a landmark is off the DEM tiles (an LM trial step then has an infinite cost)."""
        s = fit_local_surface(dem, lat, lon, method, hint=last[0])
        last[0] = s.tile
        return s.height + geoid.undulation(lat, lon), s.dh_dlat, s.dh_dlon

    return surface


def build_pass_graph(
    orbit_pass: OrbitPass,
    camera: CameraModel,
    dem: DemTiles | None,
    gcps: GcpDatabase | None,
    cfg: GraphConfig = GraphConfig(),
    pass_index: int = 0,
    geoid: Geoid | None = None,
    exclude_observations: NDArray[np.bool_] | None = None,
    shared: set[int] | None = None,
    camera_for_pass: CameraModel | None = None,
    temperature_bin: int = 0,
    known_landmarks: Mapping[int, Array] | None = None,
    camera_prior: tuple[list[str], Array] | None = None,
) -> PassGraph:
    """Build the factor graph of one pass (see the module docstring).

    ``camera_prior``: the joint covariance of the camera model's calibration (``(labels,
    covariance)``, :func:`misrgraph.io.camera.read_calibration_prior`): the corrections of the
    cameras it covers (all of ``cfg.camera_params``) get it as one joint prior instead of
    ``cfg.camera_prior_px`` each; not with per-band corrections or in a calibration.

    ``shared`` holds keys (GCPs, cameras, omega) whose value and prior another pass of the same
    problem already added: they are referenced, not added again. ``camera_for_pass`` is the
    supplied model at this pass's temperature when it differs from ``camera``. ``temperature_bin``
    selects the camera-correction variables of a thermal calibration (one set per temperature
    bin); ``camera_keys`` then maps ``bin * 1000 + camera code`` to the key.
    """
    shared = shared if shared is not None else set()
    # the height factors read a low-passed DEM (dem_smoothing_postings); their sigma keeps the
    # raw DEM's local roughness (the fit's residual RMS), which covers what the low-pass removed
    dem_raw = dem
    if dem is not None:
        dem = dem.smoothed(cfg.dem_smoothing_postings)  # 0: the DEM itself
    camera = camera_for_pass or camera
    geoid = geoid or Geoid("zero")
    obs = orbit_pass.observations
    kinds = orbit_pass.landmarks.kind
    is_gcp = kinds == KIND_GCP
    if is_gcp.any():
        n_db = len(gcps) if gcps is not None else 0
        bad = np.flatnonzero(is_gcp & (orbit_pass.landmarks.gcp_index >= n_db))
        if bad.size:
            raise InputError(
                f"pass {orbit_pass.pass_id}: landmarks.gcp_index[{bad[0]}]",
                int(orbit_pass.landmarks.gcp_index[bad[0]]),
                f"a row of the GCP database ({n_db} GCPs); is this the pass's GCP database?",
            )
    use = kinds[obs.landmark] != KIND_CHECK
    if exclude_observations is not None:
        use &= ~exclude_observations
    idx = np.flatnonzero(use)
    if idx.size == 0:
        n_all = int(np.sum(kinds[obs.landmark] != KIND_CHECK)) if len(obs) else 0
        if n_all:
            raise DegenerateProblemError(
                f"pass {orbit_pass.pass_id}: all {n_all} tie-point and GCP observations were "
                "excluded (rejected as blunders or unsupported); nothing is left to adjust"
            )
        raise DegenerateProblemError(f"pass {orbit_pass.pass_id}: no tie-point or GCP observations to adjust")
    cams_used = np.unique(obs.camera[idx])
    if cams_used.size < 2:
        raise DegenerateProblemError(
            f"pass {orbit_pass.pass_id}: observations from a single camera ({CAMERAS[cams_used[0]]}); "
            "multi-angle adjustment needs at least two cameras"
        )
    cam, band = obs.camera[idx], obs.band[idx]
    t_obs = orbit_pass.observation_times()[idx]
    t_lo, t_hi = orbit_pass.span
    geo = orbit_pass.geometry(camera)
    nav = geo.nav_state(t_obs)
    # --- ephemeris and attitude error models (structure only; values are variables)
    eph = EphemerisErrorModel.zeros(t_lo, t_hi, cfg.ephemeris_segments)
    seg, design = eph.design(t_obs)
    att = AttitudeErrorModel.zeros(t_lo, t_hi, cfg.knot_spacing_s)
    removed = []
    for a in range(3):
        if cfg.knot_prior in PROCESS_KNOT_PRIORS:  # knots without data are held by the process prior
            removed.append(np.zeros(0, np.int64))
            continue
        counts = interval_counts(att.knot_times[a], t_obs, cam)
        removed.append(knots_to_remove(counts, cfg.threshold1, cfg.threshold2, cfg.knot_rule))
    att_kept = att.without(removed)
    hermite = np.empty((idx.size, 3, 4))
    knot_keys = np.empty((idx.size, 3, 2), np.int64)
    for a in range(3):
        i, w = att_kept.bracket(a, t_obs)
        hermite[:, a] = w
        knot_keys[:, a, 0] = [K.knot_key(a, pass_index, int(j)) for j in i]
        knot_keys[:, a, 1] = [K.knot_key(a, pass_index, int(j) + 1) for j in i]
    # --- landmarks
    lm_rows = np.unique(obs.landmark[idx])
    lm_key_of = {}
    for row in lm_rows:
        if kinds[row] == KIND_GCP:
            lm_key_of[row] = K.gcp_key(int(orbit_pass.landmarks.gcp_index[row]))
        else:
            lm_key_of[row] = K.landmark_key(orbit_pass.path, int(orbit_pass.landmarks.id[row]))
    obs_lm_key = np.array([lm_key_of[r] for r in obs.landmark[idx]], np.int64)
    # initial landmark positions: mean of each view's ray cast onto the DEM (supplied navigation)
    known = known_landmarks if known_landmarks is not None else {}
    cast = np.array([lm_key_of[r] not in known for r in obs.landmark[idx]], bool)
    init = _initial_landmarks(orbit_pass, geo, idx[cast], dem, geoid, cfg.dem_method)
    init.update({int(r): np.asarray(known[lm_key_of[r]], float) for r in lm_rows if lm_key_of[r] in known})
    # --- constants and batch; the along-track residual is in image lines (a matcher's unit)
    lm_init = np.stack([init[int(r)] for r in obs.landmark[idx]])
    rate = geo.line_rate(cam, band, lm_init, t_obs)
    const = CollinearityConstants(
        nav.eci_to_ecef,
        nav.position,
        nav.t_go,
        design,
        nav.angles,
        hermite,
        camera.k[cam, band],
        obs.line[idx] - obs.exposure_index[idx],
        obs.sample[idx] - camera.cy[cam, band],
        camera.focal_plane_dy_ds(cam, band, obs.sample[idx]),
        camera.dx,
        camera.dx * rate,
    )
    keys = {
        "landmark": obs_lm_key,
        "ephemeris": np.array([K.ephemeris_key(pass_index, int(s)) for s in seg]),
        "knots": knot_keys,
    }
    camera_keys: dict[int, int] = {}
    if cfg.estimate_camera:
        if cfg.camera_per_band:
            pairs = np.unique(np.stack([cam, band], 1), axis=0)
            off = 1000 * temperature_bin
            camera_keys = {off + int(c) * 10 + int(b): K.camera_key(int(c), int(b), temperature_bin) for c, b in pairs}
            keys["camera"] = np.array([camera_keys[off + int(c) * 10 + int(b)] for c, b in zip(cam, band)], np.int64)
        else:
            off = 1000 * temperature_bin
            camera_keys = {off + int(c): K.camera_key(int(c), None, temperature_bin) for c in cams_used}
            keys["camera"] = np.array([camera_keys[off + int(c)] for c in cam], np.int64)
    if cfg.estimate_omega:
        keys["omega"] = np.full(idx.size, K.omega_key(), np.int64)
    select = tuple(CAMERA_PARAMS.index(p) for p in cfg.camera_params)
    group = obs.landmark[idx] if cfg.group_by == "landmark" else np.arange(idx.size)
    robust = None if cfg.robust == "none" else (cfg.robust, cfg.robust_k)
    cam_params = camera_parameter_matrix(camera, cam, band)
    sigma_px = obs.sigma_px[idx]
    if cfg.tie_sigma_scale != 1.0 or cfg.gcp_pixel_sigma_scale != 1.0:
        kind = orbit_pass.landmarks.kind[obs.landmark[idx]]
        sigma_px = sigma_px * np.select(
            [kind == KIND_TIE, kind == KIND_GCP], [cfg.tie_sigma_scale, cfg.gcp_pixel_sigma_scale], 1.0
        )
    sigma = observation_sigma(
        sigma_px,
        const,
        lm_init,
        cam_params,
        camera.omega,
        cfg.unresolved_attitude_rad(att_kept.knot_times),
    )
    coll = CollinearityBatch(const, cam_params, camera.omega, sigma, group, keys, select, robust)
    graph = gtsam.NonlinearFactorGraph()
    problem = Problem(graph, gtsam.Values(), [], [], {})
    problem.add_batch(coll)
    values = problem.initial
    dims: dict[int, int] = {}

    def add(key: int, value: Array) -> bool:
        """Add a variable unless another pass of the problem owns it; True when added here."""
        dims[int(key)] = int(np.size(value))
        if int(key) in shared:
            return False
        values.insert(int(key), np.asarray(value, dtype=float))
        return True

    surface = dem_surface(dem, geoid, cfg.dem_method) if dem is not None else None
    dem_keys: list[int] = []
    dem_sig = dem_stated = np.zeros(0)
    dem_rows: list[int] = []
    gcp_ecef = gcps.ecef() if gcps is not None else None
    scenes = gcps.scenes() if gcps is not None and cfg.gcp_scenes else {}
    scene_of = {int(g): sc for sc, rows in scenes.items() for g in rows}
    # each GCP's own error: all of it where it has no scene (there the two are the same)
    gcp_cov = (gcps.own_covariance_ecef() if scenes else gcps.covariance_ecef()) if gcps is not None else None
    if gcp_cov is not None and cfg.gcp_sigma_scale != 1.0:
        gcp_cov = gcp_cov * cfg.gcp_sigma_scale**2
    scene_keys: list[int] = []
    for row in lm_rows:
        key = lm_key_of[row]
        if kinds[row] == KIND_GCP:
            if gcp_ecef is None or gcp_cov is None or gcps is None:
                raise InputError("gcps", None, "the GCP database (the pass has GCP observations)")
            gi = int(orbit_pass.landmarks.gcp_index[row])
            sc = scene_of.get(gi)
            if sc is None:
                if add(key, gcp_ecef[gi]):
                    graph.add(gcp_prior(key, gcp_ecef[gi], gcp_cov[gi]))
                continue
            assert gcps.scene_sigma_m is not None
            sk = K.gcp_scene_key(sc)
            if sk not in dims:
                scene_keys.append(sk)
                if add(sk, np.zeros(3)):  # its prior at the scene's mean position (a 2 deg scene: one ENU frame)
                    r = scenes[sc]
                    c_s = enu_covariance(
                        np.radians(gcps.lat[r].mean()),
                        np.radians(gcps.lon[r].mean()),
                        np.full(3, gcps.scene_sigma_m[r[0]] * cfg.gcp_sigma_scale),
                    )
                    graph.add(scene_offset_prior(sk, c_s))
            if add(key, gcp_ecef[gi]):
                graph.add(gcp_scene_prior(key, sk, gcp_ecef[gi], gcp_cov[gi]))
        elif add(key, init[row]):
            dem_rows.append(row)
    if cfg.use_dem and dem is not None and dem_rows:
        # one vectorised surface fit for every tie point this pass owns (sigma of its DEM factor)
        lat, lon, _ = ecef_to_geodetic(np.stack([init[r] for r in dem_rows]))
        s = fit_local_surface(dem_raw, lat, lon, cfg.dem_method)
        dem_keys = [lm_key_of[r] for r, ok in zip(dem_rows, s.valid) if ok]
        # the scale is on the DEM's stated sigma; the surface fit's residual RMS is the estimator's own
        dem_stated = s.stated[s.valid] * cfg.dem_sigma_scale
        fit_rms2 = np.clip(s.sigma[s.valid] ** 2 - s.stated[s.valid] ** 2, 0.0, None)
        dem_sig = np.sqrt(dem_stated**2 + fit_rms2)
    if dem_keys:
        assert surface is not None
        problem.add_batch(DemBatch(np.array(dem_keys), dem_sig, surface, dem_stated))
    # navigation variables and priors
    att_sig = np.asarray(cfg.attitude_sigma_arcsec) * ARCSEC
    if len(cfg.attitude_rate_sigma_arcsec_per_s):
        rate_sig = np.asarray(cfg.attitude_rate_sigma_arcsec_per_s) * ARCSEC
        lam = rate_sig / att_sig  # the process's natural frequency (1/s)
    else:
        rate_sig = att_sig * ATTITUDE_RATE_FACTOR
        lam = np.full(3, ATTITUDE_RATE_FACTOR)
    for a in range(3):
        ks = [K.knot_key(a, pass_index, j) for j in range(att_kept.knot_times[a].size)]
        for k in ks:
            add(k, np.zeros(2))
        if cfg.knot_prior == "process+jitter" and cfg.attitude_jitter_arcsec > 0:
            t_a = att_kept.knot_times[a]
            cov = process_covariance(t_a, float(att_sig[a]), float(lam[a]), cfg.knot_prior_damping)
            cov = cov + projected_band_covariance(
                t_a, cfg.attitude_jitter_arcsec * ARCSEC, tuple(cfg.attitude_jitter_periods_s)
            )
            graph.add(joint_prior_factor(ks, [2] * len(ks), cov))
        elif cfg.knot_prior in PROCESS_KNOT_PRIORS:
            for f in process_prior_factors(
                ks, att_kept.knot_times[a], float(att_sig[a]), float(lam[a]), cfg.knot_prior_damping
            ):
                graph.add(f)
        else:
            for k in ks:
                graph.add(vector_prior(k, np.zeros(2), [att_sig[a], rate_sig[a]]))
    eph_keys = [K.ephemeris_key(pass_index, s) for s in range(eph.n_segments)]
    for k in eph_keys:
        add(k, np.zeros(6))
    if cfg.ephemeris_once_per_rev_m > 0:  # one joint prior: the segments share the pass's process
        cov = ephemeris_prior_covariance(
            eph.boundaries, cfg.ephemeris_a_sigma_mps, cfg.ephemeris_b_sigma_m, cfg.ephemeris_once_per_rev_m
        )
        sel = np.eye(6 * eph.n_segments)
        graph.add(
            linear_factor(
                eph_keys, [sel[:, 6 * s : 6 * s + 6] for s in range(eph.n_segments)], np.zeros(6 * eph.n_segments), cov
            )
        )
    else:
        eph_sig = np.r_[np.asarray(cfg.ephemeris_a_sigma_mps, float), np.full(3, cfg.ephemeris_b_sigma_m)]
        for k in eph_keys:
            graph.add(vector_prior(k, np.zeros(6), eph_sig))
    scale = camera_param_scale(cfg.camera_params)
    use_calibration = camera_prior is not None and not cfg.camera_per_band and not cfg.camera_prior_calibration
    joint_keys: list[int] = []
    joint_rows: list[NDArray[np.int64]] = []
    for ck, k in camera_keys.items():
        c = (ck % 1000) // 10 if cfg.camera_per_band else ck % 1000
        if cfg.camera_prior_calibration:
            sig = calibration_prior_sigma(camera, c, cfg.camera_params, cfg.calibration_focal_prior_px) / scale
        else:
            sig = (
                calibrated_camera_sigma(camera, c, cfg.camera_params, cfg.camera_prior_px, cfg.camera_focal_prior_px)
                / scale
            )
        if not add(k, np.zeros(len(cfg.camera_params))):
            continue
        rows = calibration_rows(camera_prior, c, cfg.camera_params) if use_calibration else None
        if rows is None:
            graph.add(vector_prior(k, np.zeros(len(cfg.camera_params)), sig))
        else:
            joint_keys.append(k)
            joint_rows.append(rows)
    if joint_keys:  # the calibration's joint covariance of these cameras' corrections, in the variables' units
        assert camera_prior is not None
        n = len(cfg.camera_params)
        rows_all = np.concatenate(joint_rows)
        s_all = np.tile(scale, len(joint_keys))
        cov = camera_prior[1][np.ix_(rows_all, rows_all)] / np.outer(s_all, s_all)
        graph.add(joint_prior_factor(joint_keys, [n] * len(joint_keys), cov))
    if cfg.estimate_omega and add(K.omega_key(), np.zeros(3)):
        graph.add(vector_prior(K.omega_key(), np.zeros(3), np.full(3, cfg.omega_prior_rad)))
    last = list(camera_keys.values()) + ([K.omega_key()] if cfg.estimate_omega else []) + scene_keys
    problem.eliminate_first = [int(lm_key_of[r]) for r in lm_rows]
    problem.dims = dims
    problem.eliminate_last = last
    log.info(
        "pass %s: %d observations, %d landmarks, knots kept %s (removed %s)",
        orbit_pass.pass_id,
        idx.size,
        lm_rows.size,
        [t.size for t in att_kept.knot_times],
        [r.size for r in removed],
    )
    return PassGraph(
        problem,
        pass_index,
        att_kept,
        removed,
        eph,
        lm_rows,
        np.array([lm_key_of[r] for r in lm_rows], np.int64),
        idx,
        coll,
        camera_keys,
        tuple(cfg.camera_params),
    )


def observation_sigma(
    sigma_px: Array,
    const: CollinearityConstants,
    landmarks: Array,
    camera_params: Array,
    omega: Array,
    unresolved_rad: float,
) -> Array:
    """1 sigma ``(N, 2)`` (image lines, samples) of each observation: the matcher's ``sigma_px
    (N,)`` and an attitude error of ``unresolved_rad`` (rad, 1 sigma per angle, independent
    angles) that the knots cannot follow, carried by the observation's pointing sensitivity
    ``D = d(line, sample) / d(roll, pitch, yaw)`` ``(N, 2, 3)`` at ``landmarks (N, 3)`` (ECEF m)
    and the supplied navigation and camera (``camera_params (N, 10)``, ``omega (3,)``)::

        sigma_line^2 = sigma_px^2 + unresolved^2 * sum_a D[0, a]^2,   likewise the sample.

    The line-sample correlation of the attitude term is left out (the weights are diagonal). An
    oblique camera's lines feel pitch most: 0.86" of jitter adds ~0.075 px to a D camera's line
    sigma, 14 % of the variance of a 0.2 px tie point, and ~0.011 px to An's."""
    sig = np.stack([np.asarray(sigma_px, float)] * 2, axis=1)
    if unresolved_rad == 0 or len(const) == 0:
        return sig
    one = dataclasses.replace(
        const, hermite=np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0]), const.hermite.shape).copy()
    )
    _, jac = collinearity_residual(
        np.asarray(landmarks, float),
        np.zeros((len(const), 6)),
        np.zeros((len(const), 3, 4)),
        np.asarray(camera_params, float),
        np.asarray(omega, float),
        one,
    )
    assert jac is not None
    d_angles = -jac["knots"][:, :, :, 0]  # the attitude error enters with a minus sign
    return np.sqrt(sig**2 + unresolved_rad**2 * np.sum(d_angles**2, axis=2))


def calibration_rows(
    camera_prior: tuple[list[str], Array] | None, cam: int, params: tuple[str, ...]
) -> NDArray[np.int64] | None:
    """Indices into a calibration's covariance (``(labels, covariance)``) of camera ``cam``'s
    ``params``, in their order; None when it lacks any of them (or there is none)."""
    if camera_prior is None:
        return None
    index = {label: i for i, label in enumerate(camera_prior[0])}
    rows = [index.get(f"{CAMERAS[cam]}.{p}") for p in params]
    return None if any(r is None for r in rows) else np.array(rows, np.int64)


def calibration_prior_sigma(camera: CameraModel, cam: int, params: tuple[str, ...], focal_px: float = 0.0) -> Array:
    """A-priori 1 sigma (SI, ``(len(params),)``) of camera ``cam``'s corrections in a calibration:
    :data:`CAMERA_PRIOR_SIGMA` (pre-flight knowledge after launch), except that with
    ``focal_px`` > 0 f and alpha_i get the prior of a focal plane known to ``focal_px`` pixels at
    the swath edge (:func:`calibrated_camera_sigma`)."""
    wide = np.array([CAMERA_PRIOR_SIGMA[p] for p in params])
    if focal_px <= 0:
        return wide
    focal = [p for p in params if p == "f" or p.startswith("alpha")]
    if not focal:
        return wide
    narrow = calibrated_camera_sigma(camera, cam, tuple(focal), 1.0, focal_px)
    out = wide.copy()
    for p, v in zip(focal, narrow):
        out[params.index(p)] = v
    return out


def calibrated_camera_sigma(
    camera: CameraModel, cam: int, params: tuple[str, ...], angle_px: float, focal_px: float
) -> Array:
    """A-priori 1 sigma (SI, ``(len(params),)``) of a calibrated model's parameters of camera
    ``cam`` (red band): the angles to ``angle_px`` cross-track pixels at the swath edge; each
    alpha_i to ``focal_px alpha_1 / 752^i``, which moves the swath edge (|s - c_y| = 752) by
    ``focal_px`` pixels; f to the same relative amount, ``f focal_px / 752`` (f scales both
    focal-plane components of eq. 2 alike, so it moves the along-track look angle only, through
    the band's offset ``k``)."""
    ifov = float(camera.ifov_cross_rad(cam, RED, 751.5))
    out = []
    for p in params:
        if p in ("delta", "beta", "epsilon"):
            out.append(angle_px * ifov)
        elif p == "f":
            out.append(focal_px * float(camera.focal_length[cam, RED]) / 752.0)
        else:
            i = int(p[len("alpha") :])
            out.append(focal_px * abs(float(camera.alpha[cam, RED, 1])) / 752.0**i)
    return np.array(out)


def merge_problems(problems: list[Problem]) -> Problem:
    """One problem from several passes' problems built with a common ``shared`` key set:
    landmarks first, then every pass's navigation variables pass by pass, shared cameras last."""
    graph = gtsam.NonlinearFactorGraph()
    batches: list = []
    positions: list[NDArray[np.int64]] = []
    for p in problems:
        base = int(graph.size())
        graph.push_back(p.graph)
        batches += p.batches
        positions += [base + pos for pos in p.batch_positions]
    values, first, dims, last = _merged_variables(problems)
    return Problem(graph, values, batches, first, dims, last, positions)


def _merged_variables(problems: list[Problem]) -> tuple[gtsam.Values, list[int], dict[int, int], list[int]]:
    """The merged problems' initial values, landmarks (eliminated first), dimensions and
    variables eliminated last, in the order of :func:`merge_problems`."""
    values = gtsam.Values()
    dims: dict[int, int] = {}
    first: list[int] = []
    last: list[int] = []
    for p in problems:
        values.insert(p.initial)
        for k in p.eliminate_first:
            if k not in dims:
                first.append(k)
        for k, d in p.dims.items():
            dims.setdefault(k, d)
        for k in p.eliminate_last:
            if k not in last:
                last.append(k)
    return values, first, dims, last


def merge_flat(problems: list[Problem]) -> Problem:
    """:func:`merge_problems` as one least-squares problem the flat formulation (and so the Schur
    backend) covers: the passes' collinearity batches concatenated into one batch and their DEM
    batches into one, with every pass's linear priors.

    The result's graph is new (its factors call the merged batches); the landmarks, variables,
    priors and the cost are those of :func:`merge_problems` on the same problems. Raises
    :class:`~misrgraph.estimate.problem.NotFlat` when a pass has a robust loss or a factor
    outside its batches that is not a linear prior.
    """
    from misrgraph.estimate.problem import NotFlat

    colls: list[CollinearityBatch] = []
    dems: list[DemBatch] = []
    priors = []
    for p in problems:
        in_batch: set[int] = set()
        for b, pos in zip(p.batches, p.batch_positions):
            if isinstance(b, CollinearityBatch):
                colls.append(b)
            elif isinstance(b, DemBatch):
                dems.append(b)
            else:
                raise NotFlat(f"a factor batch of type {type(b).__name__} is not covered by the flat formulation")
            in_batch.update(int(i) for i in pos)
        for i in range(int(p.graph.size())):
            if i in in_batch:
                continue
            f = p.graph.at(i)
            if not isinstance(f, (gtsam.PriorFactorVector, gtsam.LinearContainerFactor)):
                raise NotFlat(f"factor of type {type(f).__name__} is not covered by the flat formulation")
            priors.append(f)
    if any(b.robust is not None for b in colls):
        raise NotFlat("robust losses are not covered by the flat formulation")
    try:
        coll = CollinearityBatch.concatenate(colls)
    except ValueError as exc:
        raise NotFlat(str(exc)) from exc
    values, first, dims, last = _merged_variables(problems)
    problem = Problem(gtsam.NonlinearFactorGraph(), values, [], first, dims, last)
    problem.add_batch(coll)
    if dems:
        problem.add_batch(DemBatch.concatenate(dems))
    for f in priors:
        problem.graph.add(f)
    return problem


def _initial_landmarks(orbit_pass: OrbitPass, geo, idx, dem, geoid, method) -> dict[int, Array]:
    """Median over views ``idx`` of each view's ray cast onto the DEM surface (or the ellipsoid),
    by landmark row."""
    obs = orbit_pass.observations
    if idx.size == 0:
        return {}
    if dem is not None:

        def surface(lat: Array, lon: Array) -> Array:
            s = fit_local_surface(dem, lat, lon, method)
            return np.where(s.valid, s.height, 0.0) + geoid.undulation(lat, lon)
    else:
        surface = None
    g = geo.pixel_to_ground(
        obs.camera[idx],
        obs.band[idx],
        obs.line[idx],
        obs.sample[idx],
        surface=surface,
        exposure=obs.exposure_index[idx],
    )
    lm = obs.landmark[idx]
    order = np.argsort(lm, kind="stable")
    rows, starts = np.unique(lm[order], return_index=True)
    groups = np.split(g[order], starts[1:])
    return {int(r): np.median(grp, axis=0) for r, grp in zip(rows, groups)}
