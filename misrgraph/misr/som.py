"""MISR space: a path's Space Oblique Mercator grid, its 180 blocks, and block/line/sample.

MISR's gridded products are laid on one SOM projection per orbit path (1..233), set by the path's
ascending-node longitude. The projection comes from PROJ (``+proj=misrsom +path=P +ellps=WGS84``)
through pyproj; this module adds MISR's grid on top of it:

* **Blocks.** 180 blocks per path, numbered 1..180 from the north. At 1.1 km a block is
  128 lines x 512 samples, at 275 m 512 x 2048 (in general ``128 * 1100 / r`` by
  ``512 * 1100 / r`` for the resolutions in :data:`RESOLUTIONS_M`). Line runs along SOM x (along
  the track, southward for the daylight pass); sample runs along SOM y (across the track).
* **Block offsets.** Consecutive blocks are shifted across the track by a whole number of 1.1 km
  pixels (:data:`RELATIVE_OFFSETS_1100`: 0 or +-16, once -32), so that the 563 km wide block
  follows the ground track's curve on the SOM plane.
* **Pixel convention.** Line and sample are fractional pixel coordinates whose integer values are
  pixel centres; -0.5 is the outer edge of the first pixel (MISR's convention). For block ``b``
  (1-based), line ``l``, sample ``s`` at resolution ``r`` (metres)::

      som_x = X0 + r/2 + ((b - 1) * nline + l) * r
      som_y = Y0 + r/2 + (s + offset[b]) * r

  with ``X0 = 7 460 750 m``, ``Y0 = 527 450 m`` the outer corner of block 1 (the same for every
  path and resolution) and ``offset[b]`` the cumulative offset of block ``b`` in pixels of ``r``.

These are the grid constants MISR publishes with every gridded product (the structural metadata
of the SOM grid and the block offset table); they are tested against the MISR Toolkit's published
conversions in ``tests/misrgraph/misr/test_som.py``.

Units: metres (SOM x/y), degrees (geodetic WGS84 latitude/longitude, longitude in (-180, 180]),
pixels (line, sample). Every function is vectorised: arguments broadcast against each other and
results have the broadcast shape.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import CRS, Transformer

from misrgraph.errors import InputError

__all__ = [
    "N_BLOCKS",
    "N_PATHS",
    "RESOLUTIONS_M",
    "RELATIVE_OFFSETS_1100",
    "BLOCK1_CORNER_SOM",
    "SomGrid",
    "som_crs",
]

Array = NDArray[np.float64]

N_BLOCKS = 180
N_PATHS = 233
#: Resolutions (m) MISR grids its products at; each divides the 1.1 km block evenly.
RESOLUTIONS_M: tuple[int, ...] = (275, 1100, 2200, 4400, 8800, 17600)
_BASE_RES = 1100
_BASE_LINES = 128
_BASE_SAMPLES = 512
#: A SOM point this close (m) outside a block's edge is put on the edge (round-off of a projection
#: round trip); one metre outside is off the grid, as in MISR's own tools.
EDGE_TOL_M = 0.01

#: SOM (x, y) in metres of the outer corner of block 1 (line -0.5, sample -0.5) on every path.
BLOCK1_CORNER_SOM = (7460750.0, 527450.0)

#: Shift across the track (in 1.1 km pixels) of block b+1 against block b, for b = 1..179.
RELATIVE_OFFSETS_1100: tuple[int, ...] = (
    0,
    16,
    0,
    16,
    0,
    0,
    0,
    16,
    0,
    0,
    0,
    0,
    16,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    -16,
    0,
    0,
    0,
    -16,
    0,
    0,
    -16,
    0,
    0,
    -16,
    0,
    -16,
    0,
    -16,
    0,
    -16,
    -16,
    0,
    -16,
    0,
    -16,
    -16,
    0,
    -16,
    -16,
    -16,
    0,
    -16,
    -16,
    -16,
    -16,
    0,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -32,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -32,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    -16,
    0,
    -16,
    -16,
    -16,
    -16,
    -16,
    0,
    -16,
    -16,
    -16,
    0,
    -16,
    -16,
    0,
    -16,
    0,
    -16,
    -16,
    0,
    -16,
    0,
    -16,
    0,
    0,
    -16,
    0,
    -16,
    0,
    0,
    -16,
    0,
    0,
    0,
    0,
    -16,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    0,
    16,
    0,
    0,
    16,
    0,
    0,
    16,
    0,
)
assert len(RELATIVE_OFFSETS_1100) == N_BLOCKS - 1


def _check_path(path: int) -> int:
    if isinstance(path, bool) or not isinstance(path, (int, np.integer)) or not 1 <= int(path) <= N_PATHS:
        raise InputError("path", path, f"an integer in 1..{N_PATHS}")
    return int(path)


@functools.lru_cache(maxsize=N_PATHS)
def som_crs(path: int) -> CRS:
    """The pyproj CRS of ``path``'s SOM projection (metres, WGS84)."""
    return CRS.from_proj4(f"+proj=misrsom +path={_check_path(path)} +ellps=WGS84 +units=m +no_defs +type=crs")


