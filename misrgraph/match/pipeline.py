"""The matching pipeline (seed sections 3.3 and 3.5): GCP chips and tie points measured in MISR imagery.

* **GCPs.** For each GCP window (in its own band: imagery may hold GCPs in several bands, the
  measurements of the band-to-band geometry): the GCP's catalogue position is projected through the supplied
  navigation and camera model (continuous line/sample); the reference chip of that camera and band is
  correlated over ``+-search_px`` around it (NCC), and the integer peak refined by least-squares
  matching (:func:`misrgraph.match.lsm.lsm`) (``search_px`` must cover the supplied navigation's
  3 sigma prediction error: ~5 lines for the D cameras in a pass; by default it is the range the
  windows were rendered for, :func:`search_range`). Rejected when the NCC peak is below ``min_ncc``,
  ambiguous (peak ratio above ``max_peak_ratio``), LSM does not converge, or its sigma exceeds
  ``max_sigma_px``.
* **Tie points.** In each An window the strongest Foerstner interest point near the centre
  (``skimage.feature.corner_foerstner``) defines the tie point: its An position is the An
  observation (whole pixels; the point *is* what An sees there). Its conjugates are predicted
  through the supplied navigation and the DEM (ray cast, then projected into each camera), found
  by NCC and refined by LSM with the An patch as template (a conjugate whose ground point the
  DEM hides from that camera -- the supplied ray meets the DEM first more than half a pixel
  before it, :func:`misrgraph.model.geolocation.cast_first` -- is not matched: "hidden by
  terrain"; its image shows the ridge in front, the D cameras' classic failure) -- blurred along track by the
  difference between the camera's footprint and An's (``1/rate`` lines each: the D cameras'
  detector covers ~2.6 lines, An's one; Gaussian of the variances' difference) -- then **checked backwards**: the
  matched patch is matched back into An and must land within ``back_tolerance_sigma`` times the two
  matches' combined sigma (at least ``back_tolerance_px``, at most 1 px) of where it came
  from (the forward-backward check stands in for the seed's consistent labelling: a wrong match
  rarely maps back to its origin). A bright template (mean reflectance above
  ``cloud_reflectance``; land is ~0.18) is screened as cloud. A tie point is kept when it is
  matched in at least ``min_cameras`` cameras, An included.
* **Sigma.** Each observation's sigma starts as the LSM's (residual variance times the residuals'
  correlation area, :mod:`misrgraph.match.lsm`), at least ``sigma_floor_px``; one sigma per
  observation, the RMS of the line and sample ones. The residuals cannot show the largest tie
  error, the change of the pattern between view angles, so each camera's tie sigmas are then
  scaled by its precision measured from the pass's own redundancy
  (:func:`misrgraph.match.precision.camera_sigma_scales`: the scatter of matched minus predicted
  positions about a smooth navigation model on ``sigma_knot_s`` knots and each feature's height
  along An's ray; by default, ``sigma_model="shared-attitude"``, the adjustment's own model, one
  attitude correction for all cameras through each observation's numerical pointing
  sensitivity; a camera with too little redundancy takes the scale of its twin at the same view
  angle), unless ``sigma_from_redundancy`` is off. The GCP observations (in the tie points' band) join
  the shared-attitude fit as a class of their own, with three ground offsets per GCP (catalogue
  error, the chip's own registration), and all of them take its scale
  (``gcp_sigma_from_redundancy``). An's defining observation gets the
  median of its conjugates' sigmas (``an_sigma="median"``, the default), or, with
  ``an_sigma="shared-offset"``, the sigma of the offset all conjugates of a feature share, which the
  fit then models. With the default that offset is measured by a second fit whose scales are not
  used: the adjustment adds its effect to each tie point's covariance
  (``AdjustConfig.tie_offset_sigma_px``). The same fit is a consistency check across the pass: a
  conjugate beyond its 4 sigma clip is rejected ("inconsistent with the pass"), and a feature
  left in fewer than ``min_cameras`` cameras with it.

Every failure is reported per feature (reason counts), never raised: a window off the image, a
flat chip or NaN pixels make that feature's match fail with its reason.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from misrgraph.config import Config
from misrgraph.errors import InputError
from misrgraph.io.imagery import INTEREST_RADIUS_PX, PassImagery
from misrgraph.match.lsm import lsm, ncc_search
from misrgraph.match.precision import GcpRows, Pointing, PrecisionFit, camera_sigma_scales
from misrgraph.model.camera import sample_direction
from misrgraph.model.constants import CAMERAS, N_PIXELS
from misrgraph.model.frames import ecef_to_geodetic, enu_basis
from misrgraph.model.geolocation import ImagePoints, PassGeometry

__all__ = [
    "AN_SIGMAS",
    "DEFAULT_SEARCH_PX",
    "SIGMA_MODELS",
    "MatchConfig",
    "MatchedObservations",
    "TieFeature",
    "gcp_fit_rows",
    "match_gcps",
    "match_ties",
    "scale_gcp_sigmas",
    "search_range",
]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]
AN = CAMERAS.index("An")
_CENTRE = (N_PIXELS - 1) / 2.0


#: The search range (px) of imagery that does not record its own.
DEFAULT_SEARCH_PX = 8

#: each camera's twin at the same view angle on the other side of nadir (Df-Da, Cf-Ca, ...)
_TWIN = {c: len(CAMERAS) - 1 - c for c in range(len(CAMERAS))}

#: ``MatchConfig.sigma_model``'s values
SIGMA_MODELS = ("shared-attitude", "per-camera")

#: ``MatchConfig.an_sigma``'s values
AN_SIGMAS = ("median", "shared-offset")

#: attitude step (rad, per axis) of the numerical pointing sensitivities (2", ~7 m on the ground
#: from An: the predictions move by hundredths of a pixel, well inside their linear range)
_ATTITUDE_STEP_RAD = 1e-5


def search_range(cfg: "MatchConfig", imagery: PassImagery) -> int:
    """The search range (px) ``cfg`` means for ``imagery``: its own ``search_px``, or the range the
    windows were rendered for."""
    if cfg.search_px is not None:
        return int(cfg.search_px)
    return int(imagery.attrs.get("search_px", DEFAULT_SEARCH_PX))


@dataclass(frozen=True)
class MatchConfig(Config):
    """Matching settings (pixels unless named otherwise). Unknown keys are rejected by ``from_dict``."""

    template_px: int = 15
    #: search range (px) each side of the prediction; None: the range the windows were rendered
    #: for (the imagery's ``search_px`` attribute, :data:`DEFAULT_SEARCH_PX` when it has none)
    search_px: int | None = None
    min_ncc: float = 0.6
    max_peak_ratio: float = 0.95
    max_sigma_px: float = 0.5
    back_tolerance_px: float = 0.3
    back_tolerance_sigma: float = 3.0
    min_cameras: int = 3
    cloud_reflectance: float = 0.4
    sigma_floor_px: float = 0.02
    sigma_from_redundancy: bool = True
    #: the GCP observations join the shared-attitude fit and take its GCP scale (one for the pass;
    #: :mod:`misrgraph.match.precision`); False keeps the LSM's sigmas
    gcp_sigma_from_redundancy: bool = True
    sigma_knot_s: float = 60.0
    #: the precision fit's smooth model (:mod:`misrgraph.match.precision`): "shared-attitude"
    #: (one attitude correction for all cameras, through each observation's pointing sensitivity)
    #: or "per-camera" (each camera its own spline; needs ~30 matches a camera on a short pass)
    sigma_model: str = "shared-attitude"
    #: An's defining observation's sigma: "median" (its conjugates' median) or "shared-offset" (the
    #: shared-attitude fit also models an offset all conjugates of a feature share -- the template's
    #: own position error -- and An takes its sigma; :mod:`misrgraph.match.precision`)
    an_sigma: str = "median"

    def __post_init__(self) -> None:
        if not (isinstance(self.template_px, int) and self.template_px >= 7 and self.template_px % 2 == 1):
            raise InputError("template_px", self.template_px, "an odd integer >= 7")
        if self.search_px is not None and not (isinstance(self.search_px, int) and self.search_px >= 1):
            raise InputError("search_px", self.search_px, "an integer >= 1, or None (the windows' own range)")
        for name in ("min_ncc", "max_peak_ratio"):
            if not 0 < getattr(self, name) <= 1:
                raise InputError(name, getattr(self, name), "a number in (0, 1]")
        for name in (
            "max_sigma_px",
            "back_tolerance_px",
            "back_tolerance_sigma",
            "sigma_floor_px",
            "cloud_reflectance",
            "sigma_knot_s",
        ):
            if not getattr(self, name) > 0:
                raise InputError(name, getattr(self, name), "a positive number")
        if self.sigma_model not in SIGMA_MODELS:
            raise InputError("sigma_model", self.sigma_model, f"one of {SIGMA_MODELS}")
        if self.an_sigma not in AN_SIGMAS:
            raise InputError("an_sigma", self.an_sigma, f"one of {AN_SIGMAS}")
        if not (isinstance(self.min_cameras, int) and 2 <= self.min_cameras <= 9):
            raise InputError("min_cameras", self.min_cameras, "an integer in 2..9")

    @property
    def shared_attitude_fit(self) -> bool:
        """Whether the tie sigmas come from the shared-attitude precision fit (which the GCP rows
        and the shared offset need)."""
        return self.sigma_from_redundancy and self.sigma_model == "shared-attitude"


@dataclass
class MatchedObservations:
    """Matched measurements, one row each: ``feature`` (landmark row for GCPs; tie feature index
    for ties), ``camera``, ``line``, ``sample`` (continuous), ``sigma_px``, ``band``; per-feature
    failure ``reasons`` and the number of candidate (feature, camera, band) windows."""

    feature: list[int] = field(default_factory=list)
    camera: list[int] = field(default_factory=list)
    line: list[float] = field(default_factory=list)
    sample: list[float] = field(default_factory=list)
    sigma_px: list[float] = field(default_factory=list)
    band: list[int] = field(default_factory=list)
    candidates: int = 0
    reasons: Counter = field(default_factory=Counter)
    precision: PrecisionFit | None = None
    #: rows (into these lists) of the redundancy fit's observations, in its order
    pending_rows: NDArray[np.int64] | None = None

    def add(self, feature: int, camera: int, line: float, sample: float, sigma: float, band: int) -> None:
        self.band.append(int(band))
        self.feature.append(int(feature))
        self.camera.append(int(camera))
        self.line.append(float(line))
        self.sample.append(float(sample))
        self.sigma_px.append(float(sigma))

    def __len__(self) -> int:
        return len(self.feature)


def _pixels(raw: NDArray) -> Array | None:
    px = np.asarray(raw, dtype=float)
    return px if np.all(np.isfinite(px)) else None


def _match_one(
    image: Array, template: Array, row_p: float, col_p: float, cfg: MatchConfig, search: int
) -> tuple[float, float, float] | str:
    """NCC within ``+-search`` of the predicted template centre, then LSM; (row, col, sigma) or a reason."""
    peak = ncc_search(image, template, (row_p - search, row_p + search), (col_p - search, col_p + search))
    if peak is None:
        return "no search area (window off the image, flat template or NaN pixels)"
    if peak.value < cfg.min_ncc:
        return "weak correlation"
    if peak.ratio > cfg.max_peak_ratio:
        return "ambiguous correlation peak"
    res = lsm(image, template, peak.row, peak.col)
    if not res.converged:
        return f"LSM: {res.reason}"
    sigma = max(float(np.sqrt(0.5 * (res.sigma_row**2 + res.sigma_col**2))), cfg.sigma_floor_px)
    if sigma > cfg.max_sigma_px:
        return "LSM sigma too large"
    return res.row, res.col, sigma


def match_gcps(
    imagery: PassImagery,
    supplied_geo: PassGeometry,
    catalogue_ecef: Array,
    landmark_gcp_row: Callable[[int], int],
    cfg: MatchConfig = MatchConfig(),
) -> MatchedObservations:
    """Measure every GCP window (see the module docstring). ``catalogue_ecef (G, 3)`` m are the
    database positions; ``landmark_gcp_row(landmark row)`` gives a window's GCP database row."""
    out = MatchedObservations()
    wins = imagery.gcp
    search = search_range(cfg, imagery)
    chip_of = imagery.chip_index()
    for k in range(len(wins)):
        out.candidates += 1
        row, cam, band = int(wins.landmark[k]), int(wins.camera[k]), int(wins.band[k])
        chip = imagery.chips[chip_of[(row, band)], cam] if (row, band) in chip_of else None
        image = _pixels(wins.pixels[k])
        if chip is None or not np.all(np.isfinite(chip)):
            out.reasons["no reference chip"] += 1
            continue
        if image is None:
            out.reasons["NaN pixels"] += 1
            continue
        p = supplied_geo.ground_to_pixel(cam, band, catalogue_ecef[landmark_gcp_row(row)][None], continuous=True)
        if not p.visible[0]:
            out.reasons["not predicted in the image"] += 1
            continue
        got = _match_one(
            image,
            np.asarray(chip, float),
            float(p.line[0] - wins.line0[k]),
            float(p.sample[0] - wins.sample0[k]),
            cfg,
            search + 2,
        )
        if isinstance(got, str):
            out.reasons[got] += 1
            continue
        r, c, s = got
        out.add(row, cam, wins.line0[k] + r, wins.sample0[k] + c, s, band)
    return out


