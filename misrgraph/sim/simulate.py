"""Scenario simulator: realistic orbit passes with known injected errors (paper section 4).

Two scenarios, following the paper's order of work:

* ``month``: GCP passes over about a month for camera calibration. Every daylight (descending)
  orbit of the 16-day/233-path cycle whose common swath covers a GCP is simulated; each GCP is
  measured in every camera that sees it (1/8 px noise, a blunder fraction). The supplied camera
  model is the pre-flight (nominal) one; the truth carries post-launch misalignments of delta,
  beta, epsilon (default 60 arcsec 1 sigma: kilometres on the ground for the D cameras).
* ``pass``: one ~45-minute daylight pass with tie points over textured land (0.2 px), GCPs on the
  path (1/8 px), independent check points, and a supplied camera model that is calibrated
  (residual camera error ~1/16 px per angle, as after space resection).

Injected navigation errors per pass: ephemeris (eq. 19) b ~ N(0, 50 m) per orbital axis (150 m
3 sigma), drift a ~ N(0, 0.05 m/s) along track and N(0, 0.01 m/s) across/radial; attitude (eqs.
23-27) with the model truth a cubic Hermite spline through knots every 60 s drawn from the
estimator's own process prior (damped oscillator, :mod:`factors.priors`); with the independent truth a smooth random
process (periods 200-2000 s) plus jitter; 1 sigma 41/3, 44/3, 36/3 arcsec for roll, pitch, yaw (the
3-sigma knowledge requirement). The supplied navigation is the measured
one; the truth is ``P = P_meas - T_go e``, ``A = A_meas - E`` (docs/explanation/conventions.md). All
randomness comes from one ``numpy`` generator seeded by ``seed``.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import logging
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from factors.priors import process_transition
from misrgraph import __version__
from misrgraph.config import Config
from misrgraph.errors import FileFormatError, InputError, OutputError
from misrgraph.io.camera import load_camera_model, save_camera_model
from misrgraph.io.dem import read_dem, save_dem
from misrgraph.io.gcp import read_gcp_database, save_gcp_database
from misrgraph.io.h5 import atomic_file, check_writable, fsync_directory, make_temp_dir
from misrgraph.io.imagery import PassImagery
from misrgraph.io.passes import (
    KIND_CHECK,
    KIND_GCP,
    KIND_TIE,
    Landmarks,
    Observations,
    OrbitPass,
)
from misrgraph.io.truth import (
    PassTruth,
    read_gcp_truth,
    read_pass_truth,
    save_pass_with_truth,
)
from misrgraph.model.camera import CameraModel, TabulatedCameraModel
from misrgraph.model.constants import (
    ARCSEC,
    BANDS,
    CAMERAS,
    N_PIXELS,
    NODAL_PERIOD_S,
    REPEAT_PATHS,
)
from misrgraph.model.dem import DemTiles, Geoid
from misrgraph.model.errormodels import (
    ATTITUDE_DAMPING,
    ATTITUDE_RATE_FACTOR,
    AttitudeErrorModel,
    EphemerisErrorModel,
    uniform_knots,
)
from misrgraph.model.frames import ecef_to_geodetic
from misrgraph.model.gcp import GcpDatabase
from misrgraph.model.geolocation import PassGeometry
from misrgraph.model.nominal import nominal_camera_model
from misrgraph.model.orbit import (
    AttitudeSeries,
    Ephemeris,
    path_node_longitude,
    terra_like_orbit,
)
from misrgraph.sim.gcps import generate_gcp_database
from misrgraph.sim.terrain import SyntheticTerrain, land_mask, simulate_dem_tiles

__all__ = [
    "ScenarioConfig",
    "TRUTHS",
    "INDEPENDENT_SOURCES",
    "PAIRED_SOURCES",
    "draw_thermal_truth",
    "camera_change_arcsec",
    "camera_truth_on",
    "run_simulate",
    "scenario_terrain",
    "draw_ephemeris_error",
    "draw_attitude_error",
    "sample_process_knots",
    "draw_camera_misalignment",
    "simulate_pass",
    "Scenario",
    "load_scenario",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
Progress = Callable[[str, int, int], None]
RED = BANDS.index("red")


#: the truths the simulator can draw (see :class:`ScenarioConfig`)
TRUTHS = ("model", "independent")
#: the model truth's focal-plane errors (a pass's supplied alpha_2, alpha_3; a month's true
#: alpha_2, alpha_3) come from their own random stream, seeded by (scenario seed, this number)
MODEL_ALPHA_STREAM = 7

#: DEM postings each side of a landmark the tiles cover when imagery is rendered (8 without): a
#: matched tie point is An's interest point, up to 3 px (825 m) from the window centre, which is
#: itself the supplied navigation's prediction -- about 1 km from the simulated landmark, beyond
#: 8 postings (520-740 m). A landmark the adjustment moves off the DEM stalls the solve.
IMAGERY_DEM_PAD = 20

#: The independent truth's error sources beyond the navigation (ScenarioConfig fields; each off at
#: 0), with the value that switches them off: ``misrgraph bench sources`` turns them on one at a time.
INDEPENDENT_SOURCES = {
    "jitter_arcsec": 0.0,
    "once_per_rev_m": 0.0,
    "subposting_relief_m": 0.0,
    "dem_correlated_fraction": 0.0,
    "camera_f_alpha_px": 0.0,
    "noise_tail_dof": 0.0,
    "mismatch_rate": 0.0,
    "gcp_scene_fraction": 0.0,
}

#: The sources of :data:`INDEPENDENT_SOURCES` whose random draws do not depend on their value: a
#: scenario with one of them switched off draws every random number the scenario with it on
#: draws, in the same order, so the two differ by that source alone ("paired" draw for draw;
#: ``misrgraph bench sources --mode without``). The others draw only when they are on
#: (``camera_f_alpha_px``, ``mismatch_rate``) or draw differently (``noise_tail_dof``: Student-t
#: instead of Gaussian), which shifts every later draw.
PAIRED_SOURCES = frozenset(
    {"jitter_arcsec", "once_per_rev_m", "subposting_relief_m", "dem_correlated_fraction", "gcp_scene_fraction"}
)


@dataclass(frozen=True)
class ScenarioConfig(Config):
    """Simulator settings (units in the names). Unknown keys are rejected by ``from_dict``.

    ``truth``: ``"independent"`` (the default) draws the errors from processes the estimator does
    not share; ``"model"`` draws the navigation errors from the estimator's own parameterisations
    (an attitude spline on its knot grid, eq. 19 on its segments) -- NEES then checks the algebra
    only, which is what the model truth is for. Under the independent truth the attitude
    error is a smooth process (periods 200-2000 s) plus jitter (``jitter_arcsec`` 1 sigma, periods
    8-120 s) on a 2 s spline, the ephemeris error an offset, a drift and a once-per-revolution term
    (``once_per_rev_m`` 1 sigma per axis) on 60 s segments; and, also only there:

    * ``subposting_relief_m``: RMS of terrain at 30-180 m wavelengths, which a 3" DEM cannot hold;
    * ``dem_correlated_fraction``: the share of the DEM's smooth error variance correlated over
      ~28 km (the tie points' spacing) instead of ~5 km (the DEM factor treats errors of
      landmarks 10 km apart as independent);
    * ``camera_f_alpha_px``: 1 sigma (px at the swath edge, |s - c_y| = 752) of errors in f and in
      the field-angle polynomial's alpha_2 and alpha_3 of the true camera, which the supplied
      model does not carry (it keeps the pre-flight values; the calibration and the pass
      adjustment estimate alpha_2, alpha_3 within their prior besides the angles).
      Under the model truth it is the 1 sigma of the supplied model's alpha_2, alpha_3 error
      instead (f exact), as the adjustment's prior ``camera_focal_prior_px`` states it, and in a
      month the true camera's alpha_2, alpha_3 error, as the calibration's ``focal_prior_px`` does;
    * ``noise_tail_dof``: matching noise is Student-t with this many degrees of freedom scaled to
      the stated sigma (0: Gaussian); ``mismatch_rate`` of tie-point and GCP measurements are
      mismatches of ``mismatch_px`` (uniform in the range, random direction);
    * ``gcp_scene_fraction``: the share of each GCP's catalogue error variance shared with the
      GCPs of the same 2 x 2 deg cell (one Landsat scene's registration), the rest Student-t
      (4 degrees of freedom) per GCP, RMS ``gcp_sigma_m`` per axis in total.

    The camera errors above stay out of a pass adjustment's *estimate* of the navigation only as
    far as its camera variables allow (it estimates delta, beta, epsilon, alpha_2, alpha_3 by
    default). Each is switched off by 0 (``mismatch_rate``: 0.0); :data:`INDEPENDENT_SOURCES` names them.

    ``coast_ramp_m`` (both truths): the terrain's relief rises from 0 at the coast to its full
    height over this distance inland (:class:`~misrgraph.sim.terrain.SyntheticTerrain`); 0 leaves
    a cliff of the relief's height (~1.2 km on average) at every coast, as scenarios simulated
    before the ramp existed have (their ``scenario.json`` lacks the key).

    ``path`` scenario: ``n_passes`` repeat passes, one every 16 days from ``epoch_date``; or, when
    ``repeat_indices`` is given, only those repeat cycles (cycle k starts 16 k days after
    ``epoch_date``, orbit 233 k) -- the campaign simulates the passes it selects this way.

    Imagery for Reference Orbit Imagery (with ``imagery``): ``roi_blocks = (first, last)`` renders
    every pass's whole image lines over those blocks of the path (red band; ``strip_cameras``, default
    all nine; ``strip_samples = (first, count)`` of the array, default all 1504) and writes
    ``dem_som.h5``, the heights on the path's 275 m SOM grid over those blocks and one more each
    side (where terrain can hide their ends from the oblique cameras) with an error of
    ``roi_dem_sigma_m`` (1 sigma; :func:`misrgraph.sim.terrain.simulate_som_dem`). Each pass has
    its own clouds.
    ``feature_windows=False`` renders the strips only (no windows or chips for matching).

    ``bands``: the bands observed (simulated observations in each; with ``imagery``, GCP windows
    and chips in each, so that matched GCPs measure every band's geometry; tie-point windows in
    red, or the first band when red is not among them). Each band has its own reflectance
    (:data:`misrgraph.sim.imagery.LAND_REFLECTANCE`, a vegetation response that makes the NIR
    pattern differ from red's); ``band_misalignment_arcsec`` offsets each band's angles in the
    true camera.
    Rendering costs ~12 microseconds per pixel: a block is ~560 lines x 1504 samples per camera.
    """

    scenario: str = "pass"
    truth: str = "independent"
    jitter_arcsec: float = 1.0
    #: the independent truth's attitude spectrum: the slow process's band (s), the slope of its
    #: power per log-period against the period (0: equal power; 1: power growing with the period),
    #: discrete lines ``((period_s, amplitude_arcsec), ...)`` added to every angle with a random
    #: phase each; the jitter's band (s) and its own lines (reaction wheels, say)
    attitude_periods_s: tuple = (200.0, 2000.0)
    attitude_spectral_slope: float = 0.0
    attitude_lines: tuple = ()
    jitter_periods_s: tuple = (8.0, 120.0)
    jitter_lines: tuple = ()
    once_per_rev_m: float = 30.0
    subposting_relief_m: float = 3.0
    coast_ramp_m: float = 8000.0
    dem_correlated_fraction: float = 0.5
    camera_f_alpha_px: float = 0.05
    noise_tail_dof: float = 5.0
    mismatch_rate: float = 0.01
    mismatch_px: tuple = (1.0, 2.0)
    gcp_scene_fraction: float = 0.5
    seed: int = 0
    n_passes: int = 10
    repeat_indices: tuple = ()
    repeat_visibility: float = 0.8
    path: int = 37
    epoch_date: str = "2001-06-15"
    start_lat_deg: float = 72.0
    duration_s: float = 2700.0
    month_days: int = 30
    n_tie_points: int = 1000
    n_check_points: int = 100
    n_gcps: int = 120
    tie_sigma_px: float = 0.2
    gcp_sigma_px: float = 0.125
    tie_blunder_rate: float = 0.0
    gcp_blunder_rate: float = 0.05
    blunder_min_px: float = 3.0
    blunder_max_px: float = 10.0
    view_probability: float = 0.9
    texture_probability: float = 0.85
    swath_half_width_px: float = 550.0
    nav_sigma_m: float = 50.0
    along_drift_sigma_mps: float = 0.05
    drift_sigma_mps: float = 0.01
    ephemeris_segments: int = 1
    attitude_sigma_arcsec: tuple = (41.0 / 3, 44.0 / 3, 36.0 / 3)
    knot_spacing_s: tuple = (60.0, 60.0, 60.0)
    camera_misalignment_arcsec: float = 60.0
    camera_residual_px: float = 0.0625
    gcp_sigma_m: float = 30.0
    dem_tile_size: int = 32
    dted1_fraction: float = 0.6
    noise_free: bool = False
    with_chips: bool = False
    camera_truth: str = ""
    thermal_arcsec_per_c: float = 0.0
    thermal_focal_ppm_per_c: float = 0.0
    bands: tuple = ("red",)
    band_misalignment_arcsec: float = 0.0
    imagery: bool = False
    cloud_fraction: float = 0.0
    image_snr: float = 200.0
    search_px: int = 8
    roi_blocks: tuple = ()
    strip_cameras: tuple = ()
    strip_samples: tuple = ()
    roi_dem_sigma_m: float = 10.0
    feature_windows: bool = True
    #: files that misstate their accuracy: each error is drawn with this many times the sigma its
    #: file states (1: as stated). Tie-point and GCP image observations (the simulated ones; matched
    #: observations carry the matcher's own sigma), GCP positions, DEM heights
    tie_sigma_true_over_stated: float = 1.0
    gcp_pixel_sigma_true_over_stated: float = 1.0
    gcp_sigma_true_over_stated: float = 1.0
    dem_sigma_true_over_stated: float = 1.0
    #: the true camera over the years (every term off by default; both truths): per camera and
    #: pointing angle a drift ``((camera, angle, arcsec_per_year), ...)`` and an annual term
    #: ``((camera, angle, amplitude_arcsec), ...)`` (a sine of the days since
    #: ``camera_epoch_date`` over 365.25), both zero at ``camera_epoch_date`` (default:
    #: ``epoch_date``); steps ``((date, camera, angle, arcsec), ...)`` that hold from that date
    #: on. ``angle`` is delta, beta or epsilon; :func:`camera_change_arcsec` gives the sum. They
    #: change the instrument the scenario draws (or ``camera_truth`` gives); the supplied model
    #: (``camera_model.h5``) is drawn around that instrument before any change
    camera_drifts: tuple = ()
    camera_annual: tuple = ()
    camera_steps: tuple = ()
    camera_epoch_date: str = ""
    #: the lattice spacing (3-arcsec postings) of the DEM error's long-correlated share
    #: (``dem_correlated_fraction``); 300 postings is ~28 km, points two spacings apart are
    #: independent; it must divide the 432000 postings of 360 degrees
    dem_correlation_postings: int = 300

    def __post_init__(self) -> None:
        if not (self.dem_correlation_postings > 0 and 432000 % self.dem_correlation_postings == 0):
            raise InputError(
                "dem_correlation_postings", self.dem_correlation_postings, "a divisor of 432000 (postings), e.g. 300"
            )
        for name in ("attitude_periods_s", "jitter_periods_s"):
            v = getattr(self, name)
            if not (len(v) == 2 and 0 < float(v[0]) < float(v[1]) and np.isfinite(float(v[1]))):
                raise InputError(name, v, "two periods MIN, MAX in s with 0 < MIN < MAX")
        if not (np.isfinite(self.attitude_spectral_slope) and abs(self.attitude_spectral_slope) <= 4):
            raise InputError("attitude_spectral_slope", self.attitude_spectral_slope, "a slope from -4 to 4")
        for name in ("attitude_lines", "jitter_lines"):
            for line in getattr(self, name):
                if not (len(line) == 2 and float(line[0]) > 0 and float(line[1]) >= 0):
                    raise InputError(name, getattr(self, name), "pairs (period_s > 0, amplitude_arcsec >= 0)")
        for name in (
            "tie_sigma_true_over_stated",
            "gcp_pixel_sigma_true_over_stated",
            "gcp_sigma_true_over_stated",
            "dem_sigma_true_over_stated",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.1 <= v <= 10):
                raise InputError(name, v, "a factor from 0.1 to 10 (the true sigma over the stated one)")
        _check_camera_terms(self)
        if self.scenario not in ("pass", "month", "path"):
            raise InputError("scenario", self.scenario, ("pass", "month", "path"))
        if self.truth not in TRUTHS:
            raise InputError("truth", self.truth, TRUTHS)
        for name in ("jitter_arcsec", "once_per_rev_m", "subposting_relief_m", "camera_f_alpha_px"):
            if not getattr(self, name) >= 0:
                raise InputError(name, getattr(self, name), "a number >= 0 (1 sigma)")
        if not self.coast_ramp_m >= 0:
            raise InputError("coast_ramp_m", self.coast_ramp_m, "a distance >= 0 (m; 0: no ramp)")
        if not (self.noise_tail_dof == 0 or self.noise_tail_dof > 2):
            raise InputError(
                "noise_tail_dof", self.noise_tail_dof, "0 (Gaussian) or degrees of freedom > 2 (finite variance)"
            )
        if len(self.mismatch_px) != 2 or not 0 < self.mismatch_px[0] <= self.mismatch_px[1]:
            raise InputError("mismatch_px", self.mismatch_px, "(min, max) pixels, 0 < min <= max")
        if self.n_passes < 1:
            raise InputError("n_passes", self.n_passes, "an integer >= 1")
        if self.repeat_indices and (
            len(set(self.repeat_indices)) != len(self.repeat_indices)
            or any(not isinstance(k, int) or isinstance(k, bool) or k < 0 for k in self.repeat_indices)
        ):
            raise InputError(
                "repeat_indices", self.repeat_indices, "distinct integers >= 0 (repeat cycles after epoch_date)"
            )
        if not (1 <= self.path <= REPEAT_PATHS):
            raise InputError("path", self.path, f"an integer in 1..{REPEAT_PATHS}")
        for name in ("tie_sigma_px", "gcp_sigma_px", "nav_sigma_m", "gcp_sigma_m", "duration_s"):
            if getattr(self, name) <= 0:
                raise InputError(name, getattr(self, name), "a positive number")
        if not self.bands or len(set(self.bands)) != len(self.bands) or any(b not in BANDS for b in self.bands):
            raise InputError("bands", self.bands, f"distinct names from {', '.join(BANDS)}")
        if not self.band_misalignment_arcsec >= 0:
            raise InputError("band_misalignment_arcsec", self.band_misalignment_arcsec, "a number >= 0")
        for name in ("thermal_arcsec_per_c", "thermal_focal_ppm_per_c"):
            if not getattr(self, name) >= 0:
                raise InputError(name, getattr(self, name), "a number >= 0 (1 sigma of the per-camera slope)")
        for name in (
            "tie_blunder_rate",
            "gcp_blunder_rate",
            "view_probability",
            "texture_probability",
            "dted1_fraction",
            "dem_correlated_fraction",
            "mismatch_rate",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(name, getattr(self, name), "a fraction in [0, 1]")
        if not 0.0 <= self.gcp_scene_fraction < 1.0:
            raise InputError(
                "gcp_scene_fraction",
                self.gcp_scene_fraction,
                "a fraction in [0, 1) (each GCP keeps an error of its own)",
            )
        if not 0.0 <= self.cloud_fraction < 1.0:
            raise InputError("cloud_fraction", self.cloud_fraction, "a fraction in [0, 1)")
        if not self.image_snr > 0:
            raise InputError("image_snr", self.image_snr, "a positive signal-to-noise ratio")
        if not (isinstance(self.search_px, int) and 1 <= self.search_px <= 64):
            raise InputError("search_px", self.search_px, "an integer number of pixels in 1..64")
        if not self.feature_windows and not self.roi_blocks:
            raise InputError(
                "feature_windows", False, "True unless roi_blocks are rendered (the imagery would be empty)"
            )
        if self.roi_blocks:
            rb = self.roi_blocks
            if not self.imagery:
                raise InputError("roi_blocks", rb, "() unless imagery is rendered (--imagery)")
            if (
                len(rb) != 2
                or any(isinstance(b, bool) or not isinstance(b, int) for b in rb)
                or not 1 <= rb[0] <= rb[1] <= 180
            ):
                raise InputError("roi_blocks", rb, "(first, last) block numbers, 1 <= first <= last <= 180")
        if not self.roi_dem_sigma_m >= 0:
            raise InputError("roi_dem_sigma_m", self.roi_dem_sigma_m, "a number >= 0 (m, 1 sigma)")
        if any(c not in CAMERAS for c in self.strip_cameras) or len(set(self.strip_cameras)) != len(self.strip_cameras):
            raise InputError(
                "strip_cameras", self.strip_cameras, f"distinct names from {', '.join(CAMERAS)} (empty: all)"
            )
        if self.strip_samples and (
            len(self.strip_samples) != 2
            or self.strip_samples[0] < 0
            or self.strip_samples[1] < 16
            or self.strip_samples[0] + self.strip_samples[1] > N_PIXELS
        ):
            raise InputError(
                "strip_samples", self.strip_samples, f"(first sample, count): count >= 16, within 0..{N_PIXELS}"
            )
        if len(self.attitude_sigma_arcsec) != 3 or len(self.knot_spacing_s) != 3:
            raise InputError(
                "attitude_sigma_arcsec/knot_spacing_s",
                (self.attitude_sigma_arcsec, self.knot_spacing_s),
                "three values (roll, pitch, yaw)",
            )
        if self.n_tie_points < 0 or self.n_check_points < 0 or self.n_gcps < 5:
            raise InputError(
                "counts",
                (self.n_tie_points, self.n_check_points, self.n_gcps),
                "n_tie_points, n_check_points >= 0; n_gcps >= 5",
            )


# ---------------------------------------------------------------------------- truth draws
def draw_ephemeris_error(
    rng: np.random.Generator, cfg: ScenarioConfig, t_start: float, t_end: float
) -> EphemerisErrorModel:
    """Random eq. 19 model: b ~ N(0, nav_sigma_m), a ~ N(0, along/drift sigma) per segment
    (``truth="model"``); or, with ``truth="independent"``, an offset, a drift and a
    once-per-revolution term per axis, tabulated on 60 s segments (continuous)."""
    if cfg.truth == "independent":
        a_sig = np.array([cfg.along_drift_sigma_mps, cfg.drift_sigma_mps, cfg.drift_sigma_mps])
        b0 = rng.standard_normal(3) * cfg.nav_sigma_m
        a0 = rng.standard_normal(3) * a_sig
        amp = rng.standard_normal(3) * cfg.once_per_rev_m
        ph = rng.uniform(0, 2 * np.pi, 3)
        edges = np.r_[np.arange(t_start, t_end, 60.0), t_end]
        rel = edges - t_start
        e = b0 + np.outer(rel, a0) + amp * np.sin(2 * np.pi * np.outer(edges, np.ones(3)) / NODAL_PERIOD_S + ph)
        params = np.concatenate([np.diff(e, axis=0) / np.diff(edges)[:, None], e[:-1]], axis=1)
        return EphemerisErrorModel(edges, params)
    model = EphemerisErrorModel.zeros(t_start, t_end, cfg.ephemeris_segments)
    s = model.n_segments
    a_sig = np.array([cfg.along_drift_sigma_mps, cfg.drift_sigma_mps, cfg.drift_sigma_mps])
    model.params[:, :3] = rng.standard_normal((s, 3)) * a_sig
    model.params[:, 3:] = rng.standard_normal((s, 3)) * cfg.nav_sigma_m
    return model


def smooth_process(
    rng: np.random.Generator,
    sigma: float,
    n_terms: int = 6,
    periods_s: tuple[float, float] = (200.0, 2000.0),
    slope: float = 0.0,
    lines: tuple = (),
) -> Callable[[Array], tuple[Array, Array]]:
    """A zero-mean random sum of sinusoids (periods log-uniform in ``periods_s``, power per
    log-period proportional to ``period**slope``) with standard deviation ``sigma``, plus the
    discrete ``lines`` (``(period_s, amplitude)`` pairs, amplitude in the units of ``sigma``, a
    random phase each); returns ``f(t) -> (value, rate)``."""
    period = np.exp(rng.uniform(np.log(periods_s[0]), np.log(periods_s[1]), n_terms))
    w = 2 * np.pi / period
    ph = rng.uniform(0, 2 * np.pi, n_terms)
    amp = rng.rayleigh(1.0, n_terms)
    if slope:
        amp = amp * (period / periods_s[0]) ** (slope / 2.0)
    amp *= sigma / np.sqrt(np.sum(amp**2) / 2)
    if len(lines):
        line_p = np.array([float(p) for p, _ in lines])
        w = np.r_[w, 2 * np.pi / line_p]
        ph = np.r_[ph, rng.uniform(0, 2 * np.pi, line_p.size)]
        amp = np.r_[amp, [float(a) for _, a in lines]]
    return lambda t: (
        np.sum(amp * np.sin(np.multiply.outer(t, w) + ph), -1),
        np.sum(amp * w * np.cos(np.multiply.outer(t, w) + ph), -1),
    )


def draw_attitude_error(
    rng: np.random.Generator, cfg: ScenarioConfig, t_start: float, t_end: float
) -> AttitudeErrorModel:
    """Random attitude error spline: knots (value, rate) on the estimator's knot grid drawn from the
    estimator's own process prior (``truth="model"``, :func:`sample_process_knots`), or
    :func:`smooth_process` plus jitter on a 2 s grid the estimator does not share
    (``truth="independent"``)."""
    kt, kv = [], []
    if cfg.truth == "independent":
        times = np.arange(t_start, t_end + 2.0, 2.0)
        for a in range(3):
            slow = smooth_process(
                rng,
                cfg.attitude_sigma_arcsec[a] * ARCSEC,
                periods_s=tuple(cfg.attitude_periods_s),
                slope=cfg.attitude_spectral_slope,
                lines=tuple((p, amp * ARCSEC) for p, amp in cfg.attitude_lines),
            )
            fast = smooth_process(
                rng,
                cfg.jitter_arcsec * ARCSEC,
                n_terms=12,
                periods_s=tuple(cfg.jitter_periods_s),
                lines=tuple((p, amp * ARCSEC) for p, amp in cfg.jitter_lines),
            )
            (v1, r1), (v2, r2) = slow(times), fast(times)
            kt.append(times.copy())
            kv.append(np.stack([v1 + v2, r1 + r2], -1))
        return AttitudeErrorModel(kt, kv)
    for a in range(3):
        times = uniform_knots(t_start, t_end, cfg.knot_spacing_s[a])
        kt.append(times)
        kv.append(sample_process_knots(rng, times, cfg.attitude_sigma_arcsec[a] * ARCSEC))
    return AttitudeErrorModel(kt, kv)


def sample_process_knots(rng: np.random.Generator, times: Array, sigma: float) -> Array:
    """Knots ``(value, rate)`` ``(N, 2)`` at ``times`` drawn from the estimator's own attitude
    process prior (:func:`factors.priors.process_prior_factors`, rate factor
    :data:`~misrgraph.model.errormodels.ATTITUDE_RATE_FACTOR`, damping
    :data:`~misrgraph.model.errormodels.ATTITUDE_DAMPING`): the ``truth="model"`` draw."""
    lam = ATTITUDE_RATE_FACTOR
    x = np.empty((times.size, 2))
    x[0] = rng.standard_normal(2) * [sigma, lam * sigma]
    for k, dt in enumerate(np.diff(times)):
        phi, q = process_transition(float(dt), sigma, lam, ATTITUDE_DAMPING)
        x[k + 1] = phi @ x[k] + np.linalg.cholesky(q) @ rng.standard_normal(2)
    return x


#: Temperature (deg C) at which the simulator's thermal truth equals the drawn misaligned camera
#: (Table 1's pre-flight models are at 5 C); the table spans THERMAL_RANGE_C.
THERMAL_REFERENCE_C = 5.0
THERMAL_RANGE_C = (-10.0, 20.0)


_POINTING = ("delta", "beta", "epsilon")


def _iso_date(field: str, value: Any) -> _dt.date:
    try:
        return _dt.date.fromisoformat(str(value)[:10])
    except ValueError:
        raise InputError(field, value, "a date YYYY-MM-DD") from None


def _check_camera_terms(cfg: "ScenarioConfig") -> None:
    """Refuse a malformed drift, annual term or step of the true camera (one line, the field)."""
    for name in ("camera_drifts", "camera_annual"):
        for term in getattr(cfg, name):
            ok = (
                len(term) == 3
                and term[0] in CAMERAS
                and term[1] in _POINTING
                and isinstance(term[2], (int, float))
                and np.isfinite(float(term[2]))
            )
            if not ok:
                raise InputError(
                    name, list(term), "(camera, delta|beta|epsilon, arcsec) with a camera of " + ", ".join(CAMERAS)
                )
    for term in cfg.camera_steps:
        ok = len(term) == 4 and term[1] in CAMERAS and term[2] in _POINTING and isinstance(term[3], (int, float))
        if not ok or not np.isfinite(float(term[3])):
            raise InputError("camera_steps", list(term), "(YYYY-MM-DD, camera, delta|beta|epsilon, arcsec)")
        _iso_date("camera_steps", term[0])
    if cfg.camera_epoch_date:
        _iso_date("camera_epoch_date", cfg.camera_epoch_date)


def camera_change_arcsec(cfg: "ScenarioConfig", date: str | _dt.date) -> dict[tuple[str, str], float]:
    """The true camera's change (arcsec) on ``date`` from the instrument before any change, per
    ``(camera, angle)`` with a term: drift x years + annual amplitude x sin(2 pi days / 365.25)
    (days since ``camera_epoch_date``, default ``epoch_date``) + the steps dated on or before it.
    ``camera_truth.h5`` holds the camera on ``camera_epoch_date``: the difference of a pass's
    true camera from it is this on the pass's date less this on that date."""
    day = _iso_date("date", date)
    epoch = _iso_date("camera_epoch_date", cfg.camera_epoch_date or cfg.epoch_date)
    days = float((day - epoch).days)
    out: dict[tuple[str, str], float] = {}
    for cam, ang, rate in cfg.camera_drifts:
        out[(cam, ang)] = out.get((cam, ang), 0.0) + float(rate) * days / 365.25
    for cam, ang, amp in cfg.camera_annual:
        out[(cam, ang)] = out.get((cam, ang), 0.0) + float(amp) * float(np.sin(2 * np.pi * days / 365.25))
    for when, cam, ang, size in cfg.camera_steps:
        if _iso_date("camera_steps", when) <= day:
            out[(cam, ang)] = out.get((cam, ang), 0.0) + float(size)
    return out


def camera_truth_on(cfg: "ScenarioConfig", model: CameraModel, date: str | _dt.date) -> CameraModel:
    """``model`` (the instrument before any change, at a pass's temperature) as it is on
    ``date``: :func:`camera_change_arcsec` added to its angles (``model`` itself when nothing
    changes)."""
    change = camera_change_arcsec(cfg, date)
    if not change:
        return model
    m = model.copy()
    for (cam, ang), arcsec in change.items():
        m.add_correction(ang, CAMERAS.index(cam), None, arcsec * ARCSEC)
    return m


def _truth_on_epoch(
    cfg: "ScenarioConfig", model: CameraModel | TabulatedCameraModel
) -> CameraModel | TabulatedCameraModel:
    """The true camera on ``camera_epoch_date`` (``camera_truth.h5``): with the steps dated on or
    before it (the drift and annual term are zero there)."""
    day = cfg.camera_epoch_date or cfg.epoch_date
    if isinstance(model, TabulatedCameraModel):
        return TabulatedCameraModel([camera_truth_on(cfg, m, day) for m in model.models], model.valid_range_c)
    return camera_truth_on(cfg, model, day)


def draw_thermal_truth(
    rng: np.random.Generator, base: CameraModel, angle_sigma_rad: float, focal_sigma: float
) -> TabulatedCameraModel:
    """A true camera linear in temperature around ``base`` (at :data:`THERMAL_REFERENCE_C`).

    Per camera: slopes of delta and beta ~ N(0, angle_sigma_rad) rad/C and a focal scale slope
    ~ N(0, focal_sigma) 1/C (f grows, the focal-plane polynomial ``f alpha_i`` stays: the
    cross-track field angle per pixel shrinks). Tabulated over :data:`THERMAL_RANGE_C`.
    """
    nc = len(CAMERAS)
    slopes = {
        "delta": rng.standard_normal(nc) * angle_sigma_rad,
        "beta": rng.standard_normal(nc) * angle_sigma_rad,
        "focal_scale": rng.standard_normal(nc) * focal_sigma,
    }
    base = base.copy()
    base.temperature_c = THERMAL_REFERENCE_C
    table = TabulatedCameraModel.linear(base, slopes, THERMAL_RANGE_C)
    for m in table.models:
        m.provenance = dict(base.provenance, thermal="linear in temperature (simulator truth)")
    return table


def _offset_table(
    truth: TabulatedCameraModel, truth_ref: CameraModel, supplied_ref: CameraModel
) -> TabulatedCameraModel:
    """``truth`` with the difference ``supplied_ref - truth_ref`` added at every temperature."""
    models = []
    for m in truth.models:
        o = m.copy()
        for name in CameraModel._SHAPES:
            setattr(o, name, getattr(m, name) + getattr(supplied_ref, name) - getattr(truth_ref, name))
        o.provenance = dict(supplied_ref.provenance)
        models.append(o)
    return TabulatedCameraModel(models, truth.valid_range_c)


def draw_camera_misalignment(rng: np.random.Generator, nominal: CameraModel, sigma_rad: Array | float) -> CameraModel:
    """Copy of ``nominal`` with delta, beta, epsilon of every camera perturbed by N(0, sigma)."""
    m = nominal.copy()
    sig = np.broadcast_to(np.asarray(sigma_rad, dtype=float), (len(CAMERAS),))
    for name in ("delta", "beta", "epsilon"):
        getattr(m, name)[:] += rng.standard_normal(len(CAMERAS)) * sig
    return m


def _true_attitude(t: Array) -> tuple[Array, Array]:
    """Actual spacecraft pointing relative to the orbital frame: a few-arcsec slow wobble."""
    w = 2 * np.pi / np.array([1500.0, 1100.0, 1800.0])
    amp = np.array([3.0, 4.0, 5.0]) * ARCSEC
    return amp * np.sin(w * t[:, None]), amp * w * np.cos(w * t[:, None])


def matching_noise(rng: np.random.Generator, n: int, dof: float) -> Array:
    """``n`` unit-variance matching errors: Gaussian (``dof == 0``) or Student-t with ``dof`` > 2
    degrees of freedom scaled by ``sqrt((dof - 2) / dof)`` (heavier tails, same variance)."""
    if dof == 0:
        return rng.standard_normal(n)
    return rng.standard_t(dof, n) * np.sqrt((dof - 2.0) / dof)


def perturb_focal_plane(rng: np.random.Generator, camera: CameraModel, px: float) -> CameraModel:
    """Copy of ``camera`` with f and the field-angle polynomial's alpha_2, alpha_3 perturbed per
    camera (all bands alike) so that each moves a pixel at the swath edge (|s - c_y| = 752) by
    N(0, ``px``) pixels: ``df / f ~ N(0, px / 752)``, ``d alpha_i ~ N(0, px alpha_1 / 752^i)``."""
    m = camera.copy()
    m.focal_length *= 1.0 + (rng.standard_normal(len(CAMERAS)) * px / 752.0)[:, None]
    return perturb_field_angles(rng, m, px)


def perturb_field_angles(rng: np.random.Generator, camera: CameraModel, px: float) -> CameraModel:
    """Copy of ``camera`` with the field-angle polynomial's alpha_2, alpha_3 perturbed per camera
    (all bands alike): ``d alpha_i ~ N(0, px alpha_1 / 752^i)`` moves a pixel at the swath edge
    (|s - c_y| = 752) by N(0, ``px``) pixels each -- the a-priori 1 sigma the pass adjustment
    gives them (:func:`misrgraph.estimate.graph.calibrated_camera_sigma`)."""
    m = camera.copy()
    nc = len(CAMERAS)
    for i in (2, 3):
        m.alpha[:, :, i] += rng.standard_normal(nc)[:, None] * px * m.alpha[:, :, 1] / 752.0**i
    return m


# ---------------------------------------------------------------------------- one pass
@dataclass
class _Landmark:
    ecef: Array
    kind: int
    ident: int
    gcp_index: int


def _observe(
    geo: PassGeometry,
    rng: np.random.Generator,
    cfg: ScenarioConfig,
    ecef: Array,
    kinds: NDArray[np.int64],
    first_row: int,
) -> tuple[list[Array], NDArray[np.bool_]]:
    """Measure landmarks in all cameras, in each of ``cfg.bands``: the continuous image position
    (line = time index of the array-centre crossing, sample there; exposure NaN) a matcher reports.
    Visibility (and dropout) is decided per camera on the red band; every band measures what its
    camera sees. Returns observation columns and keep-mask."""
    cols: list[list[Array]] = [[] for _ in range(7)]
    cams_seen = np.zeros(len(ecef), dtype=int)
    per_cam = []
    for c in range(len(CAMERAS)):
        ln, sm, vis, _, _ = geo.ground_to_pixel(c, RED, ecef, continuous=True)
        dropout = rng.random(len(ecef)) >= cfg.view_probability
        vis = vis & ~(dropout & (kinds == KIND_TIE))
        per_cam.append((c, ln, sm, vis))
        cams_seen += vis
    keep = np.where(kinds == KIND_TIE, cams_seen >= 3, cams_seen >= 1)
    for c, ln, sm, vis in per_cam:
        sel = np.flatnonzero(vis & keep)
        for b in (BANDS.index(name) for name in cfg.bands):
            if b == RED:
                s_b, ln_b, sm_b = sel, ln[sel], sm[sel]
            else:
                ip = geo.ground_to_pixel(c, b, ecef[sel], continuous=True)
                ok = ip.visible
                s_b, ln_b, sm_b = sel[ok], ip.line[ok], ip.sample[ok]
            cols[0].append(s_b)
            cols[1].append(np.full(s_b.size, c))
            cols[2].append(np.full(s_b.size, b))
            cols[3].append(ln_b)
            cols[4].append(sm_b)
            cols[5].append(np.full(s_b.size, np.nan))  # continuous positions (a matcher's measurement)
            cols[6].append(np.where(kinds[s_b] == KIND_GCP, cfg.gcp_sigma_px, cfg.tie_sigma_px))
    return [np.concatenate(c) for c in cols], keep


def simulate_pass(
    rng: np.random.Generator,
    cfg: ScenarioConfig,
    eph: Ephemeris,
    camera_truth: CameraModel,
    terrain: SyntheticTerrain,
    geoid: Geoid,
    gcps: GcpDatabase,
    gcp_truth_ecef: Array | None,
    pass_id: str,
    path: int,
    orbit: int,
    n_tie: int,
    n_check: int,
    temperature_c: float = 5.0,
    features: list[_Landmark] | None = None,
    feature_fraction: float = 1.0,
) -> tuple[OrbitPass, PassTruth]:
    """Simulate one pass: navigation errors, landmarks, observations with noise and blunders; returns
    the pass (what the estimator sees) and its truth.

    With ``features`` (tie/check points of an earlier pass of the same path) no new features are
    drawn: each given feature is kept with probability ``feature_fraction`` (clouds) and keeps
    its id, so repeat passes observe the same ground points.
    """
    t_lo, t_hi = eph.span
    ang, rate = _true_attitude(eph.t)
    e_att = draw_attitude_error(rng, cfg, t_lo, t_hi)
    e_eph = draw_ephemeris_error(rng, cfg, t_lo, t_hi)
    att_meas = AttitudeSeries(eph.t, ang + e_att.evaluate(eph.t), rate + e_att.rate(eph.t))
    t0 = np.full((len(CAMERAS), len(BANDS)), t_lo)
    geo = PassGeometry(
        eph,
        att_meas,
        camera_truth,
        t0=t0,
        attitude_delta=lambda t: -e_att.evaluate(t),
        position_delta=lambda t: -e_eph.evaluate(t),
    )

    def surface(la, lo):
        return terrain.height(la, lo) + geoid.undulation(la, lo)

    lms: list[_Landmark] = []
    # GCPs seen by the nadir camera during the pass
    if len(gcps) and gcp_truth_ecef is not None:
        _, _, vis, _, _ = geo.ground_to_pixel(CAMERAS.index("An"), RED, gcp_truth_ecef)
        for gi in np.flatnonzero(vis):
            lms.append(_Landmark(gcp_truth_ecef[gi], KIND_GCP, int(gcps.id[gi]), int(gi)))
    # tie and check points over textured land, inside the common swath
    an = CAMERAS.index("An")
    n_lines = geo.lines_in_pass(an, RED)
    if features is not None:
        lms += [f for f in features if rng.random() < feature_fraction]
        n_tie = n_check = 0
    for kind, count in ((KIND_TIE, n_tie), (KIND_CHECK, n_check)):
        got, tries = 0, 0
        while got < count and tries < 30:
            tries += 1
            m = max(4 * (count - got), 64)
            line = np.floor(rng.uniform(0.0, 1.0, m) * n_lines)
            samp = 751.5 + rng.uniform(-cfg.swath_half_width_px, cfg.swath_half_width_px, m)
            g = geo.pixel_to_ground(an, RED, line, samp)
            lat, lon, _ = ecef_to_geodetic(g)
            ok = land_mask(lat, lon) & (rng.random(m) < cfg.texture_probability) & (np.abs(lat) < 80)
            if not ok.any():
                continue
            g = geo.pixel_to_ground(an, RED, line[ok], samp[ok], surface=surface)
            take = min(count - got, len(g))
            for p in g[:take]:
                lms.append(_Landmark(p, kind, 1 + max((lm.ident for lm in lms if lm.kind != KIND_GCP), default=-1), -1))
            got += take
    if not lms:
        ecef = np.zeros((0, 3))
        kinds = np.zeros(0, np.int64)
    else:
        ecef = np.stack([lm.ecef for lm in lms])
        kinds = np.array([lm.kind for lm in lms], np.int64)
    cols, keep = _observe(geo, rng, cfg, ecef, kinds, 0)
    # renumber the kept landmarks
    new_index = -np.ones(len(lms), np.int64)
    new_index[keep] = np.arange(int(keep.sum()))
    kept = [lm for lm, k in zip(lms, keep) if k]
    obs_lm = new_index[cols[0].astype(np.int64)]
    n_obs = obs_lm.size
    line, sample = cols[3].copy(), cols[4].copy()
    sigma = cols[6]
    independent = cfg.truth == "independent"
    if not cfg.noise_free:
        true_sigma = sigma
        if cfg.tie_sigma_true_over_stated != 1.0 or cfg.gcp_pixel_sigma_true_over_stated != 1.0:
            kinds_o = kinds[cols[0].astype(np.int64)]
            true_sigma = sigma * np.select(
                [kinds_o == KIND_GCP, kinds_o == KIND_TIE],
                [cfg.gcp_pixel_sigma_true_over_stated, cfg.tie_sigma_true_over_stated],
                1.0,
            )
        line += matching_noise(rng, n_obs, cfg.noise_tail_dof if independent else 0.0) * true_sigma
        sample += matching_noise(rng, n_obs, cfg.noise_tail_dof if independent else 0.0) * true_sigma
    kind_obs = np.array([kept[i].kind for i in obs_lm], np.int64) if n_obs else np.zeros(0, np.int64)
    rate = np.where(kind_obs == KIND_GCP, cfg.gcp_blunder_rate, cfg.tie_blunder_rate)
    blunder = (rng.random(n_obs) < rate) & (kind_obs != KIND_CHECK) & (not cfg.noise_free)
    nb = int(blunder.sum())
    if nb:
        mag = rng.uniform(cfg.blunder_min_px, cfg.blunder_max_px, nb)
        ang_b = rng.uniform(0, 2 * np.pi, nb)
        line[blunder] += mag * np.cos(ang_b)
        sample[blunder] += mag * np.sin(ang_b)
    if independent and cfg.mismatch_rate > 0 and not cfg.noise_free:
        # small mismatches (a neighbouring feature, a cloud edge): 1-2 px, i.e. 5-15 sigma
        mis = (rng.random(n_obs) < cfg.mismatch_rate) & (kind_obs != KIND_CHECK) & ~blunder
        nm = int(mis.sum())
        mag = rng.uniform(cfg.mismatch_px[0], cfg.mismatch_px[1], nm)
        ang_m = rng.uniform(0, 2 * np.pi, nm)
        line[mis] += mag * np.cos(ang_m)
        sample[mis] += mag * np.sin(ang_m)
        blunder = blunder | mis
    # a matcher measures inside the pass only: a point whose noise, blunder or mismatch moved it
    # before the first or after the last line of the pass's navigation is not measured
    t_obs = t0[cols[1].astype(np.int64), cols[2].astype(np.int64)] + line * camera_truth.line_time
    inside = (t_obs >= eph.span[0]) & (t_obs <= eph.span[1])
    if not inside.all():
        obs_lm, line, sample, sigma, blunder = (
            obs_lm[inside],
            line[inside],
            sample[inside],
            sigma[inside],
            blunder[inside],
        )
        cols = [c[inside] for c in cols]
    landmarks = Landmarks(
        np.array([lm.ident for lm in kept], np.int64),
        np.array([lm.kind for lm in kept], np.int64),
        np.array([lm.gcp_index for lm in kept], np.int64),
    )
    obs = Observations(obs_lm, cols[1], cols[2], line, sample, cols[5], sigma)
    truth = PassTruth(
        e_eph, e_att, np.stack([lm.ecef for lm in kept]) if kept else np.zeros((0, 3)), blunder, camera_truth
    )
    return OrbitPass(
        pass_id, path, orbit, eph, att_meas, t0, camera_truth.line_time, landmarks, obs, temperature_c
    ), truth


# ---------------------------------------------------------------------------- scenarios
def _month_passes(cfg: ScenarioConfig, gcps: GcpDatabase) -> list[tuple[int, int, str, float, float]]:
    """(orbit, path, date, start_lat, duration) of the daylight passes whose swath covers a GCP."""
    ref_path = cfg.path
    ref = terra_like_orbit(
        epoch_date=cfg.epoch_date, path=ref_path, start_lat_deg=80.0, duration_s=2950.0, step_s=8.192
    )
    geo = PassGeometry(ref, AttitudeSeries.zeros(ref.t), nominal_camera_model())
    nav = geo.nav_state(ref.t)
    track = np.einsum("nij,nj->ni", nav.eci_to_ecef, nav.position)
    tlat, tlon, _ = ecef_to_geodetic(track)
    tlon_rel = np.unwrap(np.radians(tlon)) - np.radians(path_node_longitude(ref_path))
    out: dict[int, list[float]] = {}
    orbits_per_day = 86400.0 / NODAL_PERIOD_S
    n_orbits = int(cfg.month_days * orbits_per_day)
    glat, glon = np.radians(gcps.lat), np.radians(gcps.lon)
    for j in range(n_orbits):
        path = (ref_path - 1 + 16 * j) % REPEAT_PATHS + 1
        lon_track = tlon_rel + np.radians(path_node_longitude(path))
        # great-circle distance from each GCP to the ground track samples
        d = np.arccos(
            np.clip(
                np.sin(glat[:, None]) * np.sin(np.radians(tlat))[None, :]
                + np.cos(glat[:, None])
                * np.cos(np.radians(tlat))[None, :]
                * np.cos(glon[:, None] - lon_track[None, :]),
                -1,
                1,
            )
        )
        dmin = d.min(axis=1) * 6371e3
        seen = np.flatnonzero(dmin < 150e3)
        if seen.size:
            lat_seen = gcps.lat[seen]
            out[j] = [path, float(lat_seen.max()), float(lat_seen.min())]
    passes = []
    d0 = _dt.date.fromisoformat(cfg.epoch_date)
    for j, (path, lat_max, lat_min) in out.items():
        day = d0 + _dt.timedelta(days=int(j / orbits_per_day))
        start = min(lat_max + 16.0, 81.0)
        # ~112 km of latitude per ~16.5 s at ~6.8 km/s ground speed; include Da's delay (~230 s)
        duration = (start - lat_min) * 111e3 / 6.75e3 + 520.0
        passes.append((j, int(path), day.isoformat(), start, min(duration, 2900.0)))
    return passes


@dataclass
class Scenario:
    """A loaded scenario directory (see :func:`run_simulate`)."""

    directory: Path
    config: dict[str, Any]
    camera_model: "CameraModel | TabulatedCameraModel"
    camera_truth: "CameraModel | TabulatedCameraModel | None"
    gcps: GcpDatabase
    dem: DemTiles
    pass_files: list[Path]

    def load_pass(self, i: int) -> OrbitPass:
        """Pass ``i`` as the estimator sees it (no truth)."""
        return OrbitPass.load(self.pass_files[i])

    def load_truth(self, i: int) -> PassTruth:
        """The simulator's truth of pass ``i``."""
        t = read_pass_truth(self.pass_files[i])
        if t is None:
            raise FileFormatError(self.pass_files[i], "no /truth group (not a simulated pass)")
        return t

    def gcp_truth(self) -> Array:
        """True GCP positions ``(G, 3)`` m ECEF."""
        t = read_gcp_truth(self.directory / "gcp.h5")
        if t is None:
            raise FileFormatError(self.directory / "gcp.h5", "no /truth group (not a simulated database)")
        return t


def load_scenario(directory: str | os.PathLike[str]) -> Scenario:
    """Load a directory written by :func:`run_simulate`, validating every file."""

    d = Path(directory)
    meta = d / "scenario.json"
    if not meta.exists():
        raise FileFormatError(d, "not a scenario directory (no scenario.json); create one with 'misrgraph simulate'")
    try:
        config = json.loads(meta.read_text())
    except json.JSONDecodeError as exc:
        raise FileFormatError(meta, f"invalid JSON: {exc.msg} at line {exc.lineno}") from exc
    truth_path = d / "camera_truth.h5"
    passes = sorted((d / "passes").glob("*.h5"))
    if not passes:
        raise FileFormatError(d / "passes", "no pass files (*.h5)")
    return Scenario(
        d,
        config,
        load_camera_model(d / "camera_model.h5"),
        load_camera_model(truth_path) if truth_path.exists() else None,
        read_gcp_database(d / "gcp.h5"),
        read_dem(d / "dem.h5"),
        passes,
    )


def scenario_terrain(cfg: ScenarioConfig | Mapping[str, Any]) -> SyntheticTerrain:
    """The true terrain of a scenario: its seed; sub-posting relief only under the independent
    truth; the coast ramp. ``cfg`` is a :class:`ScenarioConfig` or the ``config`` of a scenario's
    ``scenario.json``, where a missing ``coast_ramp_m`` (a scenario simulated before it existed)
    is 0, the world that scenario was simulated in."""
    get = cfg.get if isinstance(cfg, Mapping) else (lambda k, d: getattr(cfg, k))
    truth = str(get("truth", "model"))
    return SyntheticTerrain(
        seed=int(get("seed", 0)),
        fine_relief_m=float(get("subposting_relief_m", 0.0)) if truth == "independent" else 0.0,
        coast_ramp_m=float(get("coast_ramp_m", 0.0)),
    )


def _scenario_rng(seed: int) -> np.random.Generator:
    """The scenario's main generator: every draw of :func:`run_simulate` not given a stream of its
    own comes from it, in order (:data:`PAIRED_SOURCES` is checked against its final state)."""
    return np.random.default_rng(seed)


def run_simulate(cfg: ScenarioConfig, out: str | os.PathLike[str], progress: Progress | None = None) -> dict[str, Any]:
    """Simulate a scenario into directory ``out`` (written atomically: a temporary sibling
    directory renamed into place). Returns a summary dict (also saved as scenario.json)."""
    out_dir = Path(out)
    check_writable(out_dir, "out")
    _check_replaceable(out_dir)
    rng = _scenario_rng(cfg.seed)
    independent = cfg.truth == "independent"
    terrain = scenario_terrain(cfg)
    geoid = Geoid("zero")
    nominal = nominal_camera_model()
    gcps, gcp_truth = generate_gcp_database(
        rng,
        terrain,
        cfg.n_gcps,
        cfg.gcp_sigma_m,
        geoid,
        cfg.with_chips,
        scene_fraction=cfg.gcp_scene_fraction if independent else None,
        true_over_stated=cfg.gcp_sigma_true_over_stated,
    )
    truth_cam = draw_camera_misalignment(rng, nominal, cfg.camera_misalignment_arcsec * ARCSEC)
    if independent and cfg.camera_f_alpha_px > 0:
        truth_cam = perturb_focal_plane(rng, truth_cam, cfg.camera_f_alpha_px)
    elif cfg.scenario == "month" and cfg.camera_f_alpha_px > 0:
        # the model truth of a month: alpha_2, alpha_3 off the pre-flight values by the
        # calibration's own prior (CalibrateConfig.focal_prior_px), from a stream of their own
        truth_cam = perturb_field_angles(
            np.random.default_rng([cfg.seed, MODEL_ALPHA_STREAM]), truth_cam, cfg.camera_f_alpha_px
        )
    truth_cam.provenance = {"source": "simulator truth", "seed": str(cfg.seed)}
    truth_model: CameraModel | TabulatedCameraModel = truth_cam
    if cfg.thermal_arcsec_per_c > 0 or cfg.thermal_focal_ppm_per_c > 0:
        truth_model = draw_thermal_truth(
            rng, truth_cam, cfg.thermal_arcsec_per_c * ARCSEC, cfg.thermal_focal_ppm_per_c * 1e-6
        )
    if cfg.band_misalignment_arcsec > 0:
        offsets = rng.standard_normal((3, len(CAMERAS), len(BANDS))) * cfg.band_misalignment_arcsec * ARCSEC
        for m in [truth_cam] if truth_model is truth_cam else [truth_cam, *truth_model.models]:  # type: ignore[union-attr]
            for name, off in zip(("band_delta", "band_beta", "band_epsilon"), offsets):
                getattr(m, name)[:] += off
    if cfg.camera_truth:
        # the same instrument as another scenario (e.g. the month a calibration came from)
        truth_model = load_camera_model(cfg.camera_truth)
        truth_cam = truth_model.at_temperature(THERMAL_REFERENCE_C)
    if cfg.scenario == "month":
        supplied = nominal.copy()
        supplied.provenance = {"source": "pre-flight nominal model (misrgraph.model.nominal)"}
        plan = _month_passes(cfg, gcps)
        n_tie, n_check = 0, 0
    else:
        ifov = np.array([nominal.ifov_cross_rad(c, RED, 751.5) for c in range(len(CAMERAS))])
        supplied = draw_camera_misalignment(rng, truth_cam, ifov * cfg.camera_residual_px)
        if independent:  # a calibration of delta, beta, epsilon keeps the pre-flight f and alpha
            supplied.focal_length[:] = nominal.focal_length
            supplied.alpha[:] = nominal.alpha
        elif cfg.camera_f_alpha_px > 0:
            # the model truth: the supplied alpha_2, alpha_3 off by the adjustment's own prior (f
            # exact, as the adjustment holds it); drawn from a stream of their own so that every
            # other draw of the scenario stays as it was
            supplied = perturb_field_angles(
                np.random.default_rng([cfg.seed, MODEL_ALPHA_STREAM]), supplied, cfg.camera_f_alpha_px
            )
        supplied.provenance = {
            "source": "calibrated model (truth + residual error)",
            "residual_px": str(cfg.camera_residual_px),
        }
        if isinstance(truth_model, TabulatedCameraModel):
            # a calibrated thermal table: the same residual error at every temperature
            supplied = _offset_table(truth_model, truth_cam, supplied)
        n_tie, n_check = cfg.n_tie_points, cfg.n_check_points
        if cfg.scenario == "path":
            d0 = _dt.date.fromisoformat(cfg.epoch_date)
            cycles = sorted(cfg.repeat_indices) if cfg.repeat_indices else range(cfg.n_passes)
            plan = [
                (233 * k, cfg.path, (d0 + _dt.timedelta(days=16 * k)).isoformat(), cfg.start_lat_deg, cfg.duration_s)
                for k in cycles
            ]
        else:
            plan = [(0, cfg.path, cfg.epoch_date, cfg.start_lat_deg, cfg.duration_s)]
    tmp = make_temp_dir(f".{out_dir.name}.", out_dir.parent)
    try:
        (tmp / "passes").mkdir()
        all_lm = []
        n_obs = 0
        seen_count = np.zeros(len(gcps), int)
        summaries = []
        path_features: list[_Landmark] | None = None
        for k, (orbit, path, date, start_lat, duration) in enumerate(plan):
            if progress:
                progress(f"pass {k + 1}/{len(plan)}", k, len(plan))
            eph = terra_like_orbit(epoch_date=date, path=path, start_lat_deg=start_lat, duration_s=duration)
            temp = 5.0 + 3.0 * np.sin(2 * np.pi * orbit / 437.0) + 0.5 * rng.standard_normal()
            p, p_truth = simulate_pass(
                rng,
                cfg,
                eph,
                camera_truth_on(cfg, truth_model.at_temperature(float(temp)), date),
                terrain,
                geoid,
                gcps,
                gcp_truth,
                f"P{path:03d}_O{orbit:04d}",
                path,
                orbit,
                n_tie,
                n_check,
                float(temp),
                features=path_features,
                feature_fraction=cfg.repeat_visibility if path_features is not None else 1.0,
            )
            if cfg.scenario == "path" and path_features is None:
                path_features = [
                    _Landmark(p_truth.landmark_ecef[i], int(p.landmarks.kind[i]), int(p.landmarks.id[i]), -1)
                    for i in range(len(p.landmarks))
                    if p.landmarks.kind[i] != KIND_GCP
                ]
            if cfg.scenario == "month" and not np.any(p.landmarks.kind == KIND_GCP):
                continue
            imagery = None
            if cfg.imagery:
                if progress:
                    progress(f"pass {k + 1}/{len(plan)}: imagery", k, len(plan))
                imagery = _render_imagery(cfg, p, p_truth, supplied, terrain, geoid, k, progress)
            save_pass_with_truth(p, p_truth, tmp / "passes" / f"{p.pass_id}.h5", imagery=imagery)
            gi = p.landmarks.gcp_index[p.landmarks.kind == KIND_GCP]
            seen_count[gi] += 1
            n_obs += len(p.observations)
            all_lm.append(p_truth.landmark_ecef)
            summaries.append(
                {
                    "pass_id": p.pass_id,
                    "observations": len(p.observations),
                    "tie_points": int(np.sum(p.landmarks.kind == KIND_TIE)),
                    "gcps": int(np.sum(p.landmarks.kind == KIND_GCP)),
                    "check_points": int(np.sum(p.landmarks.kind == KIND_CHECK)),
                }
            )
        if progress:
            progress("DEM tiles", len(plan), len(plan))
        lm = np.concatenate(all_lm + [gcp_truth])
        lat, lon, _ = ecef_to_geodetic(lm)
        save_dem(
            simulate_dem_tiles(
                lat,
                lon,
                terrain,
                rng,
                cfg.dem_tile_size,
                cfg.dted1_fraction,
                pad=IMAGERY_DEM_PAD if cfg.imagery else 8,
                correlated_fraction=cfg.dem_correlated_fraction if independent else 0.0,
                true_over_stated=cfg.dem_sigma_true_over_stated,
                correlation_postings=cfg.dem_correlation_postings,
            ),
            tmp / "dem.h5",
        )
        if cfg.roi_blocks:  # the heights the ROI is orthorectified with, on the path's 275 m SOM grid,
            # one block more each side: terrain there can hide the blocks' ends from the oblique cameras
            from misrgraph.io.dem import save_som_dem
            from misrgraph.misr.som import N_BLOCKS
            from misrgraph.sim.terrain import simulate_som_dem

            padded = (max(1, cfg.roi_blocks[0] - 1), min(N_BLOCKS, cfg.roi_blocks[1] + 1))
            save_som_dem(
                simulate_som_dem(
                    lambda la, lo: terrain.height(la, lo) + geoid.undulation(la, lo),
                    cfg.path,
                    padded,
                    int(rng.integers(0, 2**62)),
                    cfg.roi_dem_sigma_m,
                ),
                tmp / "dem_som.h5",
            )
        save_camera_model(supplied, tmp / "camera_model.h5")
        save_camera_model(_truth_on_epoch(cfg, truth_model), tmp / "camera_truth.h5")
        save_gcp_database(gcps, tmp / "gcp.h5", truth_ecef=gcp_truth)
        summary = {
            "software": f"misrgraph {__version__}",
            "config": dataclasses.asdict(cfg),
            "passes": len(summaries),
            "observations": n_obs,
            "gcps_seen": int(np.sum(seen_count > 0)),
            "gcps_seen_in_3_or_more_passes": int(np.sum(seen_count >= 3)),
            "pass_summaries": summaries,
            "geoid": "zero (simulated data: DEM heights above MSL = ellipsoidal heights)",
        }
        with atomic_file(tmp / "scenario.json") as fh:
            fh.write(json.dumps(summary, indent=2))
        _swap_into_place(tmp, out_dir)
    except OutputError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputError(out_dir, exc.reason) from None  # the scenario, not its hidden temporary
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return summary


def _render_imagery(
    cfg: ScenarioConfig,
    p: OrbitPass,
    p_truth: PassTruth,
    supplied: "CameraModel | TabulatedCameraModel",
    terrain: SyntheticTerrain,
    geoid: Geoid,
    k: int,
    progress: Callable[[str, int, int], None] | None = None,
) -> "PassImagery":
    """The pass's image windows and GCP chips (:mod:`misrgraph.sim.imagery`), from a generator of
    their own so that switching imagery on changes nothing else in the scenario."""
    from misrgraph.sim.imagery import (
        SceneRadiance,
        render_block_strips,
        render_pass_imagery,
    )

    def surface(la, lo):
        return terrain.height(la, lo) + geoid.undulation(la, lo)

    scene = SceneRadiance(cfg.seed, surface, cloud_fraction=cfg.cloud_fraction, cloud_epoch=k)
    true_geo = p_truth.geometry(p)
    supplied_geo = p.geometry(supplied.at_temperature(p.temperature_c))
    if cfg.feature_windows:
        bands = tuple(BANDS.index(b) for b in cfg.bands)  # GCPs in every observed band; ties in red if observed
        imagery = render_pass_imagery(
            p,
            true_geo,
            supplied_geo,
            p_truth.landmark_ecef,
            scene,
            surface,
            np.random.default_rng([cfg.seed, 4242, k]),
            search_px=cfg.search_px,
            snr=cfg.image_snr,
            band=RED if RED in bands else bands[0],
            gcp_bands=bands,
        )
    else:  # strips only (a scenario for Reference Orbit Imagery, not for matching)
        from misrgraph.io.imagery import ImageWindows, PassImagery

        imagery = PassImagery(
            ImageWindows.empty(1),
            ImageWindows.empty(1),
            np.zeros(0, np.int64),
            np.zeros((0, len(CAMERAS), 1, 1), np.float32),
            {
                "snr": float(cfg.image_snr),
                "cloud_fraction": float(cfg.cloud_fraction),
                "band": 2,
                "full_scale_dn": 2**14 - 1,
                "feature_windows": 0,
            },
        )
    if cfg.roi_blocks:
        imagery.strips = render_block_strips(
            true_geo,
            scene,
            surface,
            p.path,
            cfg.roi_blocks,
            cfg.strip_cameras or CAMERAS,
            cfg.strip_samples,
            [cfg.seed, 4343, k],
            cfg.image_snr,
            progress=progress,
        )
        imagery.attrs["roi_blocks"] = list(cfg.roi_blocks)
    return imagery


#: What :func:`run_simulate` writes into a scenario directory (nothing else is ever replaced).
SCENARIO_ENTRIES = frozenset(
    {"scenario.json", "passes", "dem.h5", "dem_som.h5", "camera_model.h5", "camera_truth.h5", "gcp.h5"}
)


def _check_replaceable(out_dir: Path) -> None:
    """Refuse an ``--out`` that holds anything simulate did not write (user data is never deleted)."""
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("--out", str(out_dir), "a directory (this is a file)")
    if not out_dir.exists() or not any(out_dir.iterdir()):
        return
    if not (out_dir / "scenario.json").exists():
        raise InputError(
            "--out",
            str(out_dir),
            "a new or empty directory, or an earlier scenario directory to replace "
            "(this one is not empty and has no scenario.json)",
        )
    foreign = sorted(e.name for e in out_dir.iterdir() if e.name not in SCENARIO_ENTRIES)
    foreign += (
        sorted(f"passes/{e.name}" for e in (out_dir / "passes").iterdir() if not (e.is_file() and e.suffix == ".h5"))
        if (out_dir / "passes").is_dir()
        else []
    )
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise InputError(
            "--out",
            str(out_dir),
            f"a scenario directory holding only what simulate writes; it also holds "
            f"{shown}: move those elsewhere or choose another --out",
        )


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two directory entries (Linux renameat2 RENAME_EXCHANGE); False where the
    platform or file system cannot."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0


def _swap_into_place(new: Path, out_dir: Path) -> None:
    """Put ``new`` at ``out_dir``. An existing ``out_dir`` is swapped with ``new`` atomically where
    the OS allows (Linux), otherwise renamed aside first; it is deleted only once the new directory
    is in place. A crash leaves the old or the new scenario at ``out_dir`` (on the fallback path,
    possibly neither there but the old one intact as a hidden ``.<name>.old-*`` sibling)."""
    old = None
    if out_dir.exists():
        if _exchange(new, out_dir):
            fsync_directory(out_dir.parent)
            shutil.rmtree(new, ignore_errors=True)  # now holds the old scenario
            return
        old = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.old-", dir=out_dir.parent))
        os.rmdir(old)
        os.replace(out_dir, old)
    os.replace(new, out_dir)
    fsync_directory(out_dir.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
