"""DEM files (HDF5 kind ``dem``): the one reader and writer.

Layout: group ``/tiles`` with attributes ``posting_deg``, ``size``, ``height_reference`` and
datasets ``lat0, lon0, lon_posting (T,)`` deg, ``heights (T, n, n)`` m above
``height_reference`` (float32; mean sea level for simulated DEMs, the WGS84 ellipsoid for a
raster imported with a geoid), ``flags (T, n, n)`` (1 land, 2 water, 3 boundary) and ``quality (T,)`` (see
:data:`misrgraph.model.dem.QUALITY_SIGMA_M`).
"""

from __future__ import annotations

import os

import numpy as np

from misrgraph.errors import FileFormatError
from misrgraph.io.h5 import atomic_h5, create_dataset, open_h5, read_attr, read_dataset, write_dataset
from misrgraph.model.dem import DemTiles

__all__ = ["save_dem", "read_dem"]


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
        )
