"""Pushbroom geolocation: pixel -> ground (ray casting) and ground -> pixel (line search).

Model (eqs. 1, 2, 5, 6 and docs/explanation/conventions.md). For camera ``c``, band ``b`` and image
coordinates ``(l, s)`` the line is exposed at ``t = t0[c, b] + INT(l + 0.5) * dt_line`` and

    r_eci = T_go(t) @ T_os(A(t) + dA(t)) @ r_scs(c, b, l, s)
    P_eci = P(t) + T_go(t) @ dP(t)

where ``P, V, A`` are the *supplied* (measured) navigation and attitude interpolated at ``t``,
``T_go`` is built from the supplied ``P, V`` (the on-board attitude is reported relative to the
on-board orbital frame), and ``dA`` (rad, roll/pitch/yaw) and ``dP`` (m, orbital frame) are optional
corrections. With the error models of eqs. 19 and 22, ``dA = -E_att`` and ``dP = -e_eph``.
Ground points are ECEF metres; ``r_eci`` is rotated to ECEF with :class:`EarthOrientation`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from factors.geometry import attitude_matrix, orbital_frame
from misrgraph.errors import ConvergenceError, InputError
from misrgraph.model.camera import CameraModel
from misrgraph.model.constants import BANDS, CAMERAS, N_PIXELS
from misrgraph.model.frames import WGS84_A, WGS84_B, EarthOrientation, ecef_to_geodetic, enu_basis
from misrgraph.model.orbit import AttitudeSeries, Ephemeris

__all__ = [
    "PassGeometry",
    "NavState",
    "ImagePoints",
    "ray_ellipsoid",
    "cast_from",
    "cast_first",
    "cast_seen",
    "hidden_from_camera",
    "hidden_in_image",
]

Array = NDArray[np.float64]
Correction = Callable[[Array], Array]


class ImagePoints(NamedTuple):
    """Result of :meth:`PassGeometry.ground_to_pixel`, each ``(N,)``.

    ``line`` = ``exposure + frac`` (eq. 2's line coordinate), ``sample``, ``visible`` (bool) and
    ``exposure`` = the integer exposure (time) index ``L`` and ``crossing_line`` = the continuous
    ``(t* - t0) / dt_line`` at which the point crosses the band's array centre (a smooth measure of
    the along-track image position, used for co-registration). For the A cameras the along-track
    image moves ~1.1 detector pitches per line, so ``|frac|`` can slightly exceed 0.5 and
    ``INT(line + 0.5)`` can differ from ``exposure``: pass ``exposure`` back to
    :meth:`PassGeometry.pixel_to_ground` to reproduce the ground point exactly.
    """

    line: NDArray[np.float64]
    sample: NDArray[np.float64]
    visible: NDArray[np.bool_]
    exposure: NDArray[np.float64]
    crossing_line: NDArray[np.float64]


@dataclass
class NavState:
    """Navigation quantities at a set of times (all ``(N, ...)``).

    ``position`` ECI m (corrected); ``t_go`` orbital -> ECI; ``angles`` roll/pitch/yaw rad
    (corrected); ``r_eci_scs`` spacecraft -> ECI; ``eci_to_ecef`` rotation.
    """

    t: Array
    position: Array
    t_go: Array
    angles: Array
    r_eci_scs: Array
    eci_to_ecef: Array


def ray_ellipsoid(origin: Array, direction: Array, h: ArrayLike = 0.0) -> Array:
    """Distance along unit ``direction`` from ``origin`` (ECEF m, ``(N, 3)``) to the first
    intersection with the WGS84 ellipsoid inflated by ``h`` metres (semi-axes ``a+h, a+h, b+h``).
    NaN where the ray misses."""
    hh = np.asarray(h, dtype=float)
    scale = np.stack(np.broadcast_arrays(WGS84_A + hh, WGS84_A + hh, WGS84_B + hh), axis=-1)
    o = origin / scale
    d = direction / scale
    qa = np.sum(d * d, axis=-1)
    qb = 2 * np.sum(o * d, axis=-1)
    qc = np.sum(o * o, axis=-1) - 1.0
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore"):
        lam = (-qb - np.sqrt(disc)) / (2 * qa)
    return np.where(disc >= 0, lam, np.nan)


@dataclass
class PassGeometry:
    """Everything needed to geolocate the pixels of one orbit pass.

    ``t0`` (9, 4) is the time (s from the ephemeris epoch) of line 0 of each camera/band; the
    default is the first ephemeris sample for all. ``attitude_delta(t) -> (N, 3)`` rad and
    ``position_delta(t) -> (N, 3)`` m (orbital frame) are optional corrections added to the
    supplied navigation (see the module docstring).
    """

    ephemeris: Ephemeris
    attitude: AttitudeSeries
    camera: CameraModel
    earth: EarthOrientation | None = None
    t0: Array | None = None
    attitude_delta: Correction | None = None
    position_delta: Correction | None = None
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.earth is None:
            self.earth = EarthOrientation(self.ephemeris.epoch_utc)
        if self.t0 is None:
            self.t0 = np.full((len(CAMERAS), len(BANDS)), self.ephemeris.t[0])
        self.t0 = np.asarray(self.t0, dtype=float)
        if self.t0.shape != (len(CAMERAS), len(BANDS)):
            raise InputError("t0", self.t0.shape, f"shape ({len(CAMERAS)}, {len(BANDS)})")

    # ------------------------------------------------------------------ navigation state
    def nav_state(self, t: ArrayLike) -> NavState:
        """Corrected navigation at times ``t`` (s), flattened to ``(N,)``."""
        tt = np.asarray(t, dtype=float).ravel()
        p, v = self.ephemeris.interpolate(tt)
        t_go = orbital_frame(p, v)
        angles = self.attitude.interpolate(tt)
        if self.attitude_delta is not None:
            angles = angles + np.asarray(self.attitude_delta(tt), dtype=float).reshape(angles.shape)
        if self.position_delta is not None:
            dp = np.asarray(self.position_delta(tt), dtype=float).reshape(p.shape)
            p = p + np.einsum("nij,nj->ni", t_go, dp)
        r = t_go @ attitude_matrix(angles[:, 0], angles[:, 1], angles[:, 2])
        assert self.earth is not None
        return NavState(tt, p, t_go, angles, r, self.earth.eci_to_ecef(tt))

    def line_time(self, cam: ArrayLike, band: ArrayLike, line: ArrayLike, exposure: ArrayLike | None = None) -> Array:
        """Exposure time (s) of image line ``l``: ``t0[c, b] + L * dt_line`` with ``L = INT(l + 0.5)``
        unless the exposure index ``L`` is given explicitly."""
        assert self.t0 is not None
        c, b = np.asarray(cam, dtype=int), np.asarray(band, dtype=int)
        big_l = np.floor(np.asarray(line, dtype=float) + 0.5) if exposure is None else np.asarray(exposure, dtype=float)
        return self.t0[c, b] + big_l * self.camera.line_time

    def lines_in_pass(self, cam: int, band: int) -> float:
        """Number of whole image lines the ephemeris span covers for a camera/band."""
        assert self.t0 is not None
        return float(np.floor((self.ephemeris.t[-1] - self.t0[cam, band]) / self.camera.line_time))

    # ------------------------------------------------------------------ forward
    def pixel_rays(
        self, cam: ArrayLike, band: ArrayLike, line: ArrayLike, sample: ArrayLike, exposure: ArrayLike | None = None
    ) -> tuple[Array, Array]:
        """ECEF ray origins (m) and unit directions for pixels, each ``(N, 3)``.

        ``exposure`` (optional) is the integer exposure index ``L``; by default ``INT(l + 0.5)``;
        NaN marks a continuous position (``L = l``). The focal-plane fraction is always ``l - L``.
        """
        c, b, ln, s = (
            np.ravel(x)
            for x in np.broadcast_arrays(
                np.asarray(cam, dtype=int),
                np.asarray(band, dtype=int),
                np.asarray(line, dtype=float),
                np.asarray(sample, dtype=float),
            )
        )
        big_l = (
            np.floor(ln + 0.5)
            if exposure is None
            else np.ravel(np.broadcast_to(np.asarray(exposure, dtype=float), ln.shape))
        )
        big_l = np.where(np.isnan(big_l), ln, big_l)  # NaN: a continuous position (time from the line)
        if np.any((c < 0) | (c >= len(CAMERAS))):
            raise InputError("camera", c[(c < 0) | (c >= len(CAMERAS))][0], f"an index in 0..{len(CAMERAS) - 1}")
        if np.any((b < 0) | (b >= len(BANDS))):
            raise InputError("band", b[(b < 0) | (b >= len(BANDS))][0], f"an index in 0..{len(BANDS) - 1}")
        t = self.line_time(c, b, ln, big_l)
        nav = self.nav_state(t)
        r_scs = self.camera.direction_scs(c, b, ln, s, exposure=big_l)
        r_eci = np.einsum("nij,nj->ni", nav.r_eci_scs, r_scs)
        origin = np.einsum("nij,nj->ni", nav.eci_to_ecef, nav.position)
        direction = np.einsum("nij,nj->ni", nav.eci_to_ecef, r_eci)
        return origin, direction

    def pixel_to_ground(
        self,
        cam: ArrayLike,
        band: ArrayLike,
        line: ArrayLike,
        sample: ArrayLike,
        height: ArrayLike = 0.0,
        surface: Callable[[Array, Array], Array] | None = None,
        tol_m: float = 1e-4,
        exposure: ArrayLike | None = None,
    ) -> Array:
        """Ground point (ECEF m, ``(N, 3)``) where each pixel's ray meets the ground.

        Without ``surface`` the ground is the WGS84 ellipsoidal height ``height`` (m). With
        ``surface(lat_deg, lon_deg) -> h`` (ellipsoidal m) the ray is cast onto that height field
        by a bracketed root search (:func:`scipy.optimize.elementwise.find_root`) between the heights ``surface``
        can take, which are estimated along the ray; the first crossing from above is not guaranteed where
        terrain occludes itself. Rays that miss the Earth give NaN.
        """
        origin, direction = self.pixel_rays(cam, band, line, sample, exposure)
        n = origin.shape[0]
        if surface is None:
            h_target = (
                np.broadcast_to(np.asarray(height, dtype=float), (n,)) if np.ndim(height) else np.full(n, float(height))
            )

            def h_fun(lat: Array, lon: Array, idx: Array) -> Array:
                return h_target[idx]

            lo_h, hi_h = h_target - 50.0, h_target + 50.0
        else:
            return _cast_onto(origin, direction, surface, tol_m)
        return _cast(origin, direction, lo_h, hi_h, h_fun, tol_m)

    def line_rays(self, cam: int, band: int, lines: ArrayLike, samples: ArrayLike) -> tuple[Array, Array]:
        """Rays of whole image lines: ECEF origins ``(L, 3)`` m and unit directions ``(L, S, 3)``
        of the pixels ``samples (S,)`` of the integer exposures ``lines (L,)`` (focal-plane
        fraction 0), with the navigation evaluated once per line; the same rays as
        :meth:`pixel_rays` at a fraction of its cost for a full swath."""
        ln = np.asarray(lines, dtype=float).ravel()
        s = np.asarray(samples, dtype=float).ravel()
        nav = self.nav_state(self.line_time(cam, band, ln, ln))
        r_scs = self.camera.direction_scs(
            np.full(s.size, cam), np.full(s.size, band), np.zeros(s.size), s, exposure=np.zeros(s.size)
        )
        to_ecef = np.einsum("lij,ljk->lik", nav.eci_to_ecef, nav.r_eci_scs)
        origin = np.einsum("lij,lj->li", nav.eci_to_ecef, nav.position)
        return origin, np.einsum("lij,sj->lsi", to_ecef, r_scs)

    # ------------------------------------------------------------------ inverse
    def _along_cross(self, cam: Array, band: Array, ground: Array, t: Array) -> tuple[Array, Array, Array]:
        """Detector-plane coordinates (x, y in m) and depth of ground points seen at times ``t``."""
        return self._project(cam, band, ground, self.nav_state(t))

    def _project(self, cam: Array, band: Array, ground: Array, nav: NavState) -> tuple[Array, Array, Array]:
        """Detector-plane (x, y) in m and depth of ECEF ``ground`` for a navigation state.

        Arrays broadcast: ``cam, band (...)``, ``ground (..., 3)``, nav fields ``(..., 3[, 3])``.
        """
        g_eci = np.einsum("...ji,...j->...i", nav.eci_to_ecef, ground)
        v_scs = np.einsum("...ji,...j->...i", nav.r_eci_scs, g_eci - nav.position)
        m = self.camera.detector_to_spacecraft(cam, band)
        v_det = np.einsum("...ji,...j->...i", m, v_scs)
        f = self.camera.focal_length[cam, band]
        with np.errstate(divide="ignore", invalid="ignore"):
            return f * v_det[..., 0] / v_det[..., 2], f * v_det[..., 1] / v_det[..., 2], v_det[..., 2]

    def ground_to_pixel(
        self, cam: ArrayLike, band: ArrayLike, ground: ArrayLike, coarse_step_s: float = 10.0, continuous: bool = False
    ) -> ImagePoints:
        """Image coordinates at which camera ``cam``/band ``band`` sees ECEF ground points.

        The continuous time ``t*`` at which the point crosses the band's line array (detector
        ``x = -k``) is bracketed on a coarse time grid (only where the point is in front of the
        camera and above the local horizon) and refined by a bracketed root search. The exposure is
        the line nearest that crossing, ``L = round((t* - t0) / dt_line)``, and eq. 2's fraction
        follows from the detector x at ``t(L)``: ``frac = -(x + k) / dx``.

        Eq. 2 with whole-line timing is not one-to-one: the along-track image moves ~0.39 pitch
        per line in the D cameras (several lines see the same point) and ~1.1 in the A cameras.
        This inverse returns the canonical pixel, the exposure in which the point is closest to
        the array centre; ``pixel_to_ground(..., exposure=...)`` of the result reproduces the
        ground point exactly. Returns an :class:`ImagePoints`; invisible points get NaN.

        With ``continuous=True`` the result is what an image matcher measures: ``line`` =
        ``exposure`` = ``crossing_line`` (the continuous time index at which the point crosses the
        array centre, focal-plane fraction 0) and ``sample`` the sample seen at that time
        (docs/explanation/conventions.md, "Observations").
        """
        g = np.atleast_2d(np.asarray(ground, dtype=float))
        if g.ndim != 2 or g.shape[-1] != 3:
            raise InputError("ground", g.shape, "ECEF points of shape (N, 3)")
        n = g.shape[0]
        c = np.broadcast_to(np.asarray(cam, dtype=int), (n,)).copy()
        b = np.broadcast_to(np.asarray(band, dtype=int), (n,)).copy()
        k = self.camera.k[c, b]
        t_lo, t_hi = self.ephemeris.span
        grid = np.append(np.arange(t_lo, t_hi, coarse_step_s), t_hi)
        nav = self.nav_state(grid)
        x, _, depth = self._project(c[:, None], b[:, None], g[:, None, :], nav)
        h = x + k[:, None]
        sc_ecef = np.einsum("nij,nj->ni", nav.eci_to_ecef, nav.position)
        up = g / np.linalg.norm(g, axis=-1, keepdims=True)
        elevation_ok = np.einsum("gj,nj->ng", sc_ecef, up) - np.sum(g * up, axis=-1)[:, None] > 0
        front = (depth > 0) & elevation_ok
        ok = front[:, :-1] & front[:, 1:] & (np.sign(h[:, :-1]) != np.sign(h[:, 1:]))
        has = ok.any(axis=1)
        j = np.argmax(ok, axis=1)
        idx = np.flatnonzero(has)
        line = np.full(n, np.nan)
        sample = np.full(n, np.nan)
        exposure = np.full(n, np.nan)
        crossing = np.full(n, np.nan)
        if idx.size:

            def f_t(tt, ii):
                return self._along_cross(c[ii], b[ii], g[ii], tt)[0] + k[ii]

            t_star = _find_root(f_t, grid[j[idx]], grid[j[idx] + 1], tol=1e-9 if continuous else 1e-7, index=idx)
            assert self.t0 is not None
            dt = self.camera.line_time
            t0 = self.t0[c[idx], b[idx]]
            crossing[idx] = (t_star - t0) / dt
            if continuous:
                big_l, tl = (t_star - t0) / dt, t_star
                inside = (big_l >= -0.5) & (tl >= t_lo) & (tl <= t_hi)
            else:
                big_l = np.floor((t_star - t0) / dt + 0.5)
                tl = t0 + big_l * dt
                inside = (tl >= t_lo) & (tl <= t_hi) & (big_l >= 0)
            xl, yl, _ = self._along_cross(c[idx], b[idx], g[idx], np.clip(tl, t_lo, t_hi))
            frac = np.zeros(idx.size) if continuous else -(xl + k[idx]) / self.camera.dx
            line[idx] = np.where(inside, big_l + frac, np.nan)
            exposure[idx] = np.where(inside, big_l, np.nan)
            sample[idx] = np.where(inside, self.camera.sample_from_focal_plane_y(c[idx], b[idx], yl), np.nan)
        visible = np.isfinite(line) & np.isfinite(sample) & (sample >= -0.5) & (sample <= N_PIXELS - 0.5)

        def nan(a):
            return np.where(visible, a, np.nan)

        return ImagePoints(nan(line), nan(sample), visible, nan(exposure), nan(crossing))

    def line_rate(self, cam: ArrayLike, band: ArrayLike, ground: ArrayLike, t: ArrayLike) -> Array:
        """Along-track image motion ``|d xi / d l| / dx`` (detector pitches per image line, ``(N,)``)
        of ECEF ``ground (N, 3)`` seen by ``cam``/``band`` near time ``t (N,)`` s: ~1 for An, ~1.1 for
        the A cameras, ~0.4 for the D cameras. A focal-plane residual of ``d`` pitches is ``d / rate``
        image lines (central difference over one line time)."""
        g = np.atleast_2d(np.asarray(ground, dtype=float))
        n = g.shape[0]
        c = np.broadcast_to(np.asarray(cam, dtype=int), (n,))
        b = np.broadcast_to(np.asarray(band, dtype=int), (n,))
        tt = np.broadcast_to(np.asarray(t, dtype=float), (n,))
        h = 0.5 * self.camera.line_time
        t_lo, t_hi = self.ephemeris.span
        ta, tb = np.clip(tt - h, t_lo, t_hi - 2 * h), np.clip(tt + h, t_lo + 2 * h, t_hi)
        xa = self._along_cross(c, b, g, ta)[0]
        xb = self._along_cross(c, b, g, tb)[0]
        return np.abs(xb - xa) / self.camera.dx * (self.camera.line_time / (tb - ta))

    # ------------------------------------------------------------------ local frames
    def track_frame(self, ground: ArrayLike, t: ArrayLike) -> tuple[Array, Array, Array]:
        """Local horizontal along-track, cross-track and up unit vectors (ECEF) at ground points.

        Along-track is the orbital +x axis at time ``t`` projected on the local horizontal plane;
        cross-track = along x up, i.e. to the *right* of the flight direction (the orbital +y
        side). Returns three ``(N, 3)`` arrays.
        """
        g = np.atleast_2d(np.asarray(ground, dtype=float))
        lat, lon, _ = ecef_to_geodetic(g)
        up = enu_basis(lat, lon)[..., 2]
        nav = self.nav_state(np.broadcast_to(np.asarray(t, dtype=float), (g.shape[0],)))
        x_ecef = np.einsum("nij,nj->ni", nav.eci_to_ecef, nav.t_go[..., 0])
        along = x_ecef - np.sum(x_ecef * up, axis=-1, keepdims=True) * up
        along /= np.linalg.norm(along, axis=-1, keepdims=True)
        cross = np.cross(along, up)
        return along, cross, up


def cast_from(
    origin: Array,
    direction: Array,
    lam0: Array,
    surface: Callable[[Array, Array], Array],
    tol_m: float = 0.05,
    max_iter: int = 8,
    step_m: float = 20.0,
    fallback: bool = True,
) -> Array:
    """Rays ``origin + lam direction`` (``(N, 3)`` ECEF m, unit directions) cast onto the height
    field ``surface(lat, lon)`` (ellipsoidal m) by secant steps on ``h(lam) - surface(lam)`` from a
    guess ``lam0 (N,)`` (e.g. a neighbouring pixel's solution); rays that have not converged to
    ``tol_m`` in ``max_iter`` steps (a poor guess, a slope nearly parallel to the ray) are cast
    by the bracketed search of :meth:`PassGeometry.pixel_to_ground` (``fallback=False``: left
    NaN, for the caller to cast them together). Returns the ground points ``(N, 3)``, NaN where a
    ray misses."""
    lam0 = np.asarray(lam0, dtype=float)
    idx = np.flatnonzero(np.isfinite(lam0))

    def f(lam: Array, ii: Array) -> Array:
        lat, lon, h = ecef_to_geodetic(origin[ii] + lam[:, None] * direction[ii])
        return h - np.asarray(surface(lat, lon), dtype=float)

    a, b = lam0[idx], lam0[idx] - step_m
    fa, fb = f(a, idx), f(b, idx)
    out_lam = np.full(origin.shape[0], np.nan)
    for _ in range(max_iter):
        with np.errstate(divide="ignore", invalid="ignore"):
            c = b - fb * (b - a) / (fb - fa)
        bad = ~np.isfinite(c) | (np.abs(c - b) > 5e3)
        c = np.where(bad, np.nan, c)
        done = np.abs(c - b) < tol_m
        out_lam[idx[done]] = c[done]
        keep = ~done & ~bad
        if not keep.any():
            break
        idx, a, fa, b = idx[keep], b[keep], fb[keep], c[keep]
        fb = f(b, idx)
    rest = np.flatnonzero(~np.isfinite(out_lam))
    out = origin + out_lam[:, None] * direction
    if rest.size and fallback:  # the bracketed search (rays missing the Earth stay NaN)
        out[rest] = _cast_onto(origin[rest], direction[rest], surface, tol_m)
    return out


def cast_first(
    origin: Array,
    direction: Array,
    surface: Callable[[Array, Array], Array],
    lam_end: Array,
    climb_m: float = 3000.0,
    max_step_m: float = 200.0,
    max_slope: float = 1.5,
    tol_m: float = 0.05,
) -> Array:
    """Where rays ``origin + lam direction`` (``(N, 3)`` ECEF m, unit directions) first meet the
    height field ``surface(lat, lon)`` (ellipsoidal m) coming from the camera: the first crossing
    from above, which is the ground the pixel sees even where terrain hides farther ground (the
    bracketed search of :meth:`PassGeometry.pixel_to_ground` returns *a* crossing). ``lam_end (N,)``
    is a distance at or beyond a crossing (e.g. one that search found).

    Each ray is followed from where it is ``climb_m`` above the surface at ``lam_end`` towards
    ``lam_end`` by steps no terrain of slope below ``max_slope`` can hide a crossing in (sphere
    tracing on the height field): a clearance ``c`` (ray height minus surface) allows
    ``c / (cos z + max_slope sin z)`` metres along a ray of zenith angle ``z``, at most
    ``max_step_m``; the first step that ends below the surface is refined to ``tol_m``. Terrain
    steeper than ``max_slope`` (56 deg by default) and thinner than ``max_step_m`` along the ray can
    be stepped over. Returns ``(N, 3)``, NaN where no crossing is found."""
    origin, direction = np.asarray(origin, dtype=float), np.asarray(direction, dtype=float)
    lam_end = np.asarray(lam_end, dtype=float)
    n = origin.shape[0]
    out = np.full((n, 3), np.nan)
    idx = np.flatnonzero(np.isfinite(lam_end))
    if idx.size == 0:
        return out
    end = origin[idx] + lam_end[idx, None] * direction[idx]
    lat, lon, _ = ecef_to_geodetic(end)
    top = ray_ellipsoid(origin[idx], direction[idx], np.asarray(surface(lat, lon), dtype=float) + climb_m)
    top = np.where(np.isfinite(top) & (top < lam_end[idx]), top, lam_end[idx])
    up = end / np.linalg.norm(end, axis=1, keepdims=True)
    cos_z = np.clip(-np.einsum("ni,ni->n", direction[idx], up), 1e-3, 1.0)  # the ray descends towards the ground
    rate = cos_z + max_slope * np.sqrt(1.0 - cos_z**2)  # clearance lost per metre along the ray, at most

    def f(lam: Array, ii: Array) -> Array:
        la, lo, h = ecef_to_geodetic(origin[ii] + lam[:, None] * direction[ii])
        return h - np.asarray(surface(la, lo), dtype=float)

    lam = top.copy()
    c = f(lam, idx)
    found = np.full(idx.size, np.nan)
    live = np.flatnonzero(c > 0)  # starts above the surface
    found[c <= 0] = lam[c <= 0]  # already at (or in) the surface where it starts
    c_live = c[live]
    while live.size:
        stop = lam_end[idx[live]] + tol_m
        step = np.clip(c_live / rate[live], tol_m, max_step_m)
        nxt = np.minimum(lam[live] + step, stop)
        fn = f(nxt, idx[live])
        below = fn <= 0
        if below.any():
            j = live[below]
            found[j] = _find_root(f, lam[j], nxt[below], tol=tol_m, index=idx[j])
        close = ~below & (fn < tol_m)  # on the surface to the tolerance
        found[live[close]] = nxt[close]
        lam[live] = nxt
        keep = ~below & ~close & (nxt < stop)
        live, c_live = live[keep], fn[keep]
    out[idx] = origin[idx] + found[:, None] * direction[idx]
    return out


def cast_seen(
    origin: Array,
    direction: Array,
    surface: Callable[[Array, Array], Array],
    climb_m: float = 3000.0,
    tol_m: float = 0.05,
) -> Array:
    """The ground rays ``(N, 3)`` see on ``surface``: a crossing by the bracketed search, then the
    first crossing from the camera before it (:func:`cast_first`, searched from ``climb_m`` above
    that crossing). NaN where a ray misses."""
    g = _cast_onto(origin, direction, surface, tol_m)
    lam = np.einsum("ni,ni->n", g - origin, direction)
    return cast_first(origin, direction, surface, lam, climb_m=climb_m, tol_m=tol_m)


def hidden_from_camera(
    origin: Array,
    direction: Array,
    ground: Array,
    surface: Callable[[Array, Array], Array],
    min_distance_m: float = 137.5,
    climb_m: float = 3000.0,
) -> NDArray[np.bool_]:
    """``(N,)``: whether ``surface`` hides each ECEF point ``ground (N, 3)`` from the camera whose
    ray towards it is ``origin + lam direction`` (``(N, 3)``): the ray meets the surface first
    (:func:`cast_first`) more than ``min_distance_m`` (default half a 275 m pixel) before the
    point. Rays that find no crossing count as not hidden."""
    lam = np.einsum("ni,ni->n", ground - origin, direction)
    first = cast_first(origin, direction, surface, lam + 1.0, climb_m=climb_m)
    dist = np.linalg.norm(first - ground, axis=1)
    return np.isfinite(dist) & (dist > min_distance_m)


def hidden_in_image(
    geo: "PassGeometry",
    cams: NDArray[np.int64],
    band: int,
    points: ImagePoints,
    ground: Array,
    surface: Callable[[Array, Array], Array],
    min_distance_m: float = 137.5,
    climb_m: float = 3000.0,
) -> NDArray[np.bool_]:
    """``(N,)``: :func:`hidden_from_camera` for ECEF points ``ground (N, 3)`` imaged by cameras
    ``cams (N,)`` of ``band`` at ``points`` (their :meth:`PassGeometry.ground_to_pixel`), the rays
    being those of the image positions under ``geo``. Points not visible are False."""
    hidden = np.zeros(len(cams), bool)
    vis = np.flatnonzero(points.visible)
    if vis.size == 0:
        return hidden
    origin, direction = geo.pixel_rays(
        np.asarray(cams)[vis], np.full(vis.size, band), points.line[vis], points.sample[vis], np.full(vis.size, np.nan)
    )
    hidden[vis] = hidden_from_camera(origin, direction, ground[vis], surface, min_distance_m, climb_m)
    return hidden


def _cast_onto(origin: Array, direction: Array, surface: Callable[[Array, Array], Array], tol_m: float) -> Array:
    """Rays cast onto the height field ``surface`` by the bracketed search, between the heights
    it can take (from the surface where each ray meets the ellipsoid: 500 m below its lower of
    that and -500 m, 9000 m above its higher of that and 0)."""
    lam0 = ray_ellipsoid(origin, direction, 0.0)
    lat0, lon0, _ = ecef_to_geodetic(origin + lam0[:, None] * direction)
    h0 = np.asarray(surface(lat0, lon0), dtype=float)
    return _cast(
        origin,
        direction,
        np.minimum(h0, -500.0) - 500.0,
        np.maximum(h0, 0.0) + 9000.0,
        lambda lat, lon, idx: np.asarray(surface(lat, lon), dtype=float),
        tol_m,
    )


def _find_root(
    fun: Callable[[Array, Array], Array], a: Array, b: Array, tol: float, index: Array, max_iter: int = 100
) -> Array:
    """Roots of ``fun(t, index)`` bracketed by ``[a, b]`` elementwise, to ``tol`` in ``t``
    (scipy's vectorised Chandrupatla search, ``scipy.optimize.elementwise.find_root``)."""
    from scipy.optimize.elementwise import find_root

    res = find_root(
        lambda t, i: fun(t, i.astype(np.int64)),
        (a, b),
        args=(np.asarray(index, float),),
        tolerances={"xatol": tol, "xrtol": 0.0, "fatol": 0.0, "frtol": 0.0},
        maxiter=max_iter,
    )
    if not np.all(res.success):
        bad = ~np.asarray(res.success)
        raise ConvergenceError(
            f"root search did not converge in {max_iter} iterations for {int(bad.sum())} of "
            f"{bad.size} points (status {sorted(set(np.asarray(res.status)[bad].tolist()))})"
        )
    return np.asarray(res.x, dtype=float)


def _cast(
    origin: Array,
    direction: Array,
    lo_h: Array,
    hi_h: Array,
    h_fun: Callable[[Array, Array, Array], Array],
    tol_m: float,
) -> Array:
    """Find, along each ray, the point whose ellipsoidal height equals ``h_fun(lat, lon)``."""
    lam_a = ray_ellipsoid(origin, direction, hi_h)  # above the surface
    lam_b = ray_ellipsoid(origin, direction, lo_h)  # below the surface
    good = np.isfinite(lam_a) & np.isfinite(lam_b)
    out = np.full(origin.shape, np.nan)
    idx = np.flatnonzero(good)
    if idx.size == 0:
        return out

    def f(lam: Array, ii: Array) -> Array:
        p = origin[ii] + lam[:, None] * direction[ii]
        lat, lon, h = ecef_to_geodetic(p)
        return h - h_fun(lat, lon, ii)

    lam = _find_root(f, lam_a[idx], lam_b[idx], tol=tol_m, index=idx)
    out[idx] = origin[idx] + lam[:, None] * direction[idx]
    return out
