"""Digital elevation model: synthetic terrain, 3-arcsecond tiles, local surface fits (eq. 8).

* :class:`SyntheticTerrain` is a deterministic global height field (m above mean sea level) made
  of random 3-D plane waves evaluated on the sphere (smooth across the antimeridian and the
  poles) with wavelengths from 1.5 km to 300 km and amplitudes growing with wavelength (a
  fractal-like spectrum, relief of a few km, slopes up to ~20 deg), zero over the ocean (real
  land mask from ``global-land-mask``).
* :class:`DemTiles` holds square tiles of heights (``size x size`` postings) with a
  land/water/boundary flag per posting and a quality identifier per tile (``1`` = DTED-1 class,
  30 m vertical 1 sigma, about 60 % of tiles; ``2`` = reduced accuracy, 60-120 m). Postings are
  3 arcseconds in latitude; in longitude they widen with latitude as DTED's do
  (:func:`dted_lon_posting_deg`: 3" to 50 deg, 6" to 70, 9" to 75, 12" to 80, 18" beyond). Tiles
  are found by their centres on the unit sphere and columns wrap in longitude, so lookups work
  across the antimeridian; tiles stop at the poles (rows beyond +-90 deg are never made). The
  heights' error is a smooth field of the quality's sigma plus white noise of a tenth of it, a
  function of position (not of the tile), so the local fit's reported sigma is honest.
* :func:`fit_local_surface` fits the surface of eq. 8 around a point from at most 6 x 6 postings
  -- bilinear (2 x 2), biquadratic (least squares on 4 x 4) or bicubic (4 x 4) --
  (bicubic 4 x 4 interpolation is the most accurate on real terrain, measured) and returns
  height, gradient and the height's sigma.
* Heights are above mean sea level; :class:`Geoid` converts to ellipsoidal heights. For simulated
  data the named option ``"zero"`` (geoid = ellipsoid) is allowed; a constant undulation or any
  callable ``N(lat, lon)`` in metres can be given instead.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_h5, create_dataset, open_h5, read_attr, read_dataset, write_dataset

__all__ = [
    "SyntheticTerrain",
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


def _wrap_deg(d: ArrayLike) -> Array:
    return (np.asarray(d, dtype=float) + 180.0) % 360.0 - 180.0


def _unit(lat: ArrayLike, lon: ArrayLike) -> Array:
    la, lo = np.radians(np.asarray(lat, dtype=float)), np.radians(np.asarray(lon, dtype=float))
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)


def land_mask(lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
    """True over land (``global-land-mask``, 1 km resolution)."""
    from global_land_mask import globe

    la = np.clip(np.asarray(lat, dtype=float), -89.999, 89.999)
    lo = (np.asarray(lon, dtype=float) + 180.0) % 360.0 - 180.0
    lo = np.clip(lo, -179.999, 179.999)
    return np.asarray(globe.is_land(la, lo), dtype=bool)


@dataclass(frozen=True)
class SyntheticTerrain:
    """Deterministic global terrain (m above MSL) from a seed; see the module docstring."""

    seed: int = 0
    n_waves: int = 32
    max_relief_m: float = 2500.0

    def _waves(self) -> tuple[Array, Array, Array]:
        rng = np.random.default_rng(self.seed)
        lam = np.exp(rng.uniform(np.log(1.5e3), np.log(300e3), self.n_waves))
        u = rng.standard_normal((self.n_waves, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        phase = rng.uniform(0, 2 * np.pi, self.n_waves)
        amp = (lam / 300e3) ** 0.9
        amp = amp / amp.sum() * self.max_relief_m
        return (2 * np.pi / lam)[:, None] * u, phase, amp

    def relief(self, lat: ArrayLike, lon: ArrayLike) -> Array:
        """Terrain before the land mask (m): plane waves in 3-D evaluated on the sphere of radius
        6371 km, so it is smooth everywhere, across the antimeridian and over the poles."""
        k, ph, amp = self._waves()
        la = np.radians(np.asarray(lat, dtype=float))
        lo = np.radians(np.asarray(lon, dtype=float))
        xyz = EARTH_R * np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
        arg = xyz @ k.T + ph
        return np.sum(amp * (1 + np.sin(arg)), axis=-1) * 0.5

    def height(self, lat: ArrayLike, lon: ArrayLike) -> Array:
        """Height above MSL (m): relief over land, 0 over water."""
        h = self.relief(lat, lon)
        return np.where(land_mask(lat, lon), h, 0.0)


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
    height: the DEM quality sigma combined with the fit's residual RMS); ``valid`` False where the
    point is not covered by a tile.
    """

    height: Array
    dh_dlat: Array
    dh_dlon: Array
    sigma: Array
    valid: NDArray[np.bool_]
    #: index of the tile each point was read from (-1 where not covered)
    tile: NDArray[np.int64] | None = None