#: ground step (m) of the GCP rows' numerical d(line, sample)/d(east, north, up)
_GROUND_STEP_M = 10.0


def gcp_fit_rows(
    gcps: MatchedObservations,
    supplied_geo: PassGeometry,
    catalogue_ecef: Array,
    landmark_gcp_row: Callable[[int], int],
    band: int,
) -> GcpRows:
    """The GCP observations of ``band`` (the tie points') as rows of the precision fit
    (:class:`misrgraph.match.precision.GcpRows`): matched minus the catalogue position's
    prediction, the observation time, and numerical ``J_c`` (:func:`_tilt_jacobian`) and ``G``
    (the ground moved :data:`_GROUND_STEP_M` east, north, up). An observation whose prediction is
    not finite stays out."""
    idx = np.flatnonzero(np.asarray(gcps.band, np.int64) == band)
    cams = np.asarray(gcps.camera, np.int64)[idx]
    line, sample = np.asarray(gcps.line, float)[idx], np.asarray(gcps.sample, float)[idx]
    ground = np.asarray(catalogue_ecef, float)[
        [landmark_gcp_row(int(r)) for r in np.asarray(gcps.feature)[idx]]
    ].reshape(-1, 3)
    pred = supplied_geo.ground_to_pixel(cams, band, ground, continuous=True)
    jac = _tilt_jacobian(supplied_geo, cams, band, ground, pred.line, pred.sample)
    lat, lon, _ = ecef_to_geodetic(ground)
    basis = enu_basis(lat, lon).reshape(-1, 3, 3)  # columns east, north, up
    gjac = np.empty((idx.size, 2, 3))
    for k in range(3):
        q = supplied_geo.ground_to_pixel(cams, band, ground + _GROUND_STEP_M * basis[:, :, k], continuous=True)
        gjac[:, 0, k], gjac[:, 1, k] = (q.line - pred.line) / _GROUND_STEP_M, (q.sample - pred.sample) / _GROUND_STEP_M
    d = np.stack([line - pred.line, sample - pred.sample], axis=1)
    ok = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(jac), axis=(1, 2)) & np.all(np.isfinite(gjac), axis=(1, 2))
    return GcpRows(
        np.asarray(gcps.feature, np.int64)[idx][ok],
        cams[ok],
        supplied_geo.line_time(cams, band, line)[ok],
        (sample[ok] - _CENTRE) / _CENTRE,
        d[ok],
        np.asarray(gcps.sigma_px, float)[idx][ok],
        jac[ok],
        gjac[ok],
        AN,
    )


