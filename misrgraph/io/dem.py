"""DEM files (HDF5 kind ``dem``): the one reader and writer; and DEMs on a path's SOM grid (kind
``som_dem``, :class:`SomDem`), the heights Reference Orbit Imagery is orthorectified with.

Layout: group ``/tiles`` with attributes ``posting_deg``, ``size``, ``height_reference`` and
datasets ``lat0, lon0, lon_posting (T,)`` deg, ``heights (T, n, n)`` m above
``height_reference`` (float32; mean sea level for simulated DEMs, the WGS84 ellipsoid for a
raster imported with a geoid), ``flags (T, n, n)`` (1 land, 2 water, 3 boundary), ``quality (T,)`` (see
:data:`misrgraph.model.dem.QUALITY_SIGMA_M`) and, where the source states one (an AGP), ``sigma_m
(T, n, n)``: each posting's 1-sigma (m), which replaces the quality class's.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_h5, create_dataset, open_h5, read_attr, read_dataset, write_dataset
from misrgraph.model.dem import DemTiles

__all__ = ["save_dem", "read_dem", "SomDem", "save_som_dem", "read_som_dem"]


def save_dem(dem: DemTiles, path: str | os.PathLike[str], height_reference: str = "mean sea level") -> None:
    """Write DEM tiles atomically (HDF5 kind ``dem``); ``height_reference`` says what the heights
    are above (the simulator's zero geoid makes mean sea level the ellipsoid)."""
    with atomic_h5(path, "dem") as f:
        g = f.create_group("tiles")
        g.attrs["posting_deg"] = dem.posting_deg
        g.attrs["size"] = dem.size
        g.attrs["height_reference"] = height_reference
        write_dataset(g, "lat0", dem.lat0, units="deg", description="latitude of posting [0, 0] (south-west)")
        write_dataset(g, "lon0", dem.lon0, units="deg", description="longitude of posting [0, 0]")
        write_dataset(g, "lon_posting", dem.lon_posting, units="deg", description="longitude posting per tile")
        create_dataset(g, "heights", dem.heights.astype(np.float32), compression="gzip", shuffle=True)
        g["heights"].attrs["units"] = "m"
        g["heights"].attrs["reference"] = height_reference
        create_dataset(g, "flags", dem.flags, compression="gzip")
        g["flags"].attrs["meaning"] = "1 land, 2 water, 3 boundary"
        write_dataset(g, "quality", dem.quality, units="1", meaning="1: DTED-1 30 m; 2: 60 m; 3: 120 m (1 sigma)")
        if dem.sigma_m is not None:
            create_dataset(g, "sigma_m", dem.sigma_m.astype(np.float32), compression="gzip", shuffle=True)
            g["sigma_m"].attrs["units"] = "m"
            g["sigma_m"].attrs["meaning"] = "each posting's stated 1 sigma; replaces the quality class's"


def read_dem(path: str | os.PathLike[str]) -> DemTiles:
    """Read DEM tiles written by :func:`save_dem`, validating every field."""
    with open_h5(path, "dem") as f:
        if "tiles" not in f:
            raise FileFormatError(path, "missing group /tiles")
        g = f["tiles"]
        lat0 = read_dataset(g, "lat0", (None,))
        t = lat0.size
        n = int(read_attr(g, "size"))
        return DemTiles(
            lat0,
            read_dataset(g, "lon0", (t,)),
            read_dataset(g, "heights", (t, n, n)),
            read_dataset(g, "flags", (t, n, n), dtype=np.uint8),
            read_dataset(g, "quality", (t,), dtype=np.int64),
            float(read_attr(g, "posting_deg")),
            read_dataset(g, "lon_posting", (t,)),
            read_dataset(g, "sigma_m", (t, n, n)) if "sigma_m" in g else None,
        )


@dataclass
class SomDem:
    """Heights on blocks of a path's SOM grid: ``heights (B, nline, nsample)`` m above the WGS84
    ellipsoid (float32; NaN where unknown) at the pixel centres of ``blocks (B,)`` at
    ``resolution_m`` (275: 512 x 2048 per block), with their 1-sigma ``sigma_m``."""

    path: int
    resolution_m: int
    blocks: NDArray[np.int64]
    heights: NDArray[np.float32]
    sigma_m: float
    source: str = ""

    def __post_init__(self) -> None:
        from misrgraph.misr.som import SomGrid

        self.blocks = np.asarray(self.blocks, dtype=np.int64).ravel()
        grid = SomGrid(int(self.path), int(self.resolution_m))
        shape = (self.blocks.size, grid.nline, grid.nsample)
        self.heights = np.asarray(self.heights, dtype=np.float32)
        if self.heights.shape != shape:
            raise InputError("som_dem.heights", self.heights.shape, f"shape {shape} (blocks, lines, samples)")

    def block(self, block: int) -> NDArray[np.float32]:
        """The ``(nline, nsample)`` heights of one block (InputError when it has none)."""
        hit = np.flatnonzero(self.blocks == int(block))
        if hit.size == 0:
            raise InputError("block", block, f"one of the SOM DEM's blocks {self.blocks.tolist()}")
        return self.heights[int(hit[0])]

    def extended_block(self, block: int, margin: int) -> NDArray[np.float32]:
        """The heights of ``block`` with ``margin`` pixels around it, ``(nline + 2 margin,
        nsample + 2 margin)``: row ``margin + l``, column ``margin + s`` is the block's (line l,
        sample s); rows beyond its lines come from the neighbouring blocks, placed by the blocks'
        cross-track offsets; NaN where the DEM holds no block there (or beyond the samples)."""
        from misrgraph.misr.som import N_BLOCKS, SomGrid

        grid = SomGrid(int(self.path), int(self.resolution_m))
        if isinstance(margin, bool) or not isinstance(margin, (int, np.integer)) or not 0 <= margin <= grid.nline:
            raise InputError("margin", margin, f"an integer number of pixels in 0..{grid.nline}")
        nl, ns, m = grid.nline, grid.nsample, int(margin)
        out = np.full((nl + 2 * m, ns + 2 * m), np.nan, np.float32)
        out[m : m + nl, m : m + ns] = self.block(block)
        off = grid.block_offsets
        for nb, rows in ((int(block) - 1, slice(0, m)), (int(block) + 1, slice(m + nl, 2 * m + nl))):
            if m == 0 or not 1 <= nb <= N_BLOCKS or not np.any(self.blocks == nb):
                continue
            h = self.block(nb)
            part = h[nl - m :] if nb < block else h[:m]
            shift = int(off[nb - 1] - off[int(block) - 1])  # column of the neighbour's sample 0 in this block's frame
            lo, hi = max(0, shift + m), min(ns + 2 * m, shift + m + ns)
            if lo < hi:
                out[rows, lo:hi] = part[:, lo - shift - m : hi - shift - m]
        return out


def save_som_dem(dem: SomDem, path: str | os.PathLike[str]) -> None:
    """Write a :class:`SomDem` atomically (HDF5 kind ``som_dem``)."""
    with atomic_h5(path, "som_dem") as f:
        f.attrs["path"] = int(dem.path)
        f.attrs["resolution_m"] = int(dem.resolution_m)
        f.attrs["sigma_m"] = float(dem.sigma_m)
        f.attrs["source"] = dem.source
        f.attrs["height_reference"] = "WGS84 ellipsoid"
        write_dataset(f, "blocks", dem.blocks)
        create_dataset(f, "heights", dem.heights, chunks=(1,) + dem.heights.shape[1:], compression="gzip", shuffle=True)
        f["heights"].attrs["units"] = "m"


def read_som_dem(path: str | os.PathLike[str]) -> SomDem:
    """Read a :class:`SomDem`, checking the heights' shape against the path's grid."""
    from misrgraph.misr.som import SomGrid

    with open_h5(path, "som_dem") as f:
        p, res = int(read_attr(f, "path")), int(read_attr(f, "resolution_m"))
        blocks = read_dataset(f, "blocks", (None,), dtype=np.int64)
        grid = SomGrid(p, res)
        heights = read_dataset(f, "heights", (blocks.size, grid.nline, grid.nsample), dtype=np.float32)
        return SomDem(p, res, blocks, heights, float(read_attr(f, "sigma_m")), str(f.attrs.get("source", "")))