#: method -> (degree of the tensor-product polynomial, window size in postings). Measured on the
#: real Jacksboro 3-arcsec DEM (fit on every second posting, predict the ones between): RMS error
#: bilinear 8.4 m, biquadratic 4x4 6.3 m, bicubic 4x4 6.3 m, bicubic least squares on 6x6 12.4 m
#: (over-smooths) -- so the bicubic is a 4x4 interpolant. Of those, cubic convolution (Keys,
#: a = -0.5) is used because it is C1-continuous across postings (a Lagrange window that shifts
#: at each posting is not even continuous there, which stalls Levenberg-Marquardt); it reproduces
#: polynomials up to degree 2 and equals the 4-point Lagrange value at posting midpoints.
_METHODS = {"bilinear": (1, 2), "biquadratic": (2, 4), "bicubic": (3, 4)}


def _keys_weights(t: Array) -> tuple[Array, Array]:
    """Cubic-convolution weights (a = -0.5) of postings -1, 0, 1, 2 at fraction t, and d/dt."""
    t2, t3 = t * t, t * t * t
    w = np.stack([-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1, -1.5 * t3 + 2 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2], -1)
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


def _cubic_convolution(heights: Array, r: Array, c: Array, tile: NDArray[np.int64] | None = None) -> tuple[Array, Array, Array, Array]:
    """C1 bicubic (cubic convolution) on ``heights (R, C)`` or, with ``tile``, ``heights (T, R, C)``."""
    hh = heights if tile is not None else heights[None]
    t = tile if tile is not None else np.zeros(np.size(r), np.int64)
    ir = np.clip(np.floor(r).astype(int), 1, hh.shape[1] - 3)
    ic = np.clip(np.floor(c).astype(int), 1, hh.shape[2] - 3)
    off = np.arange(-1, 3)
    z = hh[t[:, None, None], (ir[:, None, None] + off[None, :, None]), (ic[:, None, None] + off[None, None, :])]
    return _cubic_convolution_windows(z, r - ir, c - ic)


