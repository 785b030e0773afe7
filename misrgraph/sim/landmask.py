"""Land/water mask for the simulator, at 1/120 deg (about 1 km), without its gigabyte of RAM.

The data are ``global-land-mask``'s (the GLOBE dataset: ``21600 x 43200`` ocean flags, shipped as a
2.5 MB compressed ``.npz``). Importing that package decompresses the whole mask into 0.93 GB of
memory in every process that calls it. Here the mask is streamed out of the ``.npz`` once per
machine, 400 rows at a time, packed to one bit per cell (117 MB) and cached as a ``.npy`` file
(``$MISRGRAPH_CACHE``, else ``$XDG_CACHE_HOME/misrgraph``, else ``~/.cache/misrgraph``; the
system's temporary directory if that cannot be written) that every
later lookup memory-maps: a process holds only the pages its points touch. The cache is written
atomically (temporary file, then rename) and named by the SHA-256 of the source ``.npz``, so a
new release of the data builds a new cache.

Lookups index the grid exactly as ``global_land_mask.globe.is_land`` does (tested against it).
:func:`coast_distance_m` gives each land point's distance to the nearest water cell (the simulator
tapers its relief towards the coast with it).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from misrgraph.errors import InputError

__all__ = ["is_land", "coast_distance_m", "cache_directory", "mask_cache_path"]

_ROWS_PER_CHUNK = 400


def _source() -> Path:
    """The data file, found without importing the package (whose import decompresses it)."""
    spec = importlib.util.find_spec("global_land_mask")
    if spec is None or not spec.submodule_search_locations:
        raise InputError(
            "global-land-mask", "not installed", "pip install 'misrgraph[sim]' (the simulator's land mask)"
        )
    return Path(list(spec.submodule_search_locations)[0]) / "globe_combined_mask_compressed.npz"


def cache_directory() -> Path:
    """Where the packed mask is cached (see the module docstring)."""
    if os.environ.get("MISRGRAPH_CACHE"):
        return Path(os.environ["MISRGRAPH_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "misrgraph"


def mask_cache_path() -> Path:
    """The packed mask's cache file for the installed data."""
    digest = hashlib.sha256(_source().read_bytes()).hexdigest()[:16]
    return cache_directory() / f"landmask-{digest}.npy"


def _read_npy_member(z: zipfile.ZipFile, name: str) -> NDArray:
    with z.open(name) as f:
        version = np.lib.format.read_magic(f)
        shape, fortran, dtype = (
            np.lib.format.read_array_header_1_0(f) if version == (1, 0) else np.lib.format.read_array_header_2_0(f)
        )
        return np.frombuffer(f.read(), dtype=dtype).reshape(shape, order="F" if fortran else "C")


