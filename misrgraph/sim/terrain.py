"""Simulated terrain and DEM: the truth the simulator draws heights from, and the DEM tiles it
hands the estimator (heights = terrain + a DEM error the estimator does not know).

* :class:`SyntheticTerrain` is a deterministic global height field (m above mean sea level) made
  of random 3-D plane waves evaluated on the sphere (smooth across the antimeridian and the
  poles) with wavelengths from 1.5 km to 300 km and amplitudes growing with wavelength (a
  fractal-like spectrum, relief of a few km, slopes up to ~20 deg), zero over the ocean (real
  land mask, :mod:`misrgraph.sim.landmask`). The waves sum to ~1.2 km on average, so without a
  taper every coast is a cliff of that height within one posting; ``coast_ramp_m`` tapers the
  relief to 0 at the coast over that distance inland (smoothstep of the distance to the coast).
* :func:`simulate_dem_tiles` makes :class:`~misrgraph.model.dem.DemTiles` around points; the
  heights' error is a smooth field of the quality's sigma plus white noise of a tenth of it, a
  function of position (not of the tile), so the local fit's reported sigma is honest.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import InputError
from misrgraph.model.dem import (
    FLAG_BOUNDARY,
    FLAG_LAND,
    FLAG_WATER,
    POSTING_DEG,
    POSTINGS_360,
    QUALITY_SIGMA_M,
    DemTiles,
    dted_lon_posting_factor,
    wrap_deg,
)
from misrgraph.sim.landmask import coast_distance_m, is_land

__all__ = [
    "SyntheticTerrain",
    "land_mask",
    "simulate_dem_tiles",
    "simulate_som_dem",
    "value_noise",
    "ERROR_CORRELATION_POSTINGS",
    "LONG_CORRELATION_POSTINGS",
    "EARTH_R",
]

if TYPE_CHECKING:
    from misrgraph.io.dem import SomDem

Array = NDArray[np.float64]
EARTH_R = 6371e3


def land_mask(lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
    """True over land (1 km resolution; :mod:`misrgraph.sim.landmask`, memory-mapped); any
    longitude (wrapped into [-180, 180))."""
    return is_land(lat, wrap_deg(lon))  # is_land clamps to the grid as global_land_mask did


@dataclass(frozen=True)
class SyntheticTerrain:
    """Deterministic global terrain (m above MSL) from a seed; see the module docstring."""

    seed: int = 0
    n_waves: int = 32
    max_relief_m: float = 2500.0
    #: RMS (m) of sub-posting relief: 24 plane waves of 30-180 m wavelength that a 3" (~90 m)
    #: DEM cannot hold (0: none, the default; the simulator's independent truth sets it)
    fine_relief_m: float = 0.0
    #: distance (m) inland over which the relief rises from 0 at the coast to its full height
    #: (smoothstep; steepest at half-way, 1.5 x relief / ramp). 0: no taper, a cliff at every coast
    coast_ramp_m: float = 0.0

    def _waves(self) -> tuple[Array, Array, Array]:
        cached = self.__dict__.get("_wave_cache")
        if cached is None:
            cached = self._draw_waves()
            object.__setattr__(self, "_wave_cache", cached)  # frozen: a derived cache, not state
        return cached

    def _draw_waves(self) -> tuple[Array, Array, Array]:
        rng = np.random.default_rng(self.seed)
        lam = np.exp(rng.uniform(np.log(1.5e3), np.log(300e3), self.n_waves))
        u = rng.standard_normal((self.n_waves, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        phase = rng.uniform(0, 2 * np.pi, self.n_waves)
        amp = (lam / 300e3) ** 0.9
        amp = amp / amp.sum() * self.max_relief_m
        k = (2 * np.pi / lam)[:, None] * u
        if self.fine_relief_m > 0:
            fr = np.random.default_rng([self.seed, 7])
            n = 24
            lf = np.exp(fr.uniform(np.log(30.0), np.log(180.0), n))
            uf = fr.standard_normal((n, 3))
            uf /= np.linalg.norm(uf, axis=1, keepdims=True)
            # relief = sum amp (1 + sin) / 2: each wave's variance is amp^2 / 8
            k = np.concatenate([k, (2 * np.pi / lf)[:, None] * uf])
            phase = np.concatenate([phase, fr.uniform(0, 2 * np.pi, n)])
            amp = np.concatenate([amp, np.full(n, self.fine_relief_m * np.sqrt(8.0 / n))])
        return k, phase, amp

    def relief(self, lat: ArrayLike, lon: ArrayLike) -> Array:
        """Terrain before the land mask (m): plane waves in 3-D evaluated on the sphere of radius
        6371 km, so it is smooth everywhere, across the antimeridian and over the poles."""
        k, ph, amp = self._waves()
        la = np.radians(np.asarray(lat, dtype=float))
        lo = np.radians(np.asarray(lon, dtype=float))
        xyz = EARTH_R * np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1)
        arg = xyz @ k.T + ph
        return np.sum(amp * (1 + np.sin(arg)), axis=-1) * 0.5

    def coast_taper(self, lat: ArrayLike, lon: ArrayLike, land: NDArray[np.bool_] | None = None) -> Array:
        """The relief's factor (0..1) near the coast: ``smoothstep(d / coast_ramp_m)`` of the
        distance ``d`` (m) to the coast (0 over water); 1 everywhere without a ramp. ``land``: the
        points' land mask when the caller already has it."""
        if self.coast_ramp_m <= 0:
            return np.ones(np.broadcast(np.asarray(lat), np.asarray(lon)).shape)
        t = coast_distance_m(lat, wrap_deg(lon), self.coast_ramp_m, land) / self.coast_ramp_m
        return t * t * (3.0 - 2.0 * t)

    def land_height(self, lat: ArrayLike, lon: ArrayLike, land: NDArray[np.bool_]) -> Array:
        """:meth:`height` for a land mask ``land`` the caller already has (same shape)."""
        h = self.relief(lat, lon)
        if self.coast_ramp_m > 0:
            h = h * self.coast_taper(lat, lon, land)
        return np.where(land, h, 0.0)

    def height(self, lat: ArrayLike, lon: ArrayLike) -> Array:
        """Height above MSL (m): relief over land (times :meth:`coast_taper`), 0 over water."""
        return self.land_height(lat, lon, land_mask(lat, lon))


