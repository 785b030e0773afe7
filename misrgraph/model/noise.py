"""The noise model: every level the estimator assumes about its inputs' errors, in one place.

A level is a 1 sigma (or a shape parameter) of an error the adjustment and the calibration model
but do not observe directly: the attitude error process, the jitter faster than the knots, the
ephemeris error, the camera model's residual error, the DEM's stated accuracy. Each comes from
one of three places, and :data:`LEVELS` says which for every field:

- **pre-flight**: the defaults here, documented knowledge before any data (the navigation's
  stated accuracy, the pre-flight camera calibration's residual);
- **input**: a noise-model file the user gives (``--noise-model FILE``; :mod:`misrgraph.io.noise`);
- **learned**: estimated from adjusted passes (a later ``misrgraph noise fit`` writes the same file).

Units are in the field names: ``arcsec`` (angles), ``arcsec_per_s`` (rates), ``m``, ``mps``
(m/s), ``px`` (pixels of the red band at the swath edge), ``s`` (periods). Axis triples are
(roll, pitch, yaw) for the attitude and (along, cross, radial) for the ephemeris.

The model maps onto the pass graph's configuration (:meth:`NoiseModel.graph_fields`); the
calibration takes its navigation levels (:meth:`NoiseModel.navigation_fields`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from misrgraph.config import Config
from misrgraph.errors import InputError
from misrgraph.model.errormodels import ATTITUDE_DAMPING, ATTITUDE_RATE_FACTOR, JITTER_PERIODS_S

__all__ = [
    "levels_markdown",
    "NOISE_MODEL_VERSION",
    "AttitudeNoise",
    "JitterNoise",
    "EphemerisNoise",
    "CameraNoise",
    "DemNoise",
    "ObservationNoise",
    "NoiseModel",
    "LEVELS",
]

#: the version of the noise model's fields (a file of another version is refused)
NOISE_MODEL_VERSION = 1

#: the GN&C's stated attitude knowledge, 3 sigma (41, 44, 36 arcsec roll, pitch, yaw), as 1 sigma
_ATTITUDE_SIGMA = (41.0 / 3, 44.0 / 3, 36.0 / 3)


def _positive(name: str, values: Any, n: int | None = None, allow_zero: bool = False) -> None:
    v = np.atleast_1d(np.asarray(values, dtype=float))
    if (n is not None and v.size != n) or not np.all(np.isfinite(v)) or not np.all(v >= 0 if allow_zero else v > 0):
        what = f"{n} " if n else ""
        raise InputError(name, values, f"{what}finite numbers {'>= 0' if allow_zero else '> 0'}")


@dataclass(frozen=True)
class AttitudeNoise(Config):
    """The slow attitude error each knot's prior and the process between knots describe.

    ``value_sigma_arcsec``: its 1 sigma per angle. ``rate_sigma_arcsec_per_s``: its rate's 1 sigma
    (with the value, it sets the process's natural frequency); empty: the value's sigma times
    :data:`~misrgraph.model.errormodels.ATTITUDE_RATE_FACTOR` (0.0146/s). ``damping``: the
    process's damping ratio (1: Matern-3/2). ``knot_spacing_s``: the attitude knots' spacing per
    angle (s); what of the process the spline on them cannot follow weights the observations with
    the jitter (:meth:`~misrgraph.estimate.graph.GraphConfig.unresolved_attitude_rad`).
    """

    value_sigma_arcsec: tuple = _ATTITUDE_SIGMA
    rate_sigma_arcsec_per_s: tuple = ()
    damping: float = ATTITUDE_DAMPING
    knot_spacing_s: tuple = (60.0, 60.0, 60.0)

    def __post_init__(self) -> None:
        _positive("attitude.value_sigma_arcsec", self.value_sigma_arcsec, 3)
        if len(self.rate_sigma_arcsec_per_s):
            _positive("attitude.rate_sigma_arcsec_per_s", self.rate_sigma_arcsec_per_s, 3)
        _positive("attitude.damping", self.damping)
        _positive("attitude.knot_spacing_s", self.knot_spacing_s, 3)

    def rate_sigmas(self) -> tuple[float, float, float]:
        """The rate's 1 sigma per angle (arcsec/s): ``rate_sigma_arcsec_per_s``, or the value's sigma
        times :data:`~misrgraph.model.errormodels.ATTITUDE_RATE_FACTOR` when empty."""
        if len(self.rate_sigma_arcsec_per_s):
            return tuple(float(r) for r in self.rate_sigma_arcsec_per_s)  # type: ignore[return-value]
        return tuple(float(v) * ATTITUDE_RATE_FACTOR for v in self.value_sigma_arcsec)  # type: ignore[return-value]


@dataclass(frozen=True)
class JitterNoise(Config):
    """The attitude error faster than the knots: 1 sigma per angle, equal power per log-period
    between the two periods. Its unresolved part weights the observations and widens every
    geolocation sigma."""

    sigma_arcsec: float = 1.0
    periods_s: tuple = JITTER_PERIODS_S

    def __post_init__(self) -> None:
        _positive("jitter.sigma_arcsec", self.sigma_arcsec, allow_zero=True)
        _positive("jitter.periods_s", self.periods_s, 2)
        if not self.periods_s[0] < self.periods_s[1]:
            raise InputError("jitter.periods_s", self.periods_s, "MIN, MAX with MIN < MAX (s)")


@dataclass(frozen=True)
class EphemerisNoise(Config):
    """The supplied ephemeris's error: an offset and a drift per orbital axis (eq. 19), and
    optionally a once-per-revolution term of the orbit determination."""

    offset_sigma_m: float = 50.0
    drift_sigma_mps: tuple = (0.05, 0.01, 0.01)
    once_per_rev_m: float = 0.0

    def __post_init__(self) -> None:
        _positive("ephemeris.offset_sigma_m", self.offset_sigma_m)
        _positive("ephemeris.drift_sigma_mps", self.drift_sigma_mps, 3)
        _positive("ephemeris.once_per_rev_m", self.once_per_rev_m, allow_zero=True)


@dataclass(frozen=True)
class CameraNoise(Config):
    """The supplied camera model's residual error where no calibration covariance is given: the
    angles' 1 sigma and the focal plane's (f, alpha_i), as pixels moved at the swath edge."""

    angle_prior_px: float = 0.0625
    focal_prior_px: float = 0.05

    def __post_init__(self) -> None:
        _positive("camera.angle_prior_px", self.angle_prior_px)
        _positive("camera.focal_prior_px", self.focal_prior_px)


@dataclass(frozen=True)
class DemNoise(Config):
    """The DEM height factors' 1 sigma is the DEM's stated 1 sigma times ``sigma_scale``, combined
    with the local surface fit's residual RMS, which the scale does not touch."""

    sigma_scale: float = 1.0

    def __post_init__(self) -> None:
        _positive("dem.sigma_scale", self.sigma_scale)


@dataclass(frozen=True)
class ObservationNoise(Config):
    """Each class of inputs' sigma is its file's stated sigma times these: tie points' and GCPs'
    image sigma (the matcher's or the pass file's), GCPs' position sigma (the catalogue's, its
    source scene's shared part too). 1 takes every file as it states itself."""

    tie_sigma_scale: float = 1.0
    gcp_pixel_sigma_scale: float = 1.0
    gcp_sigma_scale: float = 1.0

    def __post_init__(self) -> None:
        for name in ("tie_sigma_scale", "gcp_pixel_sigma_scale", "gcp_sigma_scale"):
            _positive(f"observations.{name}", getattr(self, name))


@dataclass(frozen=True)
class NoiseModel(Config):
    """Every level the estimator assumes (module docstring); the defaults are pre-flight knowledge."""

    version: int = NOISE_MODEL_VERSION
    attitude: AttitudeNoise = field(default_factory=AttitudeNoise)
    jitter: JitterNoise = field(default_factory=JitterNoise)
    ephemeris: EphemerisNoise = field(default_factory=EphemerisNoise)
    camera: CameraNoise = field(default_factory=CameraNoise)
    dem: DemNoise = field(default_factory=DemNoise)
    observations: ObservationNoise = field(default_factory=ObservationNoise)

    def __post_init__(self) -> None:
        if self.version != NOISE_MODEL_VERSION:
            raise InputError("version", self.version, f"{NOISE_MODEL_VERSION} (the noise model's version)")
        for name, cls in (
            ("attitude", AttitudeNoise),
            ("jitter", JitterNoise),
            ("ephemeris", EphemerisNoise),
            ("camera", CameraNoise),
            ("dem", DemNoise),
            ("observations", ObservationNoise),
        ):
            if not isinstance(getattr(self, name), cls):
                raise InputError(name, getattr(self, name), f"a mapping of {cls.__name__} fields")

    def navigation_fields(self) -> dict[str, Any]:
        """The attitude, ephemeris and GCP levels as :class:`~misrgraph.estimate.graph.GraphConfig`
        fields (what a calibration needs: its navigation nuisance and its GCPs)."""
        a, e, o = self.attitude, self.ephemeris, self.observations
        return {
            "gcp_pixel_sigma_scale": float(o.gcp_pixel_sigma_scale),
            "gcp_sigma_scale": float(o.gcp_sigma_scale),
            "attitude_sigma_arcsec": tuple(float(x) for x in a.value_sigma_arcsec),
            "attitude_rate_sigma_arcsec_per_s": tuple(float(x) for x in a.rate_sigma_arcsec_per_s),
            "knot_prior_damping": float(a.damping),
            "knot_spacing_s": tuple(float(x) for x in a.knot_spacing_s),
            "ephemeris_b_sigma_m": float(e.offset_sigma_m),
            "ephemeris_a_sigma_mps": tuple(float(x) for x in e.drift_sigma_mps),
            "ephemeris_once_per_rev_m": float(e.once_per_rev_m),
        }

    @classmethod
    def from_graph(cls, graph: Any) -> "NoiseModel":
        """The noise model a pass graph's configuration (:class:`~misrgraph.estimate.graph.GraphConfig`)
        holds: the inverse of :meth:`graph_fields` (e.g. the levels an ``update`` state was created
        with)."""
        return cls(
            attitude=AttitudeNoise(
                value_sigma_arcsec=tuple(float(x) for x in graph.attitude_sigma_arcsec),
                rate_sigma_arcsec_per_s=tuple(float(x) for x in graph.attitude_rate_sigma_arcsec_per_s),
                damping=float(graph.knot_prior_damping),
                knot_spacing_s=tuple(float(x) for x in graph.knot_spacing_s),
            ),
            jitter=JitterNoise(
                sigma_arcsec=float(graph.attitude_jitter_arcsec),
                periods_s=tuple(float(x) for x in graph.attitude_jitter_periods_s),
            ),
            ephemeris=EphemerisNoise(
                offset_sigma_m=float(graph.ephemeris_b_sigma_m),
                drift_sigma_mps=tuple(float(x) for x in np.broadcast_to(graph.ephemeris_a_sigma_mps, (3,))),
                once_per_rev_m=float(graph.ephemeris_once_per_rev_m),
            ),
            camera=CameraNoise(
                angle_prior_px=float(graph.camera_prior_px), focal_prior_px=float(graph.camera_focal_prior_px)
            ),
            dem=DemNoise(sigma_scale=float(graph.dem_sigma_scale)),
            observations=ObservationNoise(
                tie_sigma_scale=float(graph.tie_sigma_scale),
                gcp_pixel_sigma_scale=float(graph.gcp_pixel_sigma_scale),
                gcp_sigma_scale=float(graph.gcp_sigma_scale),
            ),
        )

    def graph_fields(self) -> dict[str, Any]:
        """Every level as :class:`~misrgraph.estimate.graph.GraphConfig` fields (a pass adjustment)."""
        return {
            **self.navigation_fields(),
            "attitude_jitter_arcsec": float(self.jitter.sigma_arcsec),
            "attitude_jitter_periods_s": tuple(float(x) for x in self.jitter.periods_s),
            "camera_prior_px": float(self.camera.angle_prior_px),
            "camera_focal_prior_px": float(self.camera.focal_prior_px),
            "dem_sigma_scale": float(self.dem.sigma_scale),
            "tie_sigma_scale": float(self.observations.tie_sigma_scale),
        }


#: every level: (section, field) -> (unit, where its default comes from)
LEVELS: dict[tuple[str, str], tuple[str, str]] = {
    ("attitude", "value_sigma_arcsec"): (
        "arcsec",
        "pre-flight: the GN&C's stated attitude knowledge, 41/44/36 arcsec 3 sigma",
    ),
    ("attitude", "rate_sigma_arcsec_per_s"): (
        "arcsec/s",
        f"pre-flight assumption: empty, the value's sigma times {ATTITUDE_RATE_FACTOR:.4f}/s "
        "(errors with periods of 200-2000 s)",
    ),
    ("attitude", "damping"): ("1", "pre-flight assumption: the process fitted to errors with periods of 200-2000 s"),
    ("attitude", "knot_spacing_s"): (
        "s",
        "pre-flight design: every 60 s for errors with periods of 200-2000 s; noise fit shortens it "
        "when it learns a faster process",
    ),
    ("jitter", "sigma_arcsec"): ("arcsec", "pre-flight assumption: the GN&C's error faster than the knots"),
    ("jitter", "periods_s"): ("s", "pre-flight assumption: 10 s Kalman updates and gyro noise, 8-120 s"),
    ("ephemeris", "offset_sigma_m"): ("m", "pre-flight: the navigation's stated position accuracy"),
    ("ephemeris", "drift_sigma_mps"): ("m/s", "pre-flight: the navigation's stated velocity accuracy"),
    ("ephemeris", "once_per_rev_m"): ("m", "input: 0 unless the orbit determination states such a term"),
    ("camera", "angle_prior_px"): (
        "px",
        "pre-flight: the calibration requirement, 1/16 px; a calibrated model's own covariance replaces it",
    ),
    ("camera", "focal_prior_px"): ("px", "pre-flight: the focal plane's ground calibration, 0.05 px at the swath edge"),
    ("dem", "sigma_scale"): (
        "1",
        "input: 1 takes the DEM's stated accuracy as it is; learned per pass (variance components) and by noise fit",
    ),
    ("observations", "tie_sigma_scale"): (
        "1",
        "input: 1 takes the tie points' stated sigma as it is; noise fit learns it",
    ),
    ("observations", "gcp_pixel_sigma_scale"): (
        "1",
        "input: 1 takes the GCP measurements' stated sigma as it is; noise fit learns it",
    ),
    ("observations", "gcp_sigma_scale"): (
        "1",
        "input: 1 takes the GCP catalogue's stated sigma as it is; noise fit learns it",
    ),
}


def levels_markdown(model: NoiseModel | None = None) -> str:
    """A Markdown table of every level: its name, pre-flight value, unit and where it comes from."""
    model = model or NoiseModel()
    rows = ["| level | pre-flight value | unit | where it comes from |", "|---|---|---|---|"]
    for (section, name), (unit, source) in LEVELS.items():
        value = getattr(getattr(model, section), name)
        if isinstance(value, tuple):
            text = ", ".join(f"{x:.6g}" for x in value) if value else "(from the value)"
        else:
            text = f"{value:.6g}"
        rows.append(f"| `{section}.{name}` | {text} | {unit} | {source} |")
    return "\n".join(rows) + "\n"