def scale_gcp_sigmas(gcps: MatchedObservations, fit: PrecisionFit | None, cfg: MatchConfig) -> None:
    """Multiply every GCP observation's sigma (all bands) by the precision fit's GCP scale
    (``fit.gcp``, when estimated), at least ``cfg.sigma_floor_px``."""
    if fit is None or fit.gcp is None or not fit.gcp.estimated:
        return
    gcps.sigma_px = [max(float(v) * fit.gcp.scale, cfg.sigma_floor_px) for v in gcps.sigma_px]


def _filled(surface: Callable[[Array, Array], Array]) -> Callable[[Array, Array], Array]:
    """``surface`` with height 0 where it has none (NaN), so a ray cast can finish; the caller checks
    that the point it finds is on the DEM."""
    return lambda lat, lon: np.nan_to_num(np.asarray(surface(lat, lon), dtype=float), nan=0.0)


#: A conjugate is hidden when its ray meets the DEM first more than this (m, half a 275 m pixel)
#: before its ground point; the DEM is searched from this height (m) above the point.
HIDDEN_DISTANCE_M = 137.5
HIDDEN_CLIMB_M = 3000.0


def _hidden_by_terrain(
    geo: PassGeometry,
    cams: NDArray[np.int64],
    band: int,
    pred: ImagePoints,
    ground: Array,
    surface: Callable[[Array, Array], Array],
) -> NDArray[np.bool_]:
    """``(len(cams),)``: whether the DEM hides ECEF ``ground (3,)`` from each camera at its
    predicted image position ``pred`` (an :class:`ImagePoints`; not visible: False)."""
    from misrgraph.model.geolocation import hidden_in_image

    return hidden_in_image(
        geo,
        cams,
        band,
        pred,
        np.repeat(ground[None, :], cams.size, axis=0),
        _filled(surface),
        HIDDEN_DISTANCE_M,
        HIDDEN_CLIMB_M,
    )