@functools.lru_cache(maxsize=N_PATHS)
def _transformers(path: int) -> tuple[Transformer, Transformer]:
    geo = CRS.from_epsg(4326)
    crs = som_crs(path)
    return (Transformer.from_crs(geo, crs, always_xy=True), Transformer.from_crs(crs, geo, always_xy=True))


def _first_bad(name: str, values: Array, bad: NDArray[np.bool_], expected: str) -> None:
    if np.any(bad):
        idx = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), bad.shape) if bad.ndim else ()
        where = f"{name}[{', '.join(str(int(i)) for i in idx)}]" if idx else name
        raise InputError(where, float(np.asarray(values)[idx]) if idx else float(values), expected)


@dataclass(frozen=True)
class SomGrid:
    """The block grid of one path at one resolution.

    Parameters
    ----------
    path:
        MISR/WRS-2 path, 1..233.
    resolution_m:
        Pixel size in metres, one of :data:`RESOLUTIONS_M` (275 for the camera-resolution
        red band and An, 1100 for the standard 1.1 km products).
    """

    path: int
    resolution_m: int = 1100

    def __post_init__(self) -> None:
        _check_path(self.path)
        if self.resolution_m not in RESOLUTIONS_M:
            raise InputError("resolution_m", self.resolution_m, RESOLUTIONS_M)

    # ------------------------------------------------------------------ grid constants
    @property
    def nline(self) -> int:
        """Lines per block (along the track)."""
        return _BASE_LINES * _BASE_RES // self.resolution_m

    @property
    def nsample(self) -> int:
        """Samples per block (across the track)."""
        return _BASE_SAMPLES * _BASE_RES // self.resolution_m

    @property
    def block_offsets(self) -> NDArray[np.int64]:
        """Cumulative cross-track offset of each block (180,), in pixels of this resolution."""
        rel = (
            np.asarray(RELATIVE_OFFSETS_1100, dtype=np.int64) * (_BASE_RES // self.resolution_m)
            if self.resolution_m <= _BASE_RES
            else np.asarray(RELATIVE_OFFSETS_1100, dtype=np.int64) // (self.resolution_m // _BASE_RES)
        )
        return np.concatenate([[0], np.cumsum(rel)])

    @property
    def crs(self) -> CRS:
        """The path's SOM CRS (pyproj)."""
        return som_crs(self.path)

    # ------------------------------------------------------------------ block/line/sample <-> SOM
    def bls_to_somxy(self, block: ArrayLike, line: ArrayLike, sample: ArrayLike) -> tuple[Array, Array]:
        """SOM (x, y) in metres of fractional (line, sample) in ``block`` (1..180).

        Raises :class:`InputError` naming the first block outside 1..180, or line/sample outside
        [-0.5, nline - 0.5] / [-0.5, nsample - 0.5]."""
        b, ln, s = np.broadcast_arrays(
            np.asarray(block), np.asarray(line, dtype=float), np.asarray(sample, dtype=float)
        )
        bf = b.astype(float)
        _first_bad(
            "block",
            bf,
            ~np.isfinite(bf) | (bf != np.round(bf)) | (bf < 1) | (bf > N_BLOCKS),
            f"an integer in 1..{N_BLOCKS}",
        )
        _first_bad("line", ln, ~(ln >= -0.5) | ~(ln <= self.nline - 0.5), f"a line in [-0.5, {self.nline - 0.5}]")
        _first_bad("sample", s, ~(s >= -0.5) | ~(s <= self.nsample - 0.5), f"a sample in [-0.5, {self.nsample - 0.5}]")
        bi = bf.astype(np.int64)
        r = float(self.resolution_m)
        x = BLOCK1_CORNER_SOM[0] + r / 2 + ((bi - 1) * self.nline + ln) * r
        y = BLOCK1_CORNER_SOM[1] + r / 2 + (s + self.block_offsets[bi - 1]) * r
        return x, y

    def somxy_to_bls(
        self, som_x: ArrayLike, som_y: ArrayLike, *, strict: bool = True
    ) -> tuple[NDArray[np.int64], Array, Array]:
        """(block, line, sample) of SOM (x, y) metres.

        A point on no block (before block 1, after block 180, or beside its block's samples)
        raises :class:`InputError` naming it; with ``strict=False`` it gets block 0 and NaN
        line/sample instead. A point on the boundary between two blocks belongs to the later
        block (line -0.5) unless only the earlier block holds its sample (and a point within
        :data:`EDGE_TOL_M` before the boundary belongs to the later block if only it holds the
        sample); the outer edges of the
        grid belong to it, and a point within :data:`EDGE_TOL_M` outside an edge is put on it."""
        x, y = np.broadcast_arrays(np.asarray(som_x, dtype=float), np.asarray(som_y, dtype=float))
        r = float(self.resolution_m)
        tol = EDGE_TOL_M / r
        i = (x - BLOCK1_CORNER_SOM[0]) / r - 0.5  # continuous line counted from block 1's first line
        j = (y - BLOCK1_CORNER_SOM[1]) / r - 0.5
        with np.errstate(invalid="ignore"):
            bf = np.floor((i + 0.5) / self.nline) + 1
        bf = np.where((bf < 1) & (i >= -0.5 - tol), 1, bf)  # the grid's outer edges are on it
        bf = np.where((bf > N_BLOCKS) & (i <= N_BLOCKS * self.nline - 0.5 + tol), N_BLOCKS, bf)
        ok_b = np.isfinite(bf) & (bf >= 1) & (bf <= N_BLOCKS)
        bi = np.where(ok_b, bf, 1).astype(np.int64)
        line = i - (bi - 1) * self.nline
        sample = j - self.block_offsets[bi - 1]
        # on the boundary of two blocks whose offsets differ, the earlier block may hold the sample
        beside = (sample < -0.5 - tol) | (sample > self.nsample - 0.5 + tol)
        prev = ok_b & beside & (line < -0.5 + tol) & (bi > 1)
        bi = np.where(prev, bi - 1, bi)
        line = np.where(prev, line + self.nline, line)
        sample = np.where(prev, j - self.block_offsets[bi - 1], sample)
        # and a point a rounding error before the boundary may be on the later block's samples only
        beside = (sample < -0.5 - tol) | (sample > self.nsample - 0.5 + tol)
        nxt = ok_b & ~prev & beside & (line > self.nline - 0.5 - tol) & (bi < N_BLOCKS)
        bi = np.where(nxt, bi + 1, bi)
        line = np.where(nxt, line - self.nline, line)
        sample = np.where(nxt, j - self.block_offsets[bi - 1], sample)
        ok = ok_b & (sample >= -0.5 - tol) & (sample <= self.nsample - 0.5 + tol)
        line = np.clip(line, -0.5, self.nline - 0.5)
        sample = np.clip(sample, -0.5, self.nsample - 0.5)
        if strict and not np.all(ok):
            k = np.unravel_index(int(np.flatnonzero(~ok.ravel())[0]), ok.shape) if ok.ndim else ()
            xv, yv = (float(x[k]), float(y[k])) if k else (float(x), float(y))
            why = (
                "a SOM x inside blocks 1..180"
                if not (ok_b[k] if k else bool(ok_b))
                else "a SOM y inside its block's samples"
            )
            raise InputError("som_x, som_y", (xv, yv), f"{why} of path {self.path} at {self.resolution_m} m")
        bi = np.where(ok, bi, 0)
        return bi, np.where(ok, line, np.nan), np.where(ok, sample, np.nan)

    # ------------------------------------------------------------------ geodetic <-> SOM
    def latlon_to_somxy(self, lat: ArrayLike, lon: ArrayLike) -> tuple[Array, Array]:
        """SOM (x, y) metres of geodetic WGS84 latitude/longitude (deg)."""
        la, lo = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
        _first_bad("lat", la, ~(np.abs(la) <= 90.0), "a latitude in [-90, 90] deg")
        _first_bad("lon", lo, ~np.isfinite(lo), "a finite longitude (deg)")
        x, y = _transformers(self.path)[0].transform(lo, la, errcheck=False)
        return np.asarray(x, dtype=float), np.asarray(y, dtype=float)

    def somxy_to_latlon(self, som_x: ArrayLike, som_y: ArrayLike) -> tuple[Array, Array]:
        """Geodetic WGS84 (latitude, longitude) in degrees of SOM (x, y) metres."""
        x, y = np.broadcast_arrays(np.asarray(som_x, dtype=float), np.asarray(som_y, dtype=float))
        _first_bad("som_x", x, ~np.isfinite(x), "finite metres")
        _first_bad("som_y", y, ~np.isfinite(y), "finite metres")
        lon, lat = _transformers(self.path)[1].transform(x, y, errcheck=False)
        lat, lon = np.asarray(lat, dtype=float), np.asarray(lon, dtype=float)
        bad = ~np.isfinite(lat) | ~np.isfinite(lon)
        if np.any(bad):
            k = np.unravel_index(int(np.flatnonzero(bad.ravel())[0]), bad.shape) if bad.ndim else ()
            raise InputError(
                "som_x, som_y",
                (float(x[k]), float(y[k])) if k else (float(x), float(y)),
                f"a point PROJ can invert on path {self.path}'s SOM",
            )
        return lat, lon

    def latlon_to_bls(
        self, lat: ArrayLike, lon: ArrayLike, *, strict: bool = True
    ) -> tuple[NDArray[np.int64], Array, Array]:
        """(block, line, sample) of geodetic latitude/longitude (deg); see :meth:`somxy_to_bls`."""
        return self.somxy_to_bls(*self.latlon_to_somxy(lat, lon), strict=strict)

    def bls_to_latlon(self, block: ArrayLike, line: ArrayLike, sample: ArrayLike) -> tuple[Array, Array]:
        """Geodetic (latitude, longitude) in degrees of (block, line, sample)."""
        return self.somxy_to_latlon(*self.bls_to_somxy(block, line, sample))

    # ------------------------------------------------------------------ whole blocks
    def block_centres(self, block: int, step: int = 1) -> tuple[Array, Array]:
        """SOM (x, y) metres of the pixel centres of ``block``, each ``(nline // step, nsample // step)``
        (every ``step``-th line and sample, starting at 0)."""
        if (
            isinstance(step, bool)
            or not isinstance(step, (int, np.integer))
            or step < 1
            or self.nline % step
            or self.nsample % step
        ):
            raise InputError("step", step, f"a positive divisor of {self.nline} and {self.nsample}")
        ln, s = np.meshgrid(
            np.arange(0, self.nline, step, dtype=float), np.arange(0, self.nsample, step, dtype=float), indexing="ij"
        )
        return self.bls_to_somxy(np.full(ln.shape, block), ln, s)
