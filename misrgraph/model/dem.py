"""Digital elevation model: 3-arcsecond tiles and local surface fits (eq. 8).

The simulated terrain and DEM are made by :mod:`misrgraph.sim.terrain`; files are read and written
by :mod:`misrgraph.io.dem`.

* :class:`DemTiles` holds square tiles of heights (``size x size`` postings) with a
  land/water/boundary flag per posting and a quality identifier per tile (``1`` = DTED-1 class,
  30 m vertical 1 sigma, about 60 % of tiles; ``2`` = reduced accuracy, 60-120 m). Postings are
  3 arcseconds in latitude; in longitude they widen with latitude as DTED's do
  (:func:`dted_lon_posting_deg`: 3" to 50 deg, 6" to 70, 9" to 75, 12" to 80, 18" beyond). Tiles
  are found by their centres on the unit sphere and columns wrap in longitude, so lookups work
  across the antimeridian; tiles stop at the poles (rows beyond +-90 deg are never made). The
  simulated heights' error is described in :mod:`misrgraph.sim.terrain`.
* :func:`fit_local_surface` fits the surface of eq. 8 around a point from at most 6 x 6 postings
  -- bilinear (2 x 2), biquadratic (least squares on 4 x 4) or bicubic (4 x 4) --
  (bicubic 4 x 4 interpolation is the most accurate on real terrain, measured) and returns
  height, gradient and the height's sigma.
* Heights are above mean sea level; :class:`Geoid` converts to ellipsoidal heights. For simulated
  data the named option ``"zero"`` (geoid = ellipsoid) is allowed; a constant undulation or any
  callable ``N(lat, lon)`` in metres can be given instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import InputError

__all__ = [
    "bilinear",
    "DemTiles",
    "LocalSurface",
    "fit_local_surface",
    "Geoid",
    "POSTING_DEG",
    "dted_lon_posting_deg",
    "QUALITY_SIGMA_M",
    "FLAG_LAND",
    "FLAG_WATER",
    "FLAG_BOUNDARY",
    "POSTINGS_360",
    "dted_lon_posting_factor",
    "wrap_deg",
]

Array = NDArray[np.float64]
POSTING_DEG = 3.0 / 3600.0
FLAG_LAND, FLAG_WATER, FLAG_BOUNDARY = 1, 2, 3
#: Vertical 1-sigma (m) of each quality identifier.
QUALITY_SIGMA_M = {1: 30.0, 2: 60.0, 3: 120.0}
EARTH_R = 6371e3
#: DTED longitude spacing: (upper |latitude| bound of the zone in deg, multiple of the 3" posting).
DTED_LON_ZONES = ((50.0, 1), (70.0, 2), (75.0, 3), (80.0, 4), (90.0, 6))
#: 3" postings around the equator.
POSTINGS_360 = 432000


def dted_lon_posting_factor(lat: ArrayLike) -> NDArray[np.int64]:
    """The longitude posting as a multiple of 3" at latitude(s) ``lat`` (deg), DTED's zones."""
    a = np.abs(np.asarray(lat, dtype=float))
    out = np.full(a.shape, DTED_LON_ZONES[-1][1], np.int64)
    for bound, factor in reversed(DTED_LON_ZONES[:-1]):
        out = np.where(a < bound, factor, out)
    return out


def dted_lon_posting_deg(lat: ArrayLike) -> Array:
    """DTED longitude posting (deg) at latitude(s) ``lat`` (deg): 3" below 50 deg, then 6", 9",
    12" and 18" above 80 deg."""
    return dted_lon_posting_factor(lat) * POSTING_DEG


def wrap_deg(d: ArrayLike) -> Array:
    """Longitude(s) wrapped into [-180, 180) deg."""
    return (np.asarray(d, dtype=float) + 180.0) % 360.0 - 180.0


def _unit(lat: ArrayLike, lon: ArrayLike) -> Array:
    la, lo = np.radians(np.asarray(lat, dtype=float)), np.radians(np.asarray(lon, dtype=float))
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)