@dataclass
class TieFeature:
    """A tie point defined by an An interest point: its ``window_row`` (the simulated feature whose
    windows it lives in), An ``line``/``sample`` (whole pixels)."""

    window_row: int
    line: float
    sample: float


def _interest_point(image: Array, margin: int, search: int) -> tuple[int, int] | None:
    """Strongest Foerstner point within ``search`` of the centre, at least ``margin`` from the edge."""
    from skimage.feature import corner_foerstner

    w, q = corner_foerstner(image / max(float(np.std(image)), 1e-9), sigma=1.0)
    h = image.shape[0]
    lo, hi = max(h // 2 - search, margin), min(h // 2 + search, h - 1 - margin)
    if lo > hi:
        return None
    sub_w = np.where(q[lo : hi + 1, lo : hi + 1] > 0.3, w[lo : hi + 1, lo : hi + 1], 0.0)
    if not np.isfinite(sub_w).all() or sub_w.max() <= 0:
        return None
    i, j = np.unravel_index(int(np.argmax(sub_w)), sub_w.shape)
    return lo + int(i), lo + int(j)


def _tilted(geo: PassGeometry, axis: int) -> PassGeometry:
    """``geo`` with its attitude turned by :data:`_ATTITUDE_STEP_RAD` about ``axis`` (0 roll,
    1 pitch, 2 yaw), on top of any correction it already has."""
    step = np.zeros(3)
    step[axis] = _ATTITUDE_STEP_RAD
    base = geo.attitude_delta

    def delta(t: Array) -> Array:
        t = np.asarray(t, float).ravel()
        out = np.tile(step, (t.size, 1))
        return out if base is None else out + np.asarray(base(t), float).reshape(t.size, 3)

    return dataclasses.replace(geo, attitude_delta=delta, _cache={})


def _tilt_jacobian(
    geo: PassGeometry, cams: NDArray[np.int64], band: int, ground: Array, pred_line: Array, pred_sample: Array
) -> Array:
    """``J_c`` ``(n, 2, 3)`` px/rad: how the predictions ``pred_line, pred_sample (n,)`` of the
    fixed ECEF points ``ground (n, 3)`` move when the navigation turns about each axis (three calls)."""
    jac = np.empty((cams.size, 2, 3))
    for a in range(3):
        p = _tilted(geo, a).ground_to_pixel(cams, band, ground, continuous=True)
        jac[:, 0, a], jac[:, 1, a] = p.line - pred_line, p.sample - pred_sample
    return jac / _ATTITUDE_STEP_RAD


def _pointing_sensitivity(
    geo: PassGeometry,
    cams: NDArray[np.int64],
    band: int,
    ground: Array,
    pred_line: Array,
    pred_sample: Array,
    an_line: Array,
    an_sample: Array,
    row_feature: NDArray[np.int64],
    surface: Callable[[Array, Array], Array],
) -> tuple[Array, Array]:
    """Numerical ``J_c`` and ``K_c`` (px/rad, each ``(n, 2, 3)``) of ``n`` conjugates' predictions
    ``pred_line, pred_sample (n,)`` of their features' An ground points ``ground (n, 3)`` ECEF m
    (:class:`misrgraph.match.precision.Pointing`): the prediction of the fixed ground point by a
    navigation tilted about each axis, and the untilted prediction of where the tilted navigation
    casts An's pixel ``an_line, an_sample (F,)`` (per feature; ``row_feature (n,)`` indexes them)
    onto the DEM. Seven calls for all the conjugates of the pass."""
    kan = np.empty((cams.size, 2, 3))
    for a in range(3):
        moved = _tilted(geo, a).pixel_to_ground(AN, band, an_line, an_sample, surface=_filled(surface), exposure=np.nan)
        q = geo.ground_to_pixel(cams, band, moved[row_feature], continuous=True)
        kan[:, 0, a], kan[:, 1, a] = q.line - pred_line, q.sample - pred_sample
    return _tilt_jacobian(geo, cams, band, ground, pred_line, pred_sample), kan / _ATTITUDE_STEP_RAD


def match_ties(
    imagery: PassImagery,
    supplied_geo: PassGeometry,
    surface: Callable[[Array, Array], Array],
    rows: NDArray[np.int64],
    cfg: MatchConfig = MatchConfig(),
    progress: Callable[[int, int], None] | None = None,
    gcp: GcpRows | None = None,
) -> tuple[list[TieFeature], MatchedObservations]:
    """Detect and match tie points in the windows of landmark ``rows`` (see the module docstring).
    ``surface(lat, lon)`` is the DEM's ellipsoidal height (m; NaN outside the DEM), for the
    conjugates' prediction; a feature whose An point falls outside the DEM is rejected. ``gcp``
    (:func:`gcp_fit_rows`) joins the pass's GCP observations to the shared-attitude precision fit,
    which then also gives their scale (``precision.gcp``; :func:`scale_gcp_sigmas` applies it)."""
    wins = imagery.tie
    band = imagery.band
    search = search_range(cfg, imagery)
    half = cfg.template_px // 2
    full = float(imagery.attrs.get("full_scale_dn", 2**14 - 1))
    features: list[TieFeature] = []
    out = MatchedObservations()
    pending: list[tuple] = []  # (row in out, feature, camera, time, sample, d_line, d_sample, epipolar line, sample)
    pending_geo: list[tuple] = []  # per pending row: An's ground point (3), the predicted line, sample, An's time
    for n_done, row in enumerate(rows):
        if progress is not None:
            progress(n_done, len(rows))
        k_an = wins.find(int(row), AN, band)
        if k_an is None:
            out.reasons["no An window"] += 1
            continue
        an_img = _pixels(wins.pixels[k_an])
        if an_img is None:
            out.reasons["NaN pixels"] += 1
            continue
        ip = _interest_point(an_img, half + 1, INTEREST_RADIUS_PX)
        if ip is None:
            out.reasons["no interest point (low texture)"] += 1
            continue
        r0, c0 = ip
        tpl = an_img[r0 - half : r0 + half + 1, c0 - half : c0 + half + 1]
        if tpl.mean() / full > cfg.cloud_reflectance:
            out.reasons["cloud (bright template)"] += 1
            continue
        line_an, samp_an = float(wins.line0[k_an] + r0), float(wins.sample0[k_an] + c0)
        ground = supplied_geo.pixel_to_ground(AN, band, line_an, samp_an, surface=_filled(surface), exposure=np.nan)
        on_dem = np.all(np.isfinite(ground))
        if on_dem:
            lat_g, lon_g, h_g = ecef_to_geodetic(ground)
            on_dem = np.all(np.isfinite(surface(lat_g, lon_g)))
        if not on_dem:
            out.reasons["An point outside the DEM"] += 1  # no prediction, and no height constraint in the adjustment
            continue
        fi = len(features)
        got: list[tuple] = []  # (camera, line, sample, sigma, predicted line, sample, time, epipolar)
        ks = np.flatnonzero((wins.landmark == row) & (wins.band == band) & (wins.camera != AN))
        # the conjugates' predictions, and each view's along-track image motion (An's first), in one call each
        cams = wins.camera[ks]
        pred = supplied_geo.ground_to_pixel(cams, band, np.repeat(ground, ks.size, axis=0), continuous=True)
        # the epipolar direction: where each conjugate moves per metre of height along An's ray
        raised = supplied_geo.pixel_to_ground(
            AN, band, line_an, samp_an, exposure=np.nan, height=h_g + _EPIPOLAR_STEP_M
        )
        pred_up = supplied_geo.ground_to_pixel(cams, band, np.repeat(raised, ks.size, axis=0), continuous=True)
        hidden = _hidden_by_terrain(supplied_geo, cams, band, pred, ground[0], surface)
        rate_cams = np.concatenate([[AN], cams])
        rate_lines = np.concatenate([[line_an], pred.line])
        times = supplied_geo.line_time(rate_cams, band, rate_lines, rate_lines)
        rates = supplied_geo.line_rate(rate_cams, band, np.repeat(ground, ks.size + 1, axis=0), times)
        rate_an = float(rates[0])
        mirrored = sample_direction(supplied_geo.camera, cams, band) != sample_direction(supplied_geo.camera, AN, band)
        for j, k in enumerate(ks):
            out.candidates += 1
            img = _pixels(wins.pixels[k])
            if img is None:
                out.reasons["NaN pixels"] += 1
                continue
            if not pred.visible[j]:
                out.reasons["not predicted in the image"] += 1
                continue
            if hidden[j]:
                out.reasons["hidden by terrain (DEM)"] += 1
                continue
            cam = int(cams[j])
            # the camera's along-track footprint (1/rate lines) is longer than An's in the C and D cameras:
            # blur An along track by the difference (variances of the box footprints) before matching
            blur = np.sqrt(max(1.0 / float(rates[j + 1]) ** 2 - 1.0 / rate_an**2, 0.0) / 12.0)
            ref = ndimage.gaussian_filter1d(an_img, blur, axis=0, mode="nearest") if blur > 0.05 else an_img
            tpl_c = ref[r0 - half : r0 + half + 1, c0 - half : c0 + half + 1]
            # a camera whose samples run the other way across the ground (the aft cameras) sees An's
            # patch mirrored in the sample direction
            mirror = bool(mirrored[j])
            if mirror:
                tpl_c = tpl_c[:, ::-1]
            m = _match_one(
                img, tpl_c, float(pred.line[j] - wins.line0[k]), float(pred.sample[j] - wins.sample0[k]), cfg, search
            )
            if isinstance(m, str):
                out.reasons[m] += 1
                continue
            r, c, s = m
            # forward-backward check: the matched patch, matched back into An, must land where it came from
            ri, ci = int(round(r)), int(round(c))
            back_tpl = img[ri - half : ri + half + 1, ci - half : ci + half + 1]
            if back_tpl.shape != tpl.shape:
                out.reasons["match at the window edge"] += 1
                continue
            if mirror:
                back_tpl = back_tpl[:, ::-1]
            er, ec = r0 + (ri - r), c0 + ((c - ci) if mirror else (ci - c))
            b = _match_one(ref, back_tpl, er, ec, cfg, 2)
            if isinstance(b, str) or np.hypot(b[0] - er, b[1] - ec) > min(
                max(cfg.back_tolerance_px, cfg.back_tolerance_sigma * np.hypot(s, b[2])), 1.0
            ):
                out.reasons["forward-backward check"] += 1
                continue
            epi = (
                (pred_up.line[j] - pred.line[j]) / _EPIPOLAR_STEP_M,
                (pred_up.sample[j] - pred.sample[j]) / _EPIPOLAR_STEP_M,
            )
            got.append(
                (cam, wins.line0[k] + r, wins.sample0[k] + c, s, pred.line[j], pred.sample[j], float(times[j + 1]), epi)
            )
        if len(got) + 1 < cfg.min_cameras:
            out.reasons[f"seen in fewer than {cfg.min_cameras} cameras"] += 1
            continue
        features.append(TieFeature(int(row), line_an, samp_an))
        out.add(fi, AN, line_an, samp_an, np.nan, band)  # An's sigma: set below from its conjugates'
        for cam, ln, sm, s, pl, ps, tt, epi in got:
            out.add(fi, cam, ln, sm, s, band)
            pending.append((len(out) - 1, fi, cam, tt, sm, ln - pl, sm - ps, epi[0], epi[1]))
            pending_geo.append((*ground[0], pl, ps, float(times[0])))
    pointing = None
    if pending and cfg.shared_attitude_fit:
        a = np.asarray(pending, float)
        pg = np.asarray(pending_geo, float)
        jac, kan = _pointing_sensitivity(
            supplied_geo,
            a[:, 2].astype(np.int64),
            band,
            pg[:, :3],
            pg[:, 3],
            pg[:, 4],
            np.array([f.line for f in features]),
            np.array([f.sample for f in features]),
            a[:, 1].astype(np.int64),
            surface,
        )
        pointing = Pointing(pg[:, 5], jac, kan)
    _rescale(out, pending, cfg, pointing, gcp)
    return _drop_inconsistent(features, out, cfg)


#: height step (m) along An's ray for the epipolar direction
_EPIPOLAR_STEP_M = 100.0


def _drop_inconsistent(
    features: list[TieFeature], out: MatchedObservations, cfg: MatchConfig
) -> tuple[list[TieFeature], MatchedObservations]:
    """Remove the conjugates the redundancy fit found inconsistent with the pass (beyond its clip),
    then the features left in fewer than ``min_cameras`` cameras; renumber the features."""
    fit = out.precision
    if fit is None or not fit.outlier.any():
        return features, out
    idx = np.asarray(out.pending_rows, np.int64)[fit.outlier]
    keep = np.ones(len(out), bool)
    keep[idx] = False
    out.reasons["inconsistent with the pass (redundancy check)"] += int(idx.size)
    feat = np.asarray(out.feature)
    cams = np.asarray(out.camera)
    n_seen = np.bincount(feat[keep], minlength=len(features))  # An included
    few = n_seen < cfg.min_cameras
    out.reasons[f"seen in fewer than {cfg.min_cameras} cameras"] += int(
        np.sum(few & (np.bincount(feat, minlength=len(features)) > 0))
    )
    keep &= ~few[feat]
    new_index = np.cumsum(~few) - 1
    kept = MatchedObservations(candidates=out.candidates, reasons=out.reasons, precision=fit)
    for i in np.flatnonzero(keep):
        kept.add(int(new_index[feat[i]]), int(cams[i]), out.line[i], out.sample[i], out.sigma_px[i], out.band[i])
    return [f for f, drop in zip(features, few) if not drop], kept


def _rescale(
    out: MatchedObservations,
    pending: list[tuple],
    cfg: MatchConfig,
    pointing: Pointing | None = None,
    gcp: GcpRows | None = None,
) -> None:
    """Scale each camera's tie sigmas by its precision from the pass's redundancy
    (:func:`misrgraph.match.precision.camera_sigma_scales`; with ``pointing``, one row per
    ``pending`` row, the shared-attitude fit, joined by the ``gcp`` rows when given; without
    ``pointing`` they are left out) and give each An observation the median of its conjugates'
    sigmas, or the shared offset's (``cfg.an_sigma``); the fit is kept in ``out.precision`` (with the
    median, its ``shared_offset`` from a second fit that models the offset, for the adjustment)."""
    sig = np.asarray(out.sigma_px, float)
    if pending and cfg.sigma_from_redundancy:
        a = np.asarray(pending, float)
        idx = a[:, 0].astype(np.int64)
        cam = a[:, 2].astype(np.int64)
        fitted = np.ones(idx.size, bool)
        if pointing is not None:  # a prediction the tilt moved off the image stays out of the fit
            fitted = (
                np.isfinite(pointing.an_time_s)
                & np.all(np.isfinite(pointing.camera_px_per_rad), axis=(1, 2))
                & np.all(np.isfinite(pointing.an_px_per_rad), axis=(1, 2))
            )
            if not fitted.all():
                log.info(
                    "%d tie observations without a pointing sensitivity left out of the precision fit",
                    int(np.sum(~fitted)),
                )
            a = a[fitted]
            pointing = Pointing(*(v[fitted] for v in pointing))
        args = (
            a[:, 1].astype(np.int64),
            a[:, 2].astype(np.int64),
            a[:, 3],
            (a[:, 4] - _CENTRE) / _CENTRE,
            a[:, 5:7],
            a[:, 7:9],
            sig[idx[fitted]],
        )
        kw = dict(knot_s=cfg.sigma_knot_s, pointing=pointing, twin=_TWIN, gcp=gcp if pointing is not None else None)
        fit = camera_sigma_scales(*args, **kw, shared_offset=cfg.an_sigma == "shared-offset" and pointing is not None)
        if pointing is not None and cfg.an_sigma != "shared-offset":
            # the offset a feature's conjugates share, measured by the fit that models it (its scales
            # are not used here): the adjustment adds its effect to each tie point's covariance
            second = camera_sigma_scales(*args, **kw, shared_offset=True)
            if second.shared_offset is not None:
                second.shared_offset.own_scale_ratio = {
                    c: second.scale[c] / fit.scale[c] for c in fit.scale if c in second.scale and fit.scale[c] > 0
                }
            fit.shared_offset = second.shared_offset
        sig[idx] = np.maximum(sig[idx] * np.array([fit.scale.get(int(c), 1.0) for c in cam]), cfg.sigma_floor_px)
        out.precision = fit
        out.pending_rows = idx[fitted]
    feat = np.asarray(out.feature)
    cams = np.asarray(out.camera)
    shared = out.precision.shared_offset if out.precision is not None else None
    if cfg.an_sigma == "shared-offset" and shared is not None and shared.estimated:
        sig[cams == AN] = max(shared.sigma_px, cfg.sigma_floor_px)
    else:
        for i in np.flatnonzero(cams == AN):
            sig[i] = float(np.median(sig[(feat == feat[i]) & (cams != AN)]))
    out.sigma_px = [float(v) for v in sig]
