"""Simulated MISR imagery: ray-cast image windows and GCP reference chips (seed sections 3.3, 3.5).

A matcher needs pixels. The simulator renders, for every camera, the image windows around each
GCP and tie-point feature that matching reads, by casting every pixel through the *true* geometry
onto the true terrain and sampling a ground reflectance field:

* **Reflectance** (:class:`SceneRadiance`): deterministic from the seed, continuous everywhere.
  Land in the red band is ``0.18 (1 + t)`` (floored at 0.018) with ``t`` a sum of 96 random 3-D plane waves of
  60 m - 6 km wavelength (a ``1/f`` amplitude spectrum, 0.35 RMS), water 0.04 (real land mask), times
  Lambertian terrain shading at a sun elevation/azimuth of the pass (``cos i / sin e``, the
  terrain normal from the true height field by central differences over 30 m). The other bands
  have their own land and water levels (:data:`LAND_REFLECTANCE`, :data:`WATER_REFLECTANCE`)
  and follow a vegetation field by :data:`VEGETATION_RESPONSE` (the NIR most, the other way).
* **Angular and temporal change**: each camera sees the land through a BRDF,
  ``1 + brdf_strength (b1 mu + b2 mu^2)`` with ``mu = tan(view) / tan(70.5 deg)`` and ``b1, b2``
  unit-variance fields (100 m - 3 km): the nine views of a patch differ as the surface's
  anisotropy varies, which is what limits multi-angle matching. A GCP chip's source image is of
  another date (:meth:`SceneRadiance.another_date`: an independent surface change of 15 % RMS,
  sun elevation 35 deg instead of 45, nadir view).
* **Clouds** (optional, ``cloud_fraction``): a smooth field (5-40 km) on a layer ``cloud_height_m``
  above the ellipsoid, thresholded to that fraction, reflectance 0.6 with its own texture. A ray
  meets the layer before the ground, so a cloud appears displaced by ``h tan(view angle)`` (up to
  8 km at 3 km for the D cameras): the reason matches on clouds are wrong. Each pass has its own
  clouds (``cloud_epoch``; the ground is the same every pass).
* **Point spread**: each pixel averages the scene over its footprint: the detector's along-track
  extent (one pitch, ``1/rate`` lines: ~700 m for the D cameras), the motion during the line time
  (one line, 275 m) and one sample across track, through the local ground Jacobian of the cast
  pixel centres (relief included at pixel scale). The texture's footprint mean is exact (a sinc
  per wave), so no sub-pixel wave aliases.
* **Terrain hides terrain**: each pixel shows the first ground its ray meets coming from the
  camera (rows are cast in the camera's sweep direction, each from its neighbour,
  :func:`_cast_rows`), so ridges hide the slopes behind them from the oblique cameras as they do
  in MISR's imagery.
* **Radiometry**: 14-bit counts, full scale at reflectance 1.0, Gaussian noise of SNR
  ``snr`` at reflectance 0.18 growing as the square root of the signal, quantised.

Image coordinates are MISR's: row ``L`` is the exposure at time ``t0 + L * line_time`` with the
array centre (focal-plane fraction 0), column ``s`` the sample; a window is stored with the
``(line0, sample0)`` of its first pixel, so a position ``(r, q)`` inside it is the continuous
observation ``line = line0 + r``, ``sample = sample0 + q`` the estimator adjusts.

Whole-swath strips (:func:`render_strip`) are the same image over whole lines, rendered for the
blocks Reference Orbit Imagery is made of (``roi_blocks`` of the scenario).

GCP chips (:func:`render_chip`) are rendered from the same scene through the *supplied* geometry,
centred on the true GCP (a Landsat chip shows the true feature; its catalogue coordinates carry
the catalogue error), without MISR's noise and with a different linear radiometry (another
sensor), 64 x 64 pixels at MISR's sampling. (Per pass here; a production database holds one
set per GCP from a nominal orbit.)
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from misrgraph.io.imagery import INTEREST_RADIUS_PX
from misrgraph.model.constants import BANDS, CAMERAS, VIEW_ANGLE_DEG
from misrgraph.model.frames import ecef_to_geodetic
from misrgraph.model.geolocation import PassGeometry, ray_ellipsoid
from misrgraph.sim.terrain import EARTH_R, SyntheticTerrain, land_mask

if TYPE_CHECKING:
    from misrgraph.io.imagery import ImageStrip, PassImagery
    from misrgraph.io.passes import OrbitPass

__all__ = [
    "SceneRadiance",
    "render_window",
    "render_windows",
    "render_strip",
    "render_block_strips",
    "strip_line_range",
    "render_chip",
    "render_pass_imagery",
    "FULL_SCALE_DN",
    "REFERENCE_REFLECTANCE",
]

Array = NDArray[np.float64]
Surface = Callable[[Array, Array], Array]

RED = BANDS.index("red")
#: 14-bit counts at reflectance 1.0 (full scale)
FULL_SCALE_DN = 2**14 - 1
#: the reflectance at which ``snr`` is stated (land's mean in the red band)
REFERENCE_REFLECTANCE = 0.18
#: Mean land reflectance per band (blue, green, red, NIR; :data:`BANDS`): land is dark in the
#: visible and bright in the near infrared, where vegetation reflects most.
LAND_REFLECTANCE = (0.08, 0.11, REFERENCE_REFLECTANCE, 0.30)
#: Water reflectance per band: it darkens towards the infrared.
WATER_REFLECTANCE = (0.07, 0.06, 0.04, 0.02)
#: Each band's relative response to a vegetation-cover field (unit RMS, 200 m - 3 km) on top of
#: the texture every band shares: red is the reference (0, its image is the texture alone); blue
#: darkens where vegetation is dense, green brightens a little (chlorophyll's green peak) and the
#: NIR a lot, so the NIR pattern differs most from the others'.
VEGETATION_RESPONSE = (-0.05, 0.03, 0.0, 0.25)


def _waves(rng: np.random.Generator, n: int, lam_lo: float, lam_hi: float, rms: float) -> tuple[Array, Array, Array]:
    """Wave vectors (n, 3) rad/m, phases and amplitudes of a 1/f field with total RMS ``rms``."""
    lam = np.exp(rng.uniform(np.log(lam_lo), np.log(lam_hi), n))
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    amp = np.sqrt(lam)  # log-uniform wavelengths: power per log band ~ lambda, a 1/f amplitude spectrum
    amp *= rms * np.sqrt(2.0 / np.sum(amp**2))
    return (2 * np.pi / lam)[:, None] * u, rng.uniform(0, 2 * np.pi, n), amp


def _sinc(x: Array) -> Array:
    """``sin(x/2) / (x/2)``: the mean of ``exp(i x u)`` over ``u`` uniform in [-1/2, 1/2]."""
    y = 0.5 * np.asarray(x, dtype=float)
    out = np.ones_like(y)
    np.divide(np.sin(y), y, out=out, where=np.abs(y) > 1e-12)
    return out


def _field(xyz: Array, waves: tuple[Array, Array, Array]) -> Array:
    k, ph, amp = waves
    out = np.zeros(xyz.shape[:-1])
    for i in range(0, k.shape[0], 16):  # chunks keep the (points, waves) temporary small
        out += np.sin(xyz @ k[i : i + 16].T + ph[i : i + 16]) @ amp[i : i + 16]
    return out


@dataclass(frozen=True)
class SceneRadiance:
    """The ground and cloud scene of a scenario (see the module docstring); deterministic from ``seed``.

    ``height(lat, lon)`` is the true ellipsoidal height field (m) used for shading."""

    seed: int
    height: Surface
    sun_elevation_deg: float = 45.0
    sun_azimuth_deg: float = 135.0
    cloud_fraction: float = 0.0
    cloud_height_m: float = 3000.0
    texture_rms: float = 0.35
    brdf_strength: float = 0.15
    epoch: int = 0
    change_rms: float = 0.0
    cloud_epoch: int = 0
    view_angle_deg: float = 0.0

    def __post_init__(self) -> None:
        rng = np.random.default_rng([self.seed, 17])
        object.__setattr__(self, "_texture", _waves(rng, 96, 60.0, 6000.0, self.texture_rms))
        object.__setattr__(self, "_cloud", _waves(rng, 24, 5e3, 40e3, 1.0))
        object.__setattr__(self, "_cloud_texture", _waves(rng, 24, 300.0, 3000.0, 0.15))
        if self.cloud_epoch:  # another day's clouds (epoch 0 keeps the scene's first draw)
            crng = np.random.default_rng([self.seed, 19, self.cloud_epoch])
            object.__setattr__(self, "_cloud", _waves(crng, 24, 5e3, 40e3, 1.0))
            object.__setattr__(self, "_cloud_texture", _waves(crng, 24, 300.0, 3000.0, 0.15))
        object.__setattr__(self, "_brdf", (_waves(rng, 48, 100.0, 3000.0, 1.0), _waves(rng, 48, 100.0, 3000.0, 1.0)))
        object.__setattr__(
            self, "_change", _waves(np.random.default_rng([self.seed, 18, self.epoch]), 64, 60.0, 3000.0, 1.0)
        )
        object.__setattr__(self, "_vegetation", _waves(np.random.default_rng([self.seed, 23]), 48, 200.0, 3000.0, 1.0))

    def for_view(self, view_angle_deg: float) -> "SceneRadiance":
        """The same scene seen from a camera ``view_angle_deg`` along track (fore > 0)."""
        return dataclasses.replace(self, view_angle_deg=float(view_angle_deg))

    def another_date(self, epoch: int, change_rms: float = 0.15, sun_elevation_deg: float = 35.0) -> "SceneRadiance":
        """The scene on another date (a reference image's), seen at nadir without clouds: an
        independent change of the surface (``change_rms`` relative) and another sun elevation."""
        return dataclasses.replace(
            self,
            sun_elevation_deg=sun_elevation_deg,
            cloud_fraction=0.0,
            epoch=epoch,
            change_rms=change_rms,
            view_angle_deg=0.0,
        )

    # ------------------------------------------------------------------ ground
    def ground_reflectance(
        self,
        ecef: Array,
        d_line: Array | None = None,
        d_sample: Array | None = None,
        rate: float = 1.0,
        band: int = RED,
    ) -> Array:
        """Shaded reflectance (dimensionless) in ``band`` (index into :data:`BANDS`; the mean level
        :data:`LAND_REFLECTANCE`, :data:`WATER_REFLECTANCE` and the vegetation response
        :data:`VEGETATION_RESPONSE` differ per band) of ground points ``(..., 3)`` ECEF m, averaged over a
        pixel footprint when ``d_line``, ``d_sample`` (``(..., 3)`` m of ground per image line and
        per sample) are given: the texture is linear in its plane waves, so its footprint mean is
        exact, each wave's amplitude times ``sinc(k.d_line) sinc(k.d_line / rate) sinc(k.d_sample)``
        (motion over one line, the detector's along-track extent, one sample; ``sinc(x) =
        sin(x/2)/(x/2)``). Land mask and shading are taken at the footprint centre."""
        shape = ecef.shape[:-1]
        g = ecef.reshape(-1, 3)
        lat, lon, _ = ecef_to_geodetic(g)
        scale = EARTH_R / np.linalg.norm(g, axis=-1, keepdims=True)
        k, ph, amp = self._texture
        tex = np.zeros(g.shape[0])
        for i in range(0, k.shape[0], 16):  # chunks keep the (points, waves) temporaries small
            ki = k[i : i + 16]
            arg = (g * scale) @ ki.T + ph[i : i + 16]
            wgt = np.broadcast_to(amp[i : i + 16], arg.shape)
            if d_line is not None and d_sample is not None:
                a = (d_line.reshape(-1, 3) * scale) @ ki.T
                w = (d_sample.reshape(-1, 3) * scale) @ ki.T
                wgt = wgt * _sinc(a) * _sinc(a / max(rate, 1e-3)) * _sinc(w)
            tex += np.sum(np.sin(arg) * wgt, axis=-1)
        land = land_mask(lat, lon)
        base = np.maximum(1.0 + tex, 0.1)
        xyz = g * scale
        mu = np.tan(np.radians(self.view_angle_deg)) / np.tan(np.radians(70.5))
        if self.brdf_strength > 0 and mu != 0:
            b1, b2 = (_field(xyz, w) for w in self._brdf)
            base = base * np.maximum(1.0 + self.brdf_strength * (b1 * mu + b2 * mu * mu), 0.1)
        if self.change_rms > 0:
            base = base * np.maximum(1.0 + self.change_rms * _field(xyz, self._change), 0.1)
        if VEGETATION_RESPONSE[band] != 0:
            base = base * np.maximum(1.0 + VEGETATION_RESPONSE[band] * _field(xyz, self._vegetation), 0.1)
        refl = np.where(land, LAND_REFLECTANCE[band] * base, WATER_REFLECTANCE[band])
        return (refl * self._shading(lat, lon)).reshape(shape)

    def _shading(self, lat: Array, lon: Array) -> Array:
        """Lambertian ``cos(i) / sin(e)`` of the true terrain (1 on flat ground), floored at 0.05."""
        d = 30.0
        dlat = np.degrees(d / EARTH_R)
        dlon = dlat / np.maximum(np.cos(np.radians(lat)), 1e-3)
        h = self.height
        dz_dn = (h(lat + dlat, lon) - h(lat - dlat, lon)) / (2 * d)
        dz_de = (h(lat, lon + dlon) - h(lat, lon - dlon)) / (2 * d)
        e, a = np.radians(self.sun_elevation_deg), np.radians(self.sun_azimuth_deg)
        sun = np.array([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)])  # east, north, up
        normal = np.stack([-dz_de, -dz_dn, np.ones_like(dz_de)], -1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return np.maximum(normal @ sun, 0.05 * np.sin(e)) / np.sin(e)

    # ------------------------------------------------------------------ clouds
    def cloud_cover(self, ecef: Array) -> Array:
        """Cloud opacity 0..1 at points of the cloud layer ``(..., 3)``."""
        if self.cloud_fraction <= 0:
            return np.zeros(ecef.shape[:-1])
        from scipy.stats import norm

        xyz = ecef / np.linalg.norm(ecef, axis=-1, keepdims=True) * EARTH_R
        c = _field(xyz, self._cloud)  # unit variance
        thr = norm.ppf(1.0 - self.cloud_fraction)
        return np.clip((c - thr) / 0.15 + 0.5, 0.0, 1.0)

    def cloud_reflectance(self, ecef: Array) -> Array:
        xyz = ecef / np.linalg.norm(ecef, axis=-1, keepdims=True) * EARTH_R
        return 0.6 * np.exp(_field(xyz, self._cloud_texture))

    def through_clouds(self, refl: Array, origin: Array, direction: Array) -> Array:
        """Ground reflectance ``refl (...)`` seen through the cloud layer by rays ``origin,
        direction (N, 3)`` (N = refl.size, row-major): blended with the cloud's reflectance by its
        opacity where each ray crosses the layer (``refl`` unchanged without clouds)."""
        if self.cloud_fraction <= 0:
            return refl
        lam = ray_ellipsoid(origin, direction, np.full(origin.shape[0], self.cloud_height_m))
        pc = (origin + lam[:, None] * direction).reshape(np.shape(refl) + (3,))
        alpha = self.cloud_cover(pc)
        return (1 - alpha) * refl + alpha * self.cloud_reflectance(pc)


def _sweeps_backward(cam: int) -> bool:
    """Whether rows of camera ``cam`` are cast from the last to the first (see :func:`_cast_rows`):
    the aft-looking cameras, whose later lines see terrain come into the line of sight in front of
    the ground they saw before."""
    return CAMERAS[int(cam)].endswith("a")


#: Height (m) above a ray's crossing from which :func:`_cast_rows` looks for terrain in front of
#: it: the simulator's relief spans 0..``max_relief_m`` (2.5 km) above the sea, plus 200 m for the
#: sub-posting relief (< 50 m) and the geoid's change over a window (metres).
FIRST_CROSSING_CLIMB_M = SyntheticTerrain.max_relief_m + 200.0


def _cast_rows(
    origin: Array, direction: Array, surface: Surface, backward: bool, lam_start: Array | None = None
) -> Array:
    """Rays ``(R, S, 3)`` of consecutive image rows cast onto ``surface`` row after row, each from
    its neighbour's solution by secant steps (:func:`misrgraph.model.geolocation.cast_from`), the
    first row (unless ``lam_start (S,)`` continues an earlier sweep) and rays that lose their
    root by :func:`misrgraph.model.geolocation.cast_seen`. Rows go from first to last, or from last to first with
    ``backward``: in the direction in which terrain in front of a ray only ever leaves the line of
    sight, so that continuing from the neighbour keeps the first crossing from the camera (the
    ground the pixel sees) where terrain hides other ground. Returns the ground points
    ``(R, S, 3)``."""
    from misrgraph.model.geolocation import cast_from, cast_seen

    n_rows = origin.shape[0]
    g = np.full(origin.shape, np.nan)
    order = range(n_rows - 1, -1, -1) if backward else range(n_rows)
    lam_prev = lam_start
    for i in order:
        o, d = origin[i], direction[i]
        if lam_prev is None:
            g[i] = cast_seen(o, d, surface, FIRST_CROSSING_CLIMB_M)
        else:
            g[i] = cast_from(o, d, lam_prev, surface, fallback=False)
            miss = np.flatnonzero(~np.isfinite(g[i, :, 0]))
            if miss.size:
                g[i, miss] = cast_seen(o[miss], d[miss], surface, FIRST_CROSSING_CLIMB_M)
        lam = np.einsum("ni,ni->n", g[i] - o, d)
        lam_prev = lam if lam_prev is None else np.where(np.isfinite(lam), lam, lam_prev)
    return g


def _cast_grid(geo: PassGeometry, cam: int, band: int, lines: Array, samples: Array, surface: Surface) -> Array:
    """Ground points (..., 3) of pixel centres (continuous exposure ``lines``, frac 0) on the grid
    ``lines (H, W)`` x ``samples (H, W)`` (rows of constant line; a single point also), cast row
    by row in the camera's sweep direction (:func:`_cast_rows`): the ground each pixel sees."""
    shape = np.broadcast_shapes(lines.shape, samples.shape)
    ln = np.broadcast_to(lines, shape).reshape(-1, shape[-1] if len(shape) > 1 else 1)
    sm = np.broadcast_to(samples, shape).reshape(ln.shape)
    origin, direction = geo.pixel_rays(
        np.full(ln.size, cam), np.full(ln.size, band), ln.ravel(), sm.ravel(), np.full(ln.size, np.nan)
    )
    g = _cast_rows(origin.reshape(ln.shape + (3,)), direction.reshape(ln.shape + (3,)), surface, _sweeps_backward(cam))
    return g.reshape(shape + (3,))


def _render(
    geo: PassGeometry,
    scene: SceneRadiance,
    cam: int,
    band: int,
    lines: Array,
    samples: Array,
    surface: Surface,
    rate: float | None = None,
) -> Array:
    """Mean scene reflectance over each pixel footprint, for a regular grid of continuous pixel
    positions ``lines (H,)`` x ``samples (W,)`` (spacing ``dl``, ``ds`` pixels). ``rate`` (image
    lines per line of ground motion, :meth:`PassGeometry.line_rate`) is taken by default at the
    grid's centre point ``(H // 2, W // 2)`` from the cast grid itself."""
    ll, ss = np.meshgrid(lines, samples, indexing="ij")
    g = _cast_grid(geo, cam, band, ll, ss, surface)
    if rate is None:
        r, q = lines.size // 2, samples.size // 2
        rate = _line_rate_at(geo, cam, band, lines[r], g[r, q])
    dl = lines[1] - lines[0] if lines.size > 1 else 1.0
    ds = samples[1] - samples[0] if samples.size > 1 else 1.0
    rays = (
        geo.pixel_rays(np.full(ll.size, cam), np.full(ll.size, band), ll.ravel(), ss.ravel(), np.full(ll.size, np.nan))
        if scene.cloud_fraction > 0
        else None
    )
    return _footprint_reflectance(scene, band, g, dl, ds, rate, rays)


def _footprint_reflectance(
    scene: SceneRadiance, band: int, g: Array, dl: float, ds: float, rate: float, rays: tuple[Array, Array] | None
) -> Array:
    """Reflectance ``(H, W)`` of the cast grid ``g (H, W, 3)`` (rows ``dl``, columns ``ds`` pixels
    apart), averaged over each pixel's footprint (the local ground Jacobian from the grid itself)
    and seen through the clouds along ``rays = (origin, direction)`` (``(H W, 3)``, row-major;
    needed only when the scene has clouds)."""
    refl = scene.ground_reflectance(g, np.gradient(g, dl, axis=0), np.gradient(g, ds, axis=1), rate, band)
    if scene.cloud_fraction > 0:
        refl = scene.through_clouds(refl, *rays)
    return refl


def render_window(
    geo: PassGeometry,
    scene: SceneRadiance,
    cam: int,
    band: int,
    line0: int,
    sample0: int,
    size: int,
    surface: Surface,
    rng: np.random.Generator,
    snr: float = 200.0,
) -> NDArray[np.uint16]:
    """A ``size x size`` window of 14-bit counts whose pixel ``(r, q)`` is image line ``line0 + r``,
    sample ``sample0 + q`` of camera ``cam``/band ``band`` under ``geo`` (the true geometry)."""
    lines = line0 + np.arange(size, dtype=float)
    samples = sample0 + np.arange(size, dtype=float)
    refl = _render(geo, scene, cam, band, lines, samples, surface)  # rate at the centre pixel
    return _counts(refl, rng, snr)


#: Windows cast together by :func:`render_windows` (bounds the temporaries: 64 windows of 100 px
#: are 640 000 rays)
WINDOW_BATCH = 64


def _window_reflectance(
    geo: PassGeometry,
    scene: SceneRadiance,
    cam: int,
    band: int,
    line0: Array,
    sample0: Array,
    size: int,
    surface: Surface,
    batch: int = WINDOW_BATCH,
) -> Array:
    """``(n, size, size)`` reflectance of the windows of :func:`render_windows` (no noise)."""
    line0 = np.asarray(line0, dtype=float).ravel()
    sample0 = np.asarray(sample0, dtype=float).ravel()
    n, step = line0.size, max(int(batch), 1)
    off = np.arange(size, dtype=float)
    refl = np.empty((n, size, size))
    for a in range(0, n, step):
        b = min(a + step, n)
        m = b - a
        # (size rows, m windows x size samples): window j's pixel (r, q) at [r, j * size + q]
        ll = np.repeat((line0[a:b, None] + off[None, :]).T, size, axis=1)
        ss = np.broadcast_to(np.tile(off, m)[None, :] + np.repeat(sample0[a:b], size)[None, :], ll.shape).copy()
        g = _cast_grid(geo, cam, band, ll, ss, surface).reshape(size, m, size, 3)
        if scene.cloud_fraction > 0:
            origin, direction = geo.pixel_rays(
                np.full(ll.size, cam), np.full(ll.size, band), ll.ravel(), ss.ravel(), np.full(ll.size, np.nan)
            )
            origin, direction = origin.reshape(size, m, size, 3), direction.reshape(size, m, size, 3)
        r = size // 2
        for j in range(m):  # as _render does for one window
            gj = np.ascontiguousarray(g[:, j])
            rate = _line_rate_at(geo, cam, band, line0[a + j] + off[r], gj[r, r])
            rays = (origin[:, j].reshape(-1, 3), direction[:, j].reshape(-1, 3)) if scene.cloud_fraction > 0 else None
            refl[a + j] = _footprint_reflectance(scene, band, gj, 1.0, 1.0, rate, rays)
    return refl


def render_windows(
    geo: PassGeometry,
    scene: SceneRadiance,
    cam: int,
    band: int,
    line0: Array,
    sample0: Array,
    size: int,
    surface: Surface,
    rng: np.random.Generator,
    snr: float = 200.0,
    batch: int = WINDOW_BATCH,
) -> NDArray[np.uint16]:
    """``(n, size, size)``: :func:`render_window` for each of ``n`` windows at ``line0 (n,)``,
    ``sample0 (n,)`` of one camera and band, with the same result (the noise drawn window after
    window, in the order given). The rays of ``batch`` windows are cast together, side by side
    along the row (every operation of the cast is per ray, so a window's ground does not depend on
    its neighbours): row ``r`` of every window is one secant step per ray, where a window alone
    spends that step's Python overhead on ``size`` rays only."""
    refl = _window_reflectance(geo, scene, cam, band, line0, sample0, size, surface, batch)
    out = np.empty(refl.shape, np.uint16)
    for i in range(refl.shape[0]):  # the noise window after window, as render_window draws it
        out[i] = _counts(refl[i], rng, snr)
    return out


def render_chip(
    geo: PassGeometry,
    scene: SceneRadiance,
    cam: int,
    band: int,
    line_c: float,
    sample_c: float,
    size: int,
    surface: Surface,
    gain: float = 0.8,
    offset_dn: float = 300.0,
) -> Array:
    """A reference chip ``(size, size)`` float32 counts, centred (between pixels ``size/2 - 1`` and
    ``size/2``) on the continuous image position ``(line_c, sample_c)`` under ``geo``, with the
    linear radiometry ``gain * counts + offset_dn`` of another sensor and no noise."""
    off = np.arange(size, dtype=float) - (size - 1) / 2.0
    # the along-track extent at pixel (size/2, size/2), half a pixel from the centre: it varies over
    # hundreds of pixels
    refl = _render(geo, scene, cam, band, line_c + off, sample_c + off, surface)
    return (gain * np.clip(refl, 0, 1) * FULL_SCALE_DN + offset_dn).astype(np.float32)


def _line_rate_at(geo: PassGeometry, cam: int, band: int, line: float, ground: Array) -> float:
    """:meth:`PassGeometry.line_rate` of image line ``line`` at its ground point ``ground (3,)``."""
    t = geo.line_time(cam, band, line, np.array(line))
    return float(geo.line_rate(cam, band, np.reshape(ground, (1, 3)), np.atleast_1d(t))[0])


def _rate(geo: PassGeometry, cam: int, band: int, line: float, sample: float, surface: Surface) -> float:
    """:func:`_line_rate_at` the pixel ``(line, sample)`` cast alone onto ``surface``."""
    g = _cast_grid(geo, cam, band, np.array([line]), np.array([sample]), surface)
    return _line_rate_at(geo, cam, band, line, g[0])


def _counts(refl: Array, rng: np.random.Generator, snr: float) -> NDArray[np.uint16]:
    signal = np.clip(refl, 0, None) * FULL_SCALE_DN
    ref = REFERENCE_REFLECTANCE * FULL_SCALE_DN
    noise = rng.standard_normal(refl.shape) * (ref / snr) * np.sqrt(np.maximum(signal, 1.0) / ref)
    return np.clip(np.round(signal + noise), 0, FULL_SCALE_DN).astype(np.uint16)


def render_strip(
    geo: PassGeometry,
    scene: SceneRadiance,
    cam: int,
    band: int,
    line0: int,
    n_lines: int,
    sample0: int,
    n_samples: int,
    surface: Surface,
    rng: np.random.Generator,
    snr: float = 200.0,
    chunk: int = 32,
    progress: Callable[[int, int], None] | None = None,
) -> NDArray[np.uint16]:
    """A strip of whole image lines (``n_lines x n_samples`` 14-bit counts): pixel ``(r, q)`` is
    exposure ``line0 + r``, sample ``sample0 + q`` of camera ``cam``/band ``band`` under ``geo``.

    The same image :func:`render_window` makes (the scene's footprint mean at every pixel's ground
    point, clouds, noise), computed ``chunk`` lines at a time for a full swath: the navigation once
    per line (:meth:`PassGeometry.line_rays`), and each line's rays cast onto the terrain by secant
    steps from the neighbouring line's solution, in the camera's sweep direction so that each
    pixel shows the first ground its ray meets (:func:`_cast_rows`; the aft cameras' chunks go
    from the last line to the first, their noise is still drawn in line order). The along-track
    detector extent (``rate``) is taken per chunk at its centre pixel."""
    samples = sample0 + np.arange(n_samples, dtype=float)
    out = np.zeros((n_lines, n_samples), np.uint16)
    backward = _sweeps_backward(cam)
    starts = list(range(0, n_lines, chunk))
    refl_of: dict[int, Array] = {}
    lam_carry: Array | None = None
    for n, a in enumerate(starts[::-1] if backward else starts):
        if progress:
            progress(n * chunk, n_lines)
        b = min(a + chunk, n_lines)
        lines = line0 + np.arange(a - 1, b + 1, dtype=float)  # one line each side: central differences
        origin, direction = geo.line_rays(cam, band, lines, samples)
        o = np.broadcast_to(origin[:, None, :], direction.shape)
        g = _cast_rows(o, direction, surface, backward, lam_carry)
        # the next chunk starts from the line it shares with this one (b - 1 forward, a backward)
        shared = 1 if backward else lines.size - 2
        lam_carry = np.einsum("ni,ni->n", g[shared] - o[shared], direction[shared])
        g_l = 0.5 * (g[2:] - g[:-2])
        g_s = np.gradient(g[1:-1], axis=1)
        c = (b - a) // 2
        rate = _line_rate_at(geo, cam, band, lines[1 + c], g[1 + c, n_samples // 2])
        refl = scene.ground_reflectance(g[1:-1], g_l, g_s, rate if np.isfinite(rate) else 1.0, band)
        if scene.cloud_fraction > 0:
            refl = scene.through_clouds(
                refl, np.repeat(origin[1:-1], n_samples, axis=0), direction[1:-1].reshape(-1, 3)
            )
        refl_of[a] = refl
    for a in starts:  # the noise drawn in line order whatever the sweep
        out[a : a + chunk] = _counts(np.nan_to_num(refl_of.pop(a), nan=0.0), rng, snr)
    if progress:
        progress(n_lines, n_lines)
    return out


#: Lines rendered beyond a block's extent in each camera (terrain parallax, PP margins)
STRIP_MARGIN_LINES = 24


def strip_line_range(
    geo: PassGeometry, cam: int, band: int, path: int, blocks: tuple[int, int], surface: Surface
) -> tuple[int, int] | None:
    """First and one-past-last exposure of camera ``cam`` that image blocks ``blocks[0]..blocks[1]``
    of ``path`` (their 1.1 km grid every 8th point on the terrain, :data:`STRIP_MARGIN_LINES` more
    each side, clipped to the pass); None when the camera sees none of them."""
    from misrgraph.misr.som import SomGrid
    from misrgraph.model.frames import geodetic_to_ecef

    grid = SomGrid(int(path), 1100)
    lines = []
    for block in range(int(blocks[0]), int(blocks[1]) + 1):
        lat, lon = grid.somxy_to_latlon(*grid.block_centres(block, step=8))
        lat, lon = lat.ravel(), lon.ravel()
        g = geodetic_to_ecef(lat, lon, np.asarray(surface(lat, lon), dtype=float))
        ip = geo.ground_to_pixel(cam, band, g, continuous=True)
        lines.append(ip.line[ip.visible])
    ln = np.concatenate(lines)
    if ln.size == 0:
        return None
    lo = max(int(np.floor(ln.min())) - STRIP_MARGIN_LINES, 0)
    hi = min(int(np.ceil(ln.max())) + STRIP_MARGIN_LINES + 1, int(geo.lines_in_pass(cam, band)))
    return (lo, hi) if hi > lo else None


def render_block_strips(
    geo: PassGeometry,
    scene: SceneRadiance,
    surface: Surface,
    path: int,
    blocks: tuple[int, int],
    cameras: tuple[str, ...],
    samples: tuple[int, int] | tuple = (),
    seed: list[int] | None = None,
    snr: float = 200.0,
    band: int = 2,
    workers: int | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> "dict[str, ImageStrip]":
    """Whole-swath strips (:func:`render_strip`) of ``cameras`` over ``blocks`` of ``path``
    (:func:`strip_line_range`), ``samples = (first, count)`` of the array (default all), each
    camera's noise from its own generator ``default_rng(seed + [camera index])`` so the result does
    not depend on the order or the ``workers`` threads (default: up to 2) that render them."""
    from concurrent.futures import ThreadPoolExecutor

    from misrgraph.io.imagery import ImageStrip
    from misrgraph.model.constants import N_PIXELS

    s0, ns = (int(samples[0]), int(samples[1])) if samples else (0, N_PIXELS)
    seed = list(seed or [0])
    done = [0]

    def one(name: str) -> "ImageStrip | None":
        cam = CAMERAS.index(name)
        rng_lines = strip_line_range(geo, cam, band, path, blocks, surface)
        if rng_lines is None:
            return None
        lo, hi = rng_lines
        px = render_strip(
            geo,
            scene.for_view(VIEW_ANGLE_DEG[name]),
            cam,
            band,
            lo,
            hi - lo,
            s0,
            ns,
            surface,
            np.random.default_rng(seed + [cam]),
            snr,
        )
        done[0] += 1
        if progress:
            progress(f"strip {name} ({done[0]}/{len(cameras)})", done[0], len(cameras))
        return ImageStrip(name, band, lo, s0, px)

    n = workers or min(2, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=max(1, n)) as pool:
        strips = list(pool.map(one, cameras))
    return {st.camera: st for st in strips if st is not None}


def _window_size(kind: str, search_px: int, template_px: int, chip_px: int) -> int:
    """GCP windows: the chip plus the search range each side; tie windows: the template plus the
    search range, the interest point's freedom and 2 px for the least-squares fit, each side."""
    if kind == "gcp":
        return chip_px + 2 * search_px
    return template_px + 2 * (search_px + INTEREST_RADIUS_PX + 2)


def render_pass_imagery(
    orbit_pass: "OrbitPass",
    true_geo: PassGeometry,
    supplied_geo: PassGeometry,
    landmark_ecef: Array,
    scene: SceneRadiance,
    surface: Surface,
    rng: np.random.Generator,
    search_px: int = 8,
    template_px: int = 15,
    chip_px: int = 64,
    snr: float = 200.0,
    band: int = RED,
    gcp_bands: tuple[int, ...] | None = None,
) -> "PassImagery":
    """Render the windows a matcher reads for one pass: tie points in band ``band`` (red by
    default), GCPs in each of ``gcp_bands`` (default: ``band`` alone) where the pass observes them.

    For every tie point or GCP and camera with a simulated observation: a window of ``template_px + 2
    (search_px + 5)`` pixels (tie and check points) or ``chip_px + 2 search_px`` (GCPs), centred on
    where the *supplied* geometry predicts the true ground point (``landmark_ecef (M, 3)``, the
    pass's true landmark positions) -- so the matcher cannot read the truth off the window
    centre -- and rendered through ``true_geo``. For every GCP and GCP band, nine reference chips
    through ``supplied_geo`` (:func:`render_chip`; one chip set per (GCP, band), in
    ``chip_landmark``/``chip_band``). ``search_px`` must cover the navigation's 3 sigma
    prediction error (about 5 lines for the D cameras with the pass scenario's attitude errors).
    Band-to-band geometry (each band's own detector line on the focal plane, its own offsets in a
    calibrated model) is what the GCPs of several bands measure."""
    from misrgraph.io.imagery import ImageWindows, PassImagery
    from misrgraph.io.passes import KIND_CHECK, KIND_GCP

    gcp_bands = (int(band),) if gcp_bands is None else tuple(int(b) for b in gcp_bands)
    o = orbit_pass.observations
    kinds = orbit_pass.landmarks.kind
    out: dict[str, list] = {"tie": [], "gcp": []}
    t_lo, t_hi = orbit_pass.span
    views = [scene.for_view(VIEW_ANGLE_DEG[name]) for name in CAMERAS]
    reference = scene.another_date(1)  # the chips' source image: another date, another sun
    for b in dict.fromkeys((int(band),) + gcp_bands):  # the tie band first, then the other GCP bands
        sel = np.flatnonzero(o.band == b)
        pairs = np.unique(np.stack([o.landmark[sel], o.camera[sel]], 1), axis=0) if sel.size else np.zeros((0, 2), int)
        for cam in np.unique(pairs[:, 1]) if len(pairs) else []:
            rows = pairs[pairs[:, 1] == cam, 0]
            pred = supplied_geo.ground_to_pixel(int(cam), b, landmark_ecef[rows], continuous=True)
            jobs = []
            for row, ln, sm, ok in zip(rows, pred.line, pred.sample, pred.visible):
                if not ok or kinds[row] == KIND_CHECK:  # check points are scored from the truth, never matched
                    continue
                kind = "gcp" if kinds[row] == KIND_GCP else "tie"
                if (kind == "tie" and b != band) or (kind == "gcp" and b not in gcp_bands):
                    continue
                size = _window_size(kind, search_px, template_px, chip_px)
                l0, s0 = int(round(ln)) - size // 2, int(round(sm)) - size // 2
                t_first, t_last = (
                    supplied_geo.line_time(int(cam), b, l0, l0),
                    supplied_geo.line_time(int(cam), b, l0, l0 + size),
                )
                if t_first < t_lo or t_last > t_hi:  # the window would reach past the pass's navigation
                    continue
                jobs.append((kind, int(row), l0, s0))
            # the windows of one kind cast together (render_windows), the noise drawn in the order above
            refl: dict[int, Array] = {}
            for kind in ("tie", "gcp"):
                mine = [i for i, job in enumerate(jobs) if job[0] == kind]
                if mine:
                    r = _window_reflectance(
                        true_geo,
                        views[int(cam)],
                        int(cam),
                        b,
                        np.array([jobs[i][2] for i in mine]),
                        np.array([jobs[i][3] for i in mine]),
                        _window_size(kind, search_px, template_px, chip_px),
                        surface,
                    )
                    refl.update(zip(mine, r))
            for i, (kind, row, l0, s0) in enumerate(jobs):
                out[kind].append((row, int(cam), b, l0, s0, _counts(refl[i], rng, snr)))
    wins = {}
    for kind, items in out.items():
        size = _window_size(kind, search_px, template_px, chip_px)
        if not items:
            wins[kind] = ImageWindows.empty(size)
            continue
        cols = list(zip(*items))
        wins[kind] = ImageWindows(*(np.array(c) for c in cols[:5]), np.stack(cols[5]))
    w = wins["gcp"]
    chip_keys = np.unique(np.stack([w.landmark, w.band], 1), axis=0) if len(w) else np.zeros((0, 2), np.int64)
    chips = np.full((len(chip_keys), 9, chip_px, chip_px), np.nan, np.float32)
    for i, (row, b) in enumerate(chip_keys):
        for cam in w.camera[(w.landmark == row) & (w.band == b)]:
            p = supplied_geo.ground_to_pixel(int(cam), int(b), landmark_ecef[row][None], continuous=True)
            if p.visible[0]:
                chips[i, int(cam)] = render_chip(
                    supplied_geo, reference, int(cam), int(b), float(p.line[0]), float(p.sample[0]), chip_px, surface
                )
    attrs = {
        "snr": float(snr),
        "cloud_fraction": float(scene.cloud_fraction),
        "search_px": int(search_px),
        "template_px": int(template_px),
        "chip_px": int(chip_px),
        "band": int(band),
        "gcp_bands": [int(b) for b in gcp_bands],
        "full_scale_dn": int(FULL_SCALE_DN),
    }
    return PassImagery(
        wins["tie"],
        wins["gcp"],
        chip_keys[:, 0].astype(np.int64),
        chips,
        attrs,
        chip_band=chip_keys[:, 1].astype(np.int64),
    )
