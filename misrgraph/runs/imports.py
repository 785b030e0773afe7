"""Importing real inputs (``misrgraph import gcps|dem|agp``): a GCP list (CSV, GeoJSON), DEM rasters
(any GDAL raster, through rasterio) or a MISR AGP (HDF-EOS2) into the HDF5 files ``adjust
--gcps/--dem`` and the other commands read. See :mod:`misrgraph.io.external` for the accepted
columns and the grid, :mod:`misrgraph.io.misrfiles` for the AGP."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from misrgraph.io.dem import save_dem
from misrgraph.io.external import read_gcp_table, read_geoid_grid, read_raster_dem
from misrgraph.io.gcp import save_gcp_database
from misrgraph.model.dem import Geoid

__all__ = ["run_import_gcps", "run_import_dem", "run_import_agp"]


def _geoid(geoid: str | os.PathLike[str] | None) -> Geoid | None:
    return None if geoid is None else read_geoid_grid(geoid)


def run_import_gcps(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    default_sigma_m: float | None = None,
    geoid: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Write the GCP database ``out`` (HDF5) from a CSV/GeoJSON list; return a summary:
    ``{"gcps", "out", "sigma_m": {"min", "median", "max"}, "lat": [min, max], "lon": [min, max]}``."""
    db = read_gcp_table(source, default_sigma_m, _geoid(geoid))
    save_gcp_database(db, out)
    s = np.asarray(db.sigma_m)
    return {
        "gcps": len(db),
        "out": str(Path(out)),
        "sigma_m": {"min": float(s.min()), "median": float(np.median(s)), "max": float(s.max())},
        "lat": [float(db.lat.min()), float(db.lat.max())],
        "lon": [float(db.lon.min()), float(db.lon.max())],
    }


def run_import_dem(
    sources: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    posting_arcsec: float = 3.0,
    tile_postings: int = 1201,
    quality: int = 1,
    geoid: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Write the DEM file ``out`` (HDF5) from rasters; return a summary: ``{"tiles", "tile_postings",
    "posting_arcsec", "height_reference", "height_m": {"min", "max"}, "lat": [min, max], "lon": [min, max], "out"}``."""
    dem = read_raster_dem(list(sources), posting_arcsec, tile_postings, quality, _geoid(geoid))
    reference = (
        "WGS84 ellipsoid (geoid grid " + Path(geoid).name + " added)"
        if geoid is not None
        else "as in " + ", ".join(Path(s).name for s in sources) + " (no geoid applied)"
    )
    save_dem(dem, out, height_reference=reference)
    span = (dem.size - 1) * dem.posting_deg
    return {
        "tiles": int(dem.lat0.size),
        "tile_postings": dem.size,
        "posting_arcsec": dem.posting_deg * 3600.0,
        "height_reference": reference,
        "height_m": {"min": float(dem.heights.min()), "max": float(dem.heights.max())},
        "lat": [float(dem.lat0.min()), float(dem.lat0.max() + span)],
        "lon": [float(dem.lon0.min()), float(dem.lon0.max() + span)],
        "out": str(Path(out)),
    }


def run_import_agp(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    blocks: str | None = None,
    posting_arcsec: float = 30.0,
    tile_postings: int = 64,
) -> dict[str, Any]:
    """Write the DEM file ``out`` (HDF5) from a MISR AGP's ``AveSceneElev`` with each posting's
    1-sigma from ``StdDevSceneElev`` (:func:`misrgraph.io.misrfiles.agp_to_dem`); ``blocks``
    ``"A-B"`` (default: the file's ``Start_block``..``End block``). Return a summary:
    ``{"path", "blocks": [first, last], "tiles", "tile_postings", "posting_arcsec",
    "height_m": {"min", "max"}, "sigma_m": {"min", "median", "max"}, "out"}``."""
    from misrgraph.io.misrfiles import agp_to_dem, read_agp

    chosen = None
    if blocks is not None:
        from misrgraph.runs.products import parse_blocks

        chosen = parse_blocks(blocks, "--blocks")
    agp = read_agp(source, chosen)
    dem = agp_to_dem(agp, posting_arcsec, tile_postings)
    save_dem(dem, out, height_reference="WGS84 ellipsoid (AGP " + Path(source).name + ")")
    sig = np.asarray(dem.sigma_m)
    return {
        "path": agp.path,
        "blocks": [int(agp.blocks.min()), int(agp.blocks.max())],
        "tiles": int(dem.lat0.size),
        "tile_postings": dem.size,
        "posting_arcsec": dem.posting_deg * 3600.0,
        "height_m": {"min": float(dem.heights.min()), "max": float(dem.heights.max())},
        "sigma_m": {"min": float(sig.min()), "median": float(np.median(sig)), "max": float(sig.max())},
        "out": str(Path(out)),
    }
