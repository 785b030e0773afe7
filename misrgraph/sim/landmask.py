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

from misrgraph.errors import InputError

__all__ = ["is_land", "cache_directory", "mask_cache_path"]

_ROWS_PER_CHUNK = 400


def _source() -> Path:
    """The data file, found without importing the package (whose import decompresses it)."""
    spec = importlib.util.find_spec("global_land_mask")
    if spec is None or not spec.submodule_search_locations:
        raise InputError("global-land-mask", "not installed", "pip install 'misrgraph[sim]' (the simulator's land mask)")
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
        shape, fortran, dtype = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                                 else np.lib.format.read_array_header_2_0(f))
        return np.frombuffer(f.read(), dtype=dtype).reshape(shape, order="F" if fortran else "C")


def _build(target: Path) -> None:
    """Stream the mask out of the ``.npz`` row block by row block, pack it and write it atomically."""
    with zipfile.ZipFile(_source()) as z, z.open("mask.npy") as f:
        version = np.lib.format.read_magic(f)
        shape, fortran, dtype = (np.lib.format.read_array_header_1_0(f) if version == (1, 0)
                                 else np.lib.format.read_array_header_2_0(f))
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
                out[r0:r0 + n] = np.packbits(block, axis=1)
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
    return (float(glat.min()), float(glat.max()), float(glat[0]), float(glat[1] - glat[0]),
            float(glon.min()), float(glon.max()), float(glon[0]), float(glon[1] - glon[0]))


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
    byte = bits[i.ravel(), (j >> 3).ravel()]
    ocean = (byte >> (7 - (j.ravel() & 7)).astype(np.uint8)) & 1  # the data are an ocean mask
    return (ocean == 0).reshape(la.shape)