def _hash_uniform(i: NDArray[np.int64], j: NDArray[np.int64], seed: int) -> Array:
    """Uniform (0, 1) numbers that are a fixed function of integer grid indices and a seed
    (splitmix64 mixing), so every tile holding a posting gives it the same random error."""
    with np.errstate(over="ignore"):
        z = (
            np.asarray(i, np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
            ^ np.asarray(j, np.int64).astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
            ^ np.uint64(seed & 0xFFFFFFFFFFFFFFFF)
        )
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
#: lattice spacing (postings, ~28 km) of the independent truth's long-correlated DEM error
LONG_CORRELATION_POSTINGS = 300


def value_noise(i: NDArray[np.int64], j: NDArray[np.int64], seed: int, spacing: int) -> Array:
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


def simulate_dem_tiles(
    lat: ArrayLike,
    lon: ArrayLike,
    terrain: SyntheticTerrain,
    rng: np.random.Generator,
    size: int = 32,
    dted1_fraction: float = 0.6,
    margin: int = 3,
    pad: int = 8,
    correlated_fraction: float = 0.0,
    true_over_stated: float = 1.0,
    correlation_postings: int = LONG_CORRELATION_POSTINGS,
) -> DemTiles:
    """Tiles of ``size x size`` postings covering each (lat, lon) and the ``pad`` postings
    around it (room for the adjustment to move a landmark), at least ``margin`` postings
    inside a tile, heights = terrain + error: one DEM, stored in tiles.

    The tiles sit on a fixed grid (origins every ``size - 2 margin - 1`` postings), so repeat
    passes over one feature share its tile, and where tiles overlap they hold the same heights:
    the error is a function of position, not of the tile -- a smooth unit-variance field
    correlated over ~5 km (:func:`value_noise`; errors of landmarks 10 km apart are
    independent, as the DEM factor assumes) plus 0.1 white noise per posting, scaled by the
    1-sigma of the quality class of the 1-degree cell (DTED-1 with probability
    ``dted1_fraction``). ``correlated_fraction`` moves that share of the smooth field's variance
    to a field correlated over ~28 km (:data:`LONG_CORRELATION_POSTINGS`), the spacing of tie
    points, which the DEM factor does not know of (the independent truth). ``true_over_stated``:
    the error is that many times the quality class's sigma, which the tiles still state.
    ``correlation_postings``: the correlated share's lattice spacing (postings; points two
    spacings apart are independent; it divides :data:`POSTINGS_360`). A DEM
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
    rj = np.floor(wrap_deg(lo) / (fz * p))[:, None] + off  # columns in the zone's posting
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
    lat0, lon0 = i0 * p, wrap_deg(j0 * p)
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
        glat, glon = gi * p, wrap_deg(gj * p)
        land = land_mask(glat, glon)
        true_h = terrain.land_height(glat, glon, land)
        flags = np.where(land, FLAG_LAND, FLAG_WATER).astype(np.uint8)
        # boundary: a land posting next to water or vice versa
        pd = np.pad(land, ((0, 0), (1, 1), (1, 1)), mode="edge")
        nb = pd[:, :-2, 1:-1] ^ land | pd[:, 2:, 1:-1] ^ land | pd[:, 1:-1, :-2] ^ land | pd[:, 1:-1, 2:] ^ land
        flags[nb] = FLAG_BOUNDARY
        sig_q = np.where(cell_quality(glat, glon) == 1, QUALITY_SIGMA_M[1], QUALITY_SIGMA_M[2])
        smooth = value_noise(gi, gj, seed + 1, ERROR_CORRELATION_POSTINGS)
        if correlated_fraction > 0:
            smooth = np.sqrt(1.0 - correlated_fraction) * smooth + np.sqrt(correlated_fraction) * value_noise(
                gi, gj, seed + 3, correlation_postings
            )
        err = sig_q * true_over_stated * (smooth + 0.1 * _hash_normal(gi, gj, seed + 2))
        return true_h + err, flags

    # in chunks of tiles: the terrain's wave sum is (tiles, n, n, waves) in memory
    heights = np.zeros((len(cells), size, size))
    flags = np.zeros((len(cells), size, size), np.uint8)
    for c in range(0, len(cells), 128):
        heights[c : c + 128], flags[c : c + 128] = chunk(i0[c : c + 128], j0[c : c + 128], fzc[c : c + 128])
    quality = cell_quality(lat0 + size / 2 * p, wrap_deg(lon0 + size / 2 * fzc * p))
    return DemTiles(lat0, lon0, heights, flags, quality, p, fzc * p)


#: lattice spacing (275 m grid points, ~5 km) of a SOM DEM's correlated error
SOM_DEM_CORRELATION_PX = 18


def simulate_som_dem(
    surface: "Callable[[Array, Array], Array]",
    path: int,
    blocks: tuple[int, int],
    seed: int,
    sigma_m: float = 10.0,
    resolution_m: int = 275,
) -> "SomDem":
    """A DEM on ``path``'s SOM grid over ``blocks[0]..blocks[1]``: the true surface
    (ellipsoidal m) at every pixel centre plus an error of 1-sigma ``sigma_m`` -- a smooth field
    correlated over ~5 km (:func:`value_noise` on the grid, 0.95 of the variance) and white noise
    per point (0.05). Over water the heights are the surface's (0 m) exactly. ``sigma_m`` 10 m is
    an SRTM-class DEM; the terrain parallax it leaves is ``sigma tan(view angle)`` (28 m, 0.1 pixel
    at 275 m, for the D cameras)."""
    from misrgraph.io.dem import SomDem
    from misrgraph.misr.som import SomGrid

    grid = SomGrid(int(path), int(resolution_m))
    bl = np.arange(int(blocks[0]), int(blocks[1]) + 1)
    out = np.zeros((bl.size, grid.nline, grid.nsample), np.float32)
    li, si = np.meshgrid(np.arange(grid.nline), np.arange(grid.nsample), indexing="ij")
    for k, b in enumerate(bl):
        lat, lon = grid.somxy_to_latlon(*grid.block_centres(int(b)))
        h = np.asarray(surface(lat, lon), dtype=float)
        gi = (int(b) - 1) * grid.nline + li  # path-continuous line index: the error field crosses block edges
        err = np.sqrt(0.95) * value_noise(gi, si, seed, SOM_DEM_CORRELATION_PX) + np.sqrt(0.05) * _hash_normal(
            gi, si, seed + 1
        )
        out[k] = np.where(land_mask(lat, lon), h + sigma_m * err, h)
    return SomDem(
        int(path), int(resolution_m), bl, out, float(sigma_m), source=f"simulated (surface + {sigma_m} m error)"
    )