def _hash_uniform(i: NDArray[np.int64], j: NDArray[np.int64], seed: int) -> Array:
    """Uniform (0, 1) numbers that are a fixed function of integer grid indices and a seed
    (splitmix64 mixing), so every tile holding a posting gives it the same random error."""
    with np.errstate(over="ignore"):
        z = (np.asarray(i, np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             ^ np.asarray(j, np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
             ^ np.uint64(seed & 0xFFFFFFFFFFFFFFFF))
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return ((z >> np.uint64(11)).astype(np.float64) + 0.5) / float(2**53)


def _hash_normal(i: NDArray[np.int64], j: NDArray[np.int64], seed: int) -> Array:
    """Standard normal numbers as a fixed function of grid indices (Box-Muller on two hashes)."""
    u1 = _hash_uniform(i, j, seed)
    u2 = _hash_uniform(i, j, seed ^ 0x5DEECE66D)
    return np.sqrt(-2.0 * np.log(u1)) * np.cos(2 * np.pi * u2)


#: lattice spacing (postings, ~4.6 km) of the simulated DEM's correlated error
ERROR_CORRELATION_POSTINGS = 50


def _value_noise(i: NDArray[np.int64], j: NDArray[np.int64], seed: int, spacing: int) -> Array:
    """Unit-variance, C1 random field on the posting grid: independent N(0, 1) values on a lattice
    every ``spacing`` postings, blended with smoothstep weights ``w`` and divided by
    ``sqrt(sum w^2)`` (so the variance is 1 everywhere). Points two lattice cells apart are
    independent. ``j`` is a longitude index: the lattice wraps at 360 deg (continuous across the
    antimeridian; ``spacing`` divides :data:`POSTINGS_360`)."""
    fi = np.asarray(i, float) / spacing
    fj = np.asarray(j, float) / spacing
    a, b = np.floor(fi).astype(np.int64), np.floor(fj).astype(np.int64)
    si, sj = fi - a, fj - b
    si, sj = si * si * (3 - 2 * si), sj * sj * (3 - 2 * sj)
    w = [(1 - si) * (1 - sj), si * (1 - sj), (1 - si) * sj, si * sj]
    period = POSTINGS_360 // spacing
    z = [_hash_normal(a + da, (b + db) % period, seed) for da, db in ((0, 0), (1, 0), (0, 1), (1, 1))]
    num = sum(wk * zk for wk, zk in zip(w, z))
    return num / np.sqrt(sum(wk * wk for wk in w))


@dataclass
class DemTiles:
    """Square DEM tiles: ``posting_deg`` (3") in latitude, ``lon_posting (T,)`` deg per tile in
    longitude (DTED's zones, :func:`dted_lon_posting_deg`; default ``posting_deg``).

    ``lat0, lon0 (T,)`` deg of posting ``[0, 0]`` (south-west corner; ``lon0`` in [-180, 180),
    columns continue east across the antimeridian); ``heights (T, n, n)`` m above MSL (row =
    latitude index northward, column = longitude eastward); ``flags (T, n, n)`` (1 land, 2 water,
    3 boundary); ``quality (T,)`` identifiers (see :data:`QUALITY_SIGMA_M`).
    """

    lat0: Array
    lon0: Array
    heights: Array
    flags: NDArray[np.uint8]
    quality: NDArray[np.int64]
    posting_deg: float = POSTING_DEG
    lon_posting: Array | None = None

    def __post_init__(self) -> None:
        self.lat0 = np.asarray(self.lat0, dtype=float)
        self.lon0 = np.asarray(self.lon0, dtype=float)
        self.lon_posting = (np.full(self.lat0.shape, float(self.posting_deg)) if self.lon_posting is None
                            else np.asarray(self.lon_posting, dtype=float))
        self.heights = np.asarray(self.heights, dtype=float)
        self.flags = np.asarray(self.flags, dtype=np.uint8)
        self.quality = np.asarray(self.quality, dtype=np.int64)
        t = self.lat0.size
        if self.heights.ndim != 3 or self.heights.shape[0] != t or self.heights.shape[1] != self.heights.shape[2]:
            raise InputError("dem.heights", self.heights.shape, f"shape ({t}, n, n)")
        if self.flags.shape != self.heights.shape:
            raise InputError("dem.flags", self.flags.shape, f"shape {self.heights.shape}")
        if self.lon0.shape != (t,) or self.quality.shape != (t,) or self.lon_posting.shape != (t,):
            raise InputError("dem.lon0/quality/lon_posting", (self.lon0.shape, self.quality.shape, self.lon_posting.shape),
                             f"shape ({t},)")
        if t and not (np.all(np.isfinite(self.lat0)) and np.all(np.abs(self.lat0) <= 90.0)):
            raise InputError("dem.lat0", self.lat0[~(np.abs(self.lat0) <= 90.0)][:1].tolist(), "finite, within [-90, 90] deg")
        if t and not np.all(self.lat0 + (self.size - 1) * self.posting_deg <= 90.0 + 1e-9):
            raise InputError("dem.lat0", float(self.lat0.max()), f"tiles ending at or below 90 deg "
                                                                 f"(lat0 <= {90.0 - (self.size - 1) * self.posting_deg:.6f})")
        if t and not (np.all(np.isfinite(self.lon_posting)) and np.all(self.lon_posting > 0)):
            raise InputError("dem.lon_posting", float(self.lon_posting.min()), "positive, finite (deg)")
        bad = set(np.unique(self.quality).tolist()) - set(QUALITY_SIGMA_M)
        if bad:
            raise InputError("dem.quality", sorted(bad)[0], tuple(str(q) for q in QUALITY_SIGMA_M))

    @property
    def size(self) -> int:
        return int(self.heights.shape[1])

    @classmethod
    def around(
        cls,
        lat: ArrayLike,
        lon: ArrayLike,
        terrain: SyntheticTerrain,
        rng: np.random.Generator,
        size: int = 32,
        dted1_fraction: float = 0.6,
        margin: int = 3,
        pad: int = 8,
    ) -> "DemTiles":
        """Tiles of ``size x size`` postings covering each (lat, lon) and the ``pad`` postings
        around it (room for the adjustment to move a landmark), at least ``margin`` postings
        inside a tile, heights = terrain + error: one DEM, stored in tiles.

        The tiles sit on a fixed grid (origins every ``size - 2 margin - 1`` postings), so repeat
        passes over one feature share its tile, and where tiles overlap they hold the same heights:
        the error is a function of position, not of the tile -- a smooth unit-variance field
        correlated over ~5 km (:func:`_value_noise`; errors of landmarks 10 km apart are
        independent, as the DEM factor assumes) plus 0.1 white noise per posting, scaled by the
        1-sigma of the quality class of the 1-degree cell (DTED-1 with probability
        ``dted1_fraction``). A DEM
        whose value depended on which of two overlapping tiles was picked would be discontinuous
        (seen: re-linearisation cycling in repeat-path scenarios).
        """
        la = np.atleast_1d(np.asarray(lat, dtype=float))
        lo = np.atleast_1d(np.asarray(lon, dtype=float))
        p = POSTING_DEG
        step = size - 2 * margin - 1
        if step < 1:
            raise InputError("dem tile size", size, f"at least {2 * margin + 2} postings")
        off = np.array([-pad, 0, pad])
        fz = dted_lon_posting_factor(la)  # the point's DTED zone: longitude posting / 3"
        ri = np.floor(la / p)[:, None] + off  # (N, 3) rows of the point and its padded corners
        rj = np.floor(_wrap_deg(lo) / (fz * p))[:, None] + off  # columns in the zone's posting
        ti = np.floor((ri - margin) / step).astype(np.int64)
        tj = np.floor((rj - margin) / step).astype(np.int64)
        tz = np.broadcast_to(fz[:, None, None], (la.size, 3, 3))
        triples = np.stack(np.broadcast_arrays(ti[:, :, None], tj[:, None, :], tz), -1).reshape(-1, 3)
        cells = np.unique(triples, axis=0) if la.size else np.zeros((0, 3), np.int64)
        # tiles stop at the poles: rows beyond +-90 deg are never made
        last = int(round(90.0 / p))
        i0 = np.clip(cells[:, 0] * step, -last, last - (size - 1))
        cells = np.unique(np.stack([i0, cells[:, 1], cells[:, 2]], -1), axis=0) if la.size else cells
        i0, fzc = cells[:, 0], cells[:, 2]
        j0 = cells[:, 1] * step * fzc  # in 3" units
        lat0, lon0 = i0 * p, _wrap_deg(j0 * p)
        g = np.arange(size)
        seed = int(rng.integers(0, 2**62))

        def cell_quality(glat_: Array, glon_: Array) -> NDArray[np.int64]:
            u = _hash_uniform(np.floor(glat_).astype(np.int64), np.floor(glon_).astype(np.int64), seed)
            return np.where(u < dted1_fraction, 1, 2)

        def chunk(c0: NDArray[np.int64], c1: NDArray[np.int64], f: NDArray[np.int64]) -> tuple[Array, NDArray[np.uint8]]:
            """Heights and flags of the tiles with origin postings (c0, c1) (3" units) and
            longitude posting f x 3"."""
            gi = c0[:, None, None] + g[None, :, None] + 0 * g[None, None, :]
            gj = (c1[:, None, None] + 0 * g[None, :, None] + g[None, None, :] * f[:, None, None]) % POSTINGS_360
            glat, glon = gi * p, _wrap_deg(gj * p)
            land = land_mask(glat, glon)
            true_h = np.where(land, terrain.relief(glat, glon), 0.0)
            flags = np.where(land, FLAG_LAND, FLAG_WATER).astype(np.uint8)
            # boundary: a land posting next to water or vice versa
            pd = np.pad(land, ((0, 0), (1, 1), (1, 1)), mode="edge")
            nb = pd[:, :-2, 1:-1] ^ land | pd[:, 2:, 1:-1] ^ land | pd[:, 1:-1, :-2] ^ land | pd[:, 1:-1, 2:] ^ land
            flags[nb] = FLAG_BOUNDARY
            sig_q = np.where(cell_quality(glat, glon) == 1, QUALITY_SIGMA_M[1], QUALITY_SIGMA_M[2])
            err = sig_q * (_value_noise(gi, gj, seed + 1, ERROR_CORRELATION_POSTINGS) + 0.1 * _hash_normal(gi, gj, seed + 2))
            return true_h + err, flags

        # in chunks of tiles: the terrain's wave sum is (tiles, n, n, waves) in memory
        heights = np.zeros((len(cells), size, size))
        flags = np.zeros((len(cells), size, size), np.uint8)
        for c in range(0, len(cells), 128):
            heights[c:c + 128], flags[c:c + 128] = chunk(i0[c:c + 128], j0[c:c + 128], fzc[c:c + 128])
        quality = cell_quality(lat0 + size / 2 * p, _wrap_deg(lon0 + size / 2 * fzc * p))
        return cls(lat0, lon0, heights, flags, quality, p, fzc * p)

    def tile_of(self, lat: ArrayLike, lon: ArrayLike, margin: int = 3,
                hint: NDArray[np.int64] | None = None) -> NDArray[np.int64]:
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
            c = _wrap_deg(lo - self.lon0[hh]) / self.lon_posting[hh]
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
        c = _wrap_deg(lo[:, None] - self.lon0[cand]) / self.lon_posting[cand]
        inside = (r >= margin) & (r <= self.size - 1 - margin) & (c >= margin) & (c <= self.size - 1 - margin)
        first = np.argmax(inside, axis=1)  # candidates come nearest first
        ok = inside[np.arange(la.size), first]
        out[ok] = cand[np.arange(la.size), first][ok]
        return out

    def posting_position(self, tile: NDArray[np.int64], row: ArrayLike, col: ArrayLike) -> tuple[Array, Array]:
        """(lat, lon) in deg (lon in [-180, 180)) of postings ``(row, col)`` of tiles ``tile``."""
        t = np.asarray(tile, np.int64)
        return (self.lat0[t] + np.asarray(row, float) * self.posting_deg,
                _wrap_deg(self.lon0[t] + np.asarray(col, float) * self.lon_posting[t]))

    def surface(self, lat: ArrayLike, lon: ArrayLike, method: str = "bicubic") -> LocalSurface:
        """Local surface fit (eq. 8) at points; see :func:`fit_local_surface`."""
        return fit_local_surface(self, lat, lon, method)

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | os.PathLike[str]) -> None:
        with atomic_h5(path, "dem") as f:
            g = f.create_group("tiles")
            g.attrs["posting_deg"] = self.posting_deg
            g.attrs["size"] = self.size
            g.attrs["height_reference"] = "mean sea level"
            write_dataset(g, "lat0", self.lat0, units="deg", description="latitude of posting [0, 0] (south-west)")
            write_dataset(g, "lon0", self.lon0, units="deg", description="longitude of posting [0, 0]")
            write_dataset(g, "lon_posting", self.lon_posting, units="deg", description="longitude posting per tile")
            create_dataset(g, "heights", self.heights.astype(np.float32), compression="gzip", shuffle=True)
            g["heights"].attrs["units"] = "m above MSL"
            create_dataset(g, "flags", self.flags, compression="gzip")
            g["flags"].attrs["meaning"] = "1 land, 2 water, 3 boundary"
            write_dataset(g, "quality", self.quality, units="1", meaning="1: DTED-1 30 m; 2: 60 m; 3: 120 m (1 sigma)")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "DemTiles":
        with open_h5(path, "dem") as f:
            if "tiles" not in f:
                raise FileFormatError(path, "missing group /tiles")
            g = f["tiles"]
            lat0 = read_dataset(g, "lat0", (None,))
            t = lat0.size
            n = int(read_attr(g, "size"))
            return cls(
                lat0,
                read_dataset(g, "lon0", (t,)),
                read_dataset(g, "heights", (t, n, n)),
                read_dataset(g, "flags", (t, n, n), dtype=np.uint8),
                read_dataset(g, "quality", (t,), dtype=np.int64),
                float(read_attr(g, "posting_deg")),
                read_dataset(g, "lon_posting", (t,)),
            )


def fit_local_surface(dem: DemTiles, lat: ArrayLike, lon: ArrayLike, method: str = "bicubic",
                      hint: NDArray[np.int64] | None = None) -> LocalSurface:
    """Eq. 8 at points (deg): height above MSL, gradient (m/deg) and 1-sigma (m); ``hint``: the
    ``tile`` of an earlier result for the same points (see :meth:`DemTiles.tile_of`)."""
    la = np.atleast_1d(np.asarray(lat, dtype=float))
    lo = np.atleast_1d(np.asarray(lon, dtype=float))
    n = la.size
    out = LocalSurface(np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, bool))
    tile = dem.tile_of(la, lo, hint=hint)
    out.tile = tile
    sel = np.flatnonzero(tile >= 0)
    if sel.size == 0:
        return out
    t = tile[sel]
    r = (la[sel] - dem.lat0[t]) / dem.posting_deg
    c = _wrap_deg(lo[sel] - dem.lon0[t]) / dem.lon_posting[t]
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
    out.sigma[sel] = np.sqrt(sig_q[dem.quality[t]] ** 2 + rms**2)
    out.valid[sel] = True
    return out