@dataclass
class Geoid:
    """Geoid undulation ``N`` (m) so that ``h_ellipsoid = h_msl + N``.

    ``Geoid("zero")`` (allowed for simulated data), ``Geoid("constant", value=N)`` or
    ``Geoid("function", function=callable(lat, lon) -> N)``.
    """

    kind: str = "zero"
    value: float = 0.0
    function: Callable[[Array, Array], Array] | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("zero", "constant", "function"):
            raise InputError("geoid", self.kind, ("zero", "constant", "function"))
        if self.kind == "function" and self.function is None:
            raise InputError("geoid.function", None, "a callable N(lat_deg, lon_deg) in metres")

    def undulation(self, lat: ArrayLike, lon: ArrayLike) -> Array:
        shape = np.broadcast(np.asarray(lat), np.asarray(lon)).shape
        if self.kind == "zero":
            return np.zeros(shape)
        if self.kind == "constant":
            return np.full(shape, self.value)
        assert self.function is not None
        return np.asarray(self.function(np.asarray(lat, float), np.asarray(lon, float)), dtype=float)


@dataclass
class LocalSurface:
    """Result of :func:`fit_local_surface` per point (arrays ``(N,)``).

    ``height`` m above MSL; ``dh_dlat``, ``dh_dlon`` in m per degree; ``sigma`` m (1 sigma of the
    height: the DEM's stated sigma combined with the fit's residual RMS, ``sqrt(stated^2 +
    rms^2)``); ``valid`` False where the point is not covered by a tile; ``stated`` m the DEM's
    stated sigma alone (the posting nearest the point, or its tile's quality class).
    """

    height: Array
    dh_dlat: Array
    dh_dlon: Array
    sigma: Array
    valid: NDArray[np.bool_]
    #: index of the tile each point was read from (-1 where not covered)
    tile: NDArray[np.int64] | None = None
    stated: Array | None = None


#: method -> (degree of the tensor-product polynomial, window size in postings). Measured on the
#: real Jacksboro 3-arcsec DEM (fit on every second posting, predict the ones between): RMS error
#: bilinear 8.4 m, biquadratic 4x4 6.3 m, bicubic 4x4 6.3 m, bicubic least squares on 6x6 12.4 m
#: (over-smooths) -- so the bicubic is a 4x4 interpolant. Of those, cubic convolution (Keys,
#: a = -0.5) is used because it is C1-continuous across postings (a Lagrange window that shifts
#: at each posting is not even continuous there, which stalls Levenberg-Marquardt); it reproduces
#: polynomials up to degree 2 and equals the 4-point Lagrange value at posting midpoints.
_METHODS = {"bilinear": (1, 2), "biquadratic": (2, 4), "bicubic": (3, 4)}


def bilinear(z: ArrayLike, r: Array, c: Array) -> Array:
    """Bilinear interpolation of ``z (R, C)`` at fractional pixel-centre indices ``r, c``; NaN
    where a neighbour with a non-zero weight is no-data (NaN) or outside the raster. A point on a
    posting takes that posting's value whatever its neighbours hold. NaN indices give NaN."""
    z = np.asarray(z)
    r, c = np.broadcast_arrays(np.asarray(r, dtype=float), np.asarray(c, dtype=float))
    finite = np.isfinite(r) & np.isfinite(c)
    r, c = np.where(finite, r, -2.0), np.where(finite, c, -2.0)  # outside the raster: NaN below
    r = np.where(np.abs(r - np.round(r)) < 1e-6, np.round(r), r)  # on a posting, to round-off
    c = np.where(np.abs(c - np.round(c)) < 1e-6, np.round(c), c)
    r0, c0 = np.floor(r).astype(np.int64), np.floor(c).astype(np.int64)
    fr, fc = r - r0, c - c0
    out = np.zeros(r.shape)
    for dr, wr in ((0, 1.0 - fr), (1, fr)):
        for dc, wc in ((0, 1.0 - fc), (1, fc)):
            w = wr * wc
            rr, cc = r0 + dr, c0 + dc
            inside = (rr >= 0) & (rr < z.shape[0]) & (cc >= 0) & (cc < z.shape[1])
            v = z[np.clip(rr, 0, z.shape[0] - 1), np.clip(cc, 0, z.shape[1] - 1)]
            v = np.where(inside, v, np.nan)
            out = out + np.where(w > 0, w * v, 0.0)
    return out


def _keys_weights(t: Array) -> tuple[Array, Array]:
    """Cubic-convolution weights (a = -0.5) of postings -1, 0, 1, 2 at fraction t, and d/dt."""
    t2, t3 = t * t, t * t * t
    w = np.stack(
        [-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1, -1.5 * t3 + 2 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2], -1
    )
    dw = np.stack([-1.5 * t2 + 2 * t - 0.5, 4.5 * t2 - 5 * t, -4.5 * t2 + 4 * t + 0.5, 1.5 * t2 - t], -1)
    return w, dw