def _build(target: Path) -> None:
    """Stream the mask out of the ``.npz`` row block by row block, pack it and write it atomically."""
    with zipfile.ZipFile(_source()) as z, z.open("mask.npy") as f:
        version = np.lib.format.read_magic(f)
        shape, fortran, dtype = (
            np.lib.format.read_array_header_1_0(f) if version == (1, 0) else np.lib.format.read_array_header_2_0(f)
        )
        if fortran or dtype != np.bool_ or len(shape) != 2:
            raise InputError("global-land-mask data", (shape, str(dtype), fortran), "a C-ordered 2-D boolean mask")
        rows, cols = shape
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=target.parent)
        os.close(fd)
        try:
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(rows, (cols + 7) // 8))
            for r0 in range(0, rows, _ROWS_PER_CHUNK):
                n = min(_ROWS_PER_CHUNK, rows - r0)
                block = np.frombuffer(f.read(n * cols), dtype=np.bool_).reshape(n, cols)
                out[r0 : r0 + n] = np.packbits(block, axis=1)
            out.flush()
            del out
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


@functools.lru_cache(maxsize=1)
def _mask() -> tuple[NDArray[np.uint8], NDArray[np.float64], NDArray[np.float64]]:
    path = mask_cache_path()
    if not path.exists():
        try:
            _build(path)
        except OSError:  # a read-only cache directory: fall back to the temporary directory
            path = Path(tempfile.gettempdir()) / f"misrgraph-{os.getuid()}" / path.name
            if not path.exists():
                _build(path)
    with zipfile.ZipFile(_source()) as z:
        lat, lon = _read_npy_member(z, "lat.npy"), _read_npy_member(z, "lon.npy")
    return np.load(path, mmap_mode="r"), lat, lon


@functools.lru_cache(maxsize=1)
def _axes() -> tuple[float, float, float, float, float, float, float, float]:
    """The grid's (min, max, first, step) of latitude, then of longitude (deg), computed once:
    :func:`is_land` is called with a few dozen points at a time by the ray casting."""
    _, glat, glon = _mask()
    return (
        float(glat.min()),
        float(glat.max()),
        float(glat[0]),
        float(glat[1] - glat[0]),
        float(glon.min()),
        float(glon.max()),
        float(glon[0]),
        float(glon[1] - glon[0]),
    )


def is_land(lat: ArrayLike, lon: ArrayLike) -> NDArray[np.bool_]:
    """True over land at geodetic ``lat, lon`` (deg; any broadcastable shapes). Latitudes outside
    the grid are clamped to its first/last row, as ``global_land_mask`` does; longitudes must be in
    [-180, 180)."""
    bits = _mask()[0]
    lat_min, lat_max, lat0, dlat, lon_min, lon_max, lon0, dlon = _axes()
    la, lo = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
    la = np.clip(la, lat_min, lat_max)
    lo = np.clip(lo, lon_min, lon_max)
    i = ((la - lat0) / dlat).astype(np.int64)
    j = ((lo - lon0) / dlon).astype(np.int64)
    return np.asarray(_ocean(bits, i, j) == 0).reshape(la.shape)


def _ocean(bits: NDArray[np.uint8], i: NDArray[np.int64], j: NDArray[np.int64]) -> NDArray[np.uint8]:
    """The packed mask's ocean flag (1: water) of cells (row ``i``, column ``j``), broadcast."""
    return (bits[i, j >> 3] >> (7 - (j & 7)).astype(np.uint8)) & 1


#: cells per side of the tiles (1 deg) whose distance fields :func:`coast_distance_m` caches
_TILE_CELLS = 120
#: metres per degree of latitude on the 6371 km sphere (the cells' size for distances)
_M_PER_DEG = 6371e3 * np.pi / 180.0


@functools.lru_cache(maxsize=1024)
def _tile_distance(ti: int, tj: int, cap_m: float) -> tuple[NDArray[np.float32], int, int]:
    """Distance (m) from every cell centre of the 1-deg tile ``(ti, tj)`` (row/column tile
    indices of the mask grid), plus a margin wide enough to hold ``cap_m`` each side, to the
    nearest water cell centre, at most ``cap_m`` plus a cell (so that water beyond the margin
    never matters). Returns the field (rows, columns) and the margin (rows, columns) in cells."""
    bits = _mask()[0]
    n_rows, n_cols = bits.shape[0], bits.shape[1] * 8
    _, _, lat0, dlat, _, _, _, dlon = _axes()
    dy = abs(dlat) * _M_PER_DEG
    # the tile's poleward edge has the narrowest columns
    edge_lat = max(abs(lat0 + ti * _TILE_CELLS * dlat), abs(lat0 + (ti + 1) * _TILE_CELLS * dlat))
    dx = abs(dlon) * _M_PER_DEG * max(np.cos(np.radians(min(edge_lat, 90.0))), 0.01)
    mr, mc = int(np.ceil(cap_m / dy)) + 2, int(np.ceil(cap_m / dx)) + 2
    r = np.clip(np.arange(ti * _TILE_CELLS - mr, (ti + 1) * _TILE_CELLS + mr), 0, n_rows - 1)
    c = np.arange(tj * _TILE_CELLS - mc, (tj + 1) * _TILE_CELLS + mc) % n_cols
    land = _ocean(bits, r[:, None], c[None, :]) == 0
    if land.all():
        return np.full(land.shape, cap_m + dy, np.float32), mr, mc
    lat_mid = lat0 + (ti + 0.5) * _TILE_CELLS * dlat
    dx_mid = abs(dlon) * _M_PER_DEG * max(np.cos(np.radians(lat_mid)), 0.01)
    d = ndimage.distance_transform_edt(land, sampling=(dy, dx_mid))
    return np.minimum(d, cap_m + dy).astype(np.float32), mr, mc


def coast_distance_m(
    lat: ArrayLike, lon: ArrayLike, cap_m: float, land: NDArray[np.bool_] | None = None
) -> NDArray[np.float64]:
    """Distance (m) from geodetic ``lat, lon`` (deg; longitudes in [-180, 180); any broadcastable
    shapes) to the coast of the land mask, 0 over water, capped at ``cap_m`` (farther is
    ``cap_m``). Continuous: the distance of each cell centre to the nearest water cell centre,
    bilinear between cell centres, less half a cell (the coast is a cell edge, half a cell from
    the centres either side), so it is near 0 along the mask's coast (under half a cell on its land
    side: where two rows' coasts differ, their blend can miss the edge) and grows by about a metre
    per metre inland; within 0.71 cell of the distance to the nearest water (tested). Cells are
    1/120 deg on the 6371 km sphere. ``land``: :func:`is_land` of the points when the caller
    already has it (the broadcast shape)."""
    cap = float(cap_m)
    la, lo = np.broadcast_arrays(np.asarray(lat, dtype=float), np.asarray(lon, dtype=float))
    out = np.zeros(la.shape)
    land = is_land(la, lo) if land is None else np.broadcast_to(land, la.shape)
    if cap <= 0 or not land.any():
        return out
    lat_min, lat_max, lat0, dlat, _, _, lon0, dlon = _axes()
    n_rows, n_bytes = _mask()[0].shape
    n_cols = 8 * n_bytes
    u = (np.clip(la[land], lat_min, lat_max) - lat0) / dlat - 0.5  # cell i's centre at u = i
    v = (lo[land] - lon0) / dlon - 0.5
    i0, j0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - i0, v - j0
    i0 = np.clip(i0, 0, n_rows - 2)
    j0 = j0 % n_cols
    ti, tj = i0 // _TILE_CELLS, j0 // _TILE_CELLS
    key = ti * (n_cols // _TILE_CELLS + 1) + tj
    vals = np.empty(key.size)
    order = np.argsort(key, kind="stable")  # the points grouped by tile
    _, starts = np.unique(key[order], return_index=True)
    for sel in np.split(order, starts[1:]):
        a, b = int(ti[sel[0]]), int(tj[sel[0]])
        d, mr, mc = _tile_distance(a, b, cap)
        ri, ci = i0[sel] - a * _TILE_CELLS + mr, j0[sel] - b * _TILE_CELLS + mc
        wu, wv = fu[sel], fv[sel]
        vals[sel] = (1 - wu) * ((1 - wv) * d[ri, ci] + wv * d[ri, ci + 1]) + wu * (
            (1 - wv) * d[ri + 1, ci] + wv * d[ri + 1, ci + 1]
        )
    half = 0.5 * abs(dlat) * _M_PER_DEG  # rows are the longer side (cos(lat) <= 1 shortens columns)
    out[land] = np.clip(vals - half, 0.0, cap)
    return out