def _basis(u: Array, v: Array, degree: int) -> tuple[Array, Array, Array]:
    """Tensor-product monomials u^i v^j (i, j <= degree) and their u- and v-derivatives."""
    p = np.arange(degree + 1)
    ui, vj = u[..., None] ** p, v[..., None] ** p
    dui = np.where(p > 0, p * u[..., None] ** np.maximum(p - 1, 0), 0.0)
    dvj = np.where(p > 0, p * v[..., None] ** np.maximum(p - 1, 0), 0.0)
    b = (ui[..., :, None] * vj[..., None, :]).reshape(*u.shape, -1)
    bu = (dui[..., :, None] * vj[..., None, :]).reshape(*u.shape, -1)
    bv = (ui[..., :, None] * dvj[..., None, :]).reshape(*u.shape, -1)
    return b, bu, bv


def fit_grid_surface(
    heights: Array, row: Array, col: Array, method: str = "bicubic"
) -> tuple[Array, Array, Array, Array]:
    """Fit eq. 8 on a regular grid at fractional (row, col) positions.

    ``heights (R, C)``; returns height, dh/drow, dh/dcol (per posting) and the fit's residual RMS,
    each ``(N,)``. The window is the ``n x n`` postings around the point (n = 2, 4, 4 for
    bilinear, biquadratic, bicubic); points too close to the edge use the nearest full window.
    The bilinear and bicubic fits interpolate exactly, so the returned RMS -- a proxy for the
    interpolation error -- is the residual RMS of the next lower-order fit on the same window (a
    plane for bilinear, the biquadratic for bicubic); for the biquadratic it is its own residual.
    """
    if method not in _METHODS:
        raise InputError("dem method", method, tuple(_METHODS))
    degree, n = _METHODS[method]
    r = np.asarray(row, dtype=float)
    c = np.asarray(col, dtype=float)
    if method == "bicubic":
        return _cubic_convolution(heights, np.atleast_1d(r), np.atleast_1d(c))
    r0 = np.clip(np.floor(r).astype(int) - (n // 2 - 1), 0, heights.shape[0] - n)
    c0 = np.clip(np.floor(c).astype(int) - (n // 2 - 1), 0, heights.shape[1] - n)
    off = np.arange(n)
    rr = r0[:, None, None] + off[None, :, None]
    cc = c0[:, None, None] + off[None, None, :]
    z = heights[rr, cc].reshape(r.size, n * n)
    # local coordinates centred on the window, in postings, scaled to about [-1, 1]
    half = (n - 1) / 2.0
    gu, gv = np.meshgrid(off - half, off - half, indexing="ij")
    b, _, _ = _basis(gu.ravel() / max(half, 0.5), gv.ravel() / max(half, 0.5), degree)
    coef, *_ = np.linalg.lstsq(b, z.T, rcond=None)  # same design for every window
    if degree == 1:
        lower = np.stack([np.ones(n * n), gu.ravel(), gv.ravel()], -1)
    elif degree == 3:
        lower = _basis(gu.ravel() / max(half, 0.5), gv.ravel() / max(half, 0.5), 2)[0]
    else:
        lower = b
    lc, *_ = np.linalg.lstsq(lower, z.T, rcond=None)
    resid = z.T - lower @ lc
    rms = np.sqrt(np.sum(resid**2, axis=0) / max(n * n - lower.shape[1], 1))
    u = (r - r0 - half) / max(half, 0.5)
    v = (c - c0 - half) / max(half, 0.5)
    bp, bu, bv = _basis(u, v, degree)
    h = np.sum(bp * coef.T, axis=-1)
    dh_dr = np.sum(bu * coef.T, axis=-1) / max(half, 0.5)
    dh_dc = np.sum(bv * coef.T, axis=-1) / max(half, 0.5)
    return h, dh_dr, dh_dc, rms


_GU, _GV = np.meshgrid(np.arange(-1, 3) - 0.5, np.arange(-1, 3) - 0.5, indexing="ij")
_QUAD16 = _basis(_GU.ravel() / 1.5, _GV.ravel() / 1.5, 2)[0]
#: residual projector of the biquadratic least-squares fit on a 4 x 4 window: r = (I - B B^+) z
_QUAD16_RESID = np.eye(16) - _QUAD16 @ np.linalg.pinv(_QUAD16)


def _cubic_convolution_windows(z: Array, tr: Array, tc: Array) -> tuple[Array, Array, Array, Array]:
    """Value, d/drow, d/dcol and roughness RMS from 4 x 4 windows ``z (N, 4, 4)`` at fractions."""
    wr, dwr = _keys_weights(tr)
    wc, dwc = _keys_weights(tc)
    h = np.einsum("ni,nij,nj->n", wr, z, wc)
    dh_dr = np.einsum("ni,nij,nj->n", dwr, z, wc)
    dh_dc = np.einsum("ni,nij,nj->n", wr, z, dwc)
    resid = z.reshape(-1, 16) @ _QUAD16_RESID.T
    rms = np.sqrt(np.sum(resid**2, axis=1) / (16 - _QUAD16.shape[1]))
    return h, dh_dr, dh_dc, rms


def _cubic_convolution(
    heights: Array, r: Array, c: Array, tile: NDArray[np.int64] | None = None
) -> tuple[Array, Array, Array, Array]:
    """C1 bicubic (cubic convolution) on ``heights (R, C)`` or, with ``tile``, ``heights (T, R, C)``."""
    hh = heights if tile is not None else heights[None]
    t = tile if tile is not None else np.zeros(np.size(r), np.int64)
    ir = np.clip(np.floor(r).astype(int), 1, hh.shape[1] - 3)
    ic = np.clip(np.floor(c).astype(int), 1, hh.shape[2] - 3)
    off = np.arange(-1, 3)
    z = hh[t[:, None, None], (ir[:, None, None] + off[None, :, None]), (ic[:, None, None] + off[None, None, :])]
    return _cubic_convolution_windows(z, r - ir, c - ic)


@dataclass
class DemTiles:
    """Square DEM tiles: ``posting_deg`` (3") in latitude, ``lon_posting (T,)`` deg per tile in
    longitude (DTED's zones, :func:`dted_lon_posting_deg`; default ``posting_deg``).

    ``lat0, lon0 (T,)`` deg of posting ``[0, 0]`` (south-west corner; ``lon0`` in [-180, 180),
    columns continue east across the antimeridian); ``heights (T, n, n)`` m above MSL (row =
    latitude index northward, column = longitude eastward); ``flags (T, n, n)`` (1 land, 2 water,
    3 boundary); ``quality (T,)`` identifiers (see :data:`QUALITY_SIGMA_M`); ``sigma_m (T, n, n)``
    (optional) each posting's stated 1-sigma in metres, which replaces the quality class's
    (e.g. an AGP's ``StdDevSceneElev``).
    """

    lat0: Array
    lon0: Array
    heights: Array
    flags: NDArray[np.uint8]
    quality: NDArray[np.int64]
    posting_deg: float = POSTING_DEG
    lon_posting: Array | None = None
    sigma_m: Array | None = None

    def __post_init__(self) -> None:
        self.lat0 = np.asarray(self.lat0, dtype=float)
        self.lon0 = np.asarray(self.lon0, dtype=float)
        self.lon_posting = (
            np.full(self.lat0.shape, float(self.posting_deg))
            if self.lon_posting is None
            else np.asarray(self.lon_posting, dtype=float)
        )
        self.heights = np.asarray(self.heights, dtype=float)
        self.flags = np.asarray(self.flags, dtype=np.uint8)
        self.quality = np.asarray(self.quality, dtype=np.int64)
        t = self.lat0.size
        if self.heights.ndim != 3 or self.heights.shape[0] != t or self.heights.shape[1] != self.heights.shape[2]:
            raise InputError("dem.heights", self.heights.shape, f"shape ({t}, n, n)")
        if self.flags.shape != self.heights.shape:
            raise InputError("dem.flags", self.flags.shape, f"shape {self.heights.shape}")
        if self.lon0.shape != (t,) or self.quality.shape != (t,) or self.lon_posting.shape != (t,):
            raise InputError(
                "dem.lon0/quality/lon_posting",
                (self.lon0.shape, self.quality.shape, self.lon_posting.shape),
                f"shape ({t},)",
            )
        if t and not (np.all(np.isfinite(self.lat0)) and np.all(np.abs(self.lat0) <= 90.0)):
            raise InputError(
                "dem.lat0", self.lat0[~(np.abs(self.lat0) <= 90.0)][:1].tolist(), "finite, within [-90, 90] deg"
            )
        if t and not np.all(self.lat0 + (self.size - 1) * self.posting_deg <= 90.0 + 1e-9):
            raise InputError(
                "dem.lat0",
                float(self.lat0.max()),
                f"tiles ending at or below 90 deg (lat0 <= {90.0 - (self.size - 1) * self.posting_deg:.6f})",
            )
        if t and not (np.all(np.isfinite(self.lon_posting)) and np.all(self.lon_posting > 0)):
            raise InputError("dem.lon_posting", float(self.lon_posting.min()), "positive, finite (deg)")
        bad = set(np.unique(self.quality).tolist()) - set(QUALITY_SIGMA_M)
        if bad:
            raise InputError("dem.quality", sorted(bad)[0], tuple(str(q) for q in QUALITY_SIGMA_M))
        if self.sigma_m is not None:
            self.sigma_m = np.asarray(self.sigma_m, dtype=float)
            if self.sigma_m.shape != self.heights.shape:
                raise InputError("dem.sigma_m", self.sigma_m.shape, f"shape {self.heights.shape}")
            if not (np.all(np.isfinite(self.sigma_m)) and np.all(self.sigma_m >= 0)):
                raise InputError("dem.sigma_m", float(np.nanmin(self.sigma_m)), "finite sigmas >= 0 (m)")

    @property
    def size(self) -> int:
        return int(self.heights.shape[1])

    def smoothed(self, sigma_postings: float) -> "DemTiles":
        """The same tiles with heights low-passed by a Gaussian of ``sigma_postings`` postings (1
        sigma, along rows and columns; 0: ``self``), cut at 2 postings so that every posting
        the local surface can read (2 or more from a tile's edge: :meth:`tile_of`'s margin 3 and
        the 4 x 4 window) is filtered from real postings only: overlapping tiles keep the same
        heights there. Cached per sigma on this object.

        Why: posting-level roughness (white DEM noise, relief aliased from below the posting)
        curves the surface at the scale of a landmark's horizontal uncertainty; the sum of those
        curvatures over hundreds of landmarks makes the DEM cost non-quadratic along the pass's
        common horizontal position (docs/explanation/design.md, "The DEM weight")."""
        s = float(sigma_postings)
        if not (np.isfinite(s) and s >= 0):
            raise InputError("dem smoothing", sigma_postings, "a sigma >= 0 in DEM postings")
        if s == 0:
            return self
        cache = self.__dict__.setdefault("_smoothed", {})
        if s not in cache:
            from scipy.ndimage import gaussian_filter

            h = gaussian_filter(self.heights, sigma=(0.0, s, s), mode="nearest", truncate=2.0 / s)
            cache[s] = DemTiles(
                self.lat0, self.lon0, h, self.flags, self.quality, self.posting_deg, self.lon_posting, self.sigma_m
            )
        return cache[s]

    def tile_of(
        self, lat: ArrayLike, lon: ArrayLike, margin: int = 3, hint: NDArray[np.int64] | None = None
    ) -> NDArray[np.int64]:
        """Index of a tile containing each point at least ``margin`` postings from its edge (-1 if none);
        among several, the tile whose centre is nearest.

        ``hint (N,)``: tiles from an earlier call for the same points (an iterative solver moving
        landmarks by metres); a hinted tile that still contains its point is kept, and only the
        others are searched. Overlapping tiles hold the same DEM (:meth:`around`), so the heights
        read are the same either way.
        """
        la = np.atleast_1d(np.asarray(lat, dtype=float))
        lo = np.atleast_1d(np.asarray(lon, dtype=float))
        out = -np.ones(la.size, np.int64)
        if self.lat0.size == 0 or la.size == 0:
            return out
        if hint is not None and np.shape(hint) == la.shape:
            h = np.asarray(hint, np.int64)
            ok = h >= 0
            hh = np.where(ok, h, 0)
            r = (la - self.lat0[hh]) / self.posting_deg
            c = wrap_deg(lo - self.lon0[hh]) / self.lon_posting[hh]
            ok &= (r >= margin) & (r <= self.size - 1 - margin) & (c >= margin) & (c <= self.size - 1 - margin)
            out[ok] = h[ok]
            rest = np.flatnonzero(~ok)
            if rest.size:
                out[rest] = self.tile_of(la[rest], lo[rest], margin)
            return out
        if not hasattr(self, "_tree"):
            from scipy.spatial import cKDTree

            # centres on the unit sphere: nearness that knows the antimeridian and the poles
            half = (self.size - 1) / 2
            self._tree = cKDTree(_unit(self.lat0 + half * self.posting_deg, self.lon0 + half * self.lon_posting))
        k = min(8, self.lat0.size)
        _, cand = self._tree.query(_unit(la, lo), k=k)
        cand = cand.reshape(la.size, k)
        r = (la[:, None] - self.lat0[cand]) / self.posting_deg
        c = wrap_deg(lo[:, None] - self.lon0[cand]) / self.lon_posting[cand]
        inside = (r >= margin) & (r <= self.size - 1 - margin) & (c >= margin) & (c <= self.size - 1 - margin)
        first = np.argmax(inside, axis=1)  # candidates come nearest first
        ok = inside[np.arange(la.size), first]
        out[ok] = cand[np.arange(la.size), first][ok]
        return out

    def posting_position(self, tile: NDArray[np.int64], row: ArrayLike, col: ArrayLike) -> tuple[Array, Array]:
        """(lat, lon) in deg (lon in [-180, 180)) of postings ``(row, col)`` of tiles ``tile``."""
        t = np.asarray(tile, np.int64)
        return (
            self.lat0[t] + np.asarray(row, float) * self.posting_deg,
            wrap_deg(self.lon0[t] + np.asarray(col, float) * self.lon_posting[t]),
        )

    def surface(self, lat: ArrayLike, lon: ArrayLike, method: str = "bicubic") -> LocalSurface:
        """Local surface fit (eq. 8) at points; see :func:`fit_local_surface`."""
        return fit_local_surface(self, lat, lon, method)


def fit_local_surface(
    dem: DemTiles, lat: ArrayLike, lon: ArrayLike, method: str = "bicubic", hint: NDArray[np.int64] | None = None
) -> LocalSurface:
    """Eq. 8 at points (deg): height above MSL, gradient (m/deg) and 1-sigma (m); ``hint``: the
    ``tile`` of an earlier result for the same points (see :meth:`DemTiles.tile_of`)."""
    la = np.atleast_1d(np.asarray(lat, dtype=float))
    lo = np.atleast_1d(np.asarray(lon, dtype=float))
    n = la.size
    out = LocalSurface(
        np.full(n, np.nan),
        np.full(n, np.nan),
        np.full(n, np.nan),
        np.full(n, np.nan),
        np.zeros(n, bool),
        stated=np.full(n, np.nan),
    )
    tile = dem.tile_of(la, lo, hint=hint)
    out.tile = tile
    sel = np.flatnonzero(tile >= 0)
    if sel.size == 0:
        return out
    t = tile[sel]
    r = (la[sel] - dem.lat0[t]) / dem.posting_deg
    c = wrap_deg(lo[sel] - dem.lon0[t]) / dem.lon_posting[t]
    if method == "bicubic":
        h, dr, dc, rms = _cubic_convolution(dem.heights, r, c, t)
    else:
        h, dr, dc, rms = (np.empty(sel.size) for _ in range(4))
        for tt in np.unique(t):
            m = t == tt
            h[m], dr[m], dc[m], rms[m] = fit_grid_surface(dem.heights[tt], r[m], c[m], method)
    sig_q = np.zeros(max(QUALITY_SIGMA_M) + 1)
    for q, v in QUALITY_SIGMA_M.items():
        sig_q[q] = v
    out.height[sel] = h
    out.dh_dlat[sel] = dr / dem.posting_deg
    out.dh_dlon[sel] = dc / dem.lon_posting[t]
    if dem.sigma_m is not None:
        # the stated sigma of the posting nearest each point
        ir = np.clip(np.rint(r).astype(np.int64), 0, dem.size - 1)
        ic = np.clip(np.rint(c).astype(np.int64), 0, dem.size - 1)
        stated = dem.sigma_m[t, ir, ic]
    else:
        stated = sig_q[dem.quality[t]]
    out.sigma[sel] = np.sqrt(stated**2 + rms**2)
    out.stated[sel] = stated
    out.valid[sel] = True
    return out
