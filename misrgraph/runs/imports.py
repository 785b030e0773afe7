"""Importing real inputs (``misrgraph import gcps|dem|agp|l1b2``): a GCP list (CSV, GeoJSON), DEM rasters
(any GDAL raster, through rasterio) or a MISR AGP (HDF-EOS2) into the HDF5 files ``adjust
--gcps/--dem`` and the other commands read. See :mod:`misrgraph.io.external` for the accepted
columns and the grid, :mod:`misrgraph.io.misrfiles` for the AGP."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from misrgraph.errors import InputError
from misrgraph.io.dem import save_dem
from misrgraph.io.external import read_gcp_table, read_geoid_grid, read_raster_dem
from misrgraph.io.gcp import save_gcp_database
from misrgraph.model.dem import Geoid

__all__ = ["run_import_gcps", "run_import_dem", "run_import_agp", "run_import_l1b2"]


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


def run_import_l1b2(
    sources: Sequence[str | os.PathLike[str]],
    out: str | os.PathLike[str],
    band: str = "red",
    blocks: str | None = None,
    compare: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Write a Reference Orbit Imagery file ``out`` (HDF5, as ``products --roi`` writes) from MISR
    L1B2 files, one per camera, at 275 m (the red band, or An's bands): each pixel's 14-bit count
    (radiance / ``Scale factor``) where the file has a radiance with RDQI 0 or 1, empty (0,
    source -1) where it has fill, an RDQI of 2 or 3, or terrain hides the point (then also
    ``obscured``). ``blocks`` ``"A-B"`` (default: every block the files share). Return a summary:
    ``{"path", "band", "cameras", "pass_ids", "blocks": [first, last], "empty_fraction": {camera},
    "out"}``; with ``compare`` (misrgraph's ROI file of the path), also ``"comparison"``: the
    imported imagery's misregistration against it per camera and block
    (:func:`misrgraph.products.roi.compare_rois`: ``excess_px``, ``mean_px``, ``matches``, ...)."""
    from misrgraph.io.misrfiles import orbit_of_file_name, read_l1b2
    from misrgraph.io.roi import roi_writer
    from misrgraph.model.constants import CAMERAS

    if not sources:
        raise InputError("L1B2 files", [], "at least one file")
    chosen = None
    if blocks is not None:
        from misrgraph.runs.products import parse_blocks

        chosen = parse_blocks(blocks, "--blocks")
    bands = [read_l1b2(s, band, chosen) for s in sources]
    for b, s in zip(bands, sources):
        if b.camera not in CAMERAS:
            raise InputError(f"{Path(s).name}: camera", b.camera, "a file that names its camera (attribute or name)")
        if b.resolution_m != 275:
            raise InputError(f"{Path(s).name}: resolution", b.resolution_m, "275 m (the ROI's grid)")
        if b.path != bands[0].path:
            raise InputError(f"{Path(s).name}: path", b.path, f"path {bands[0].path}, as {Path(sources[0]).name}")
    cams = [b.camera for b in bands]
    dup = sorted({c for c in cams if cams.count(c) > 1})
    if dup:
        raise InputError("L1B2 files: camera", dup[0], "one file per camera")
    order = sorted(range(len(bands)), key=lambda i: CAMERAS.index(str(bands[i].camera)))
    bands = [bands[i] for i in order]
    names = [Path(sources[i]).name for i in order]
    common = set(bands[0].blocks.tolist())
    for b in bands[1:]:
        common &= set(b.blocks.tolist())
    if not common:
        raise InputError("L1B2 files: blocks", [b.blocks.tolist()[:1] for b in bands], "blocks the files share")
    shared = np.array(sorted(common))
    pass_of = [f"P{bands[0].path:03d}_O{orbit_of_file_name(n):06d}" if orbit_of_file_name(n) else n for n in names]
    pass_ids = list(dict.fromkeys(pass_of))
    cameras = tuple(str(b.camera) for b in bands)
    empty = {c: 0.0 for c in cameras}
    with roi_writer(out, bands[0].path, band, cameras, pass_ids, shared, 16383) as w:
        for blk in shared:
            pixels, source, obscured = [], [], []
            for c, b in enumerate(bands):
                k = int(np.flatnonzero(b.blocks == blk)[0])
                ok = np.isfinite(b.radiance[k]) & (b.rdqi[k] < 2)
                dn = np.rint(np.nan_to_num(b.radiance[k]) / b.scale_factor)
                pixels.append(np.where(ok, dn, 0).astype(np.uint16))
                source.append(np.where(ok, pass_ids.index(pass_of[c]), -1).astype(np.int8))
                obscured.append(b.obscured[k])
                empty[cameras[c]] += float(np.mean(~ok)) / shared.size
            src = np.stack(source)
            w.write(
                _RoiBlock(
                    block=int(blk),
                    pixels=np.stack(pixels),
                    source=src,
                    cloudy=np.zeros(src.shape, bool),
                    obscured=np.stack(obscured),
                    clear_fraction=np.array([float(np.mean(src == p)) for p in range(len(pass_ids))]),
                    chosen=0,
                )
            )
    summary: dict[str, Any] = {
        "path": bands[0].path,
        "band": band,
        "cameras": list(cameras),
        "pass_ids": pass_ids,
        "blocks": [int(shared.min()), int(shared.max())],
        "empty_fraction": empty,
        "out": str(Path(out)),
    }
    if compare is not None:
        from misrgraph.io.roi import read_roi
        from misrgraph.products.roi import compare_rois

        summary["comparison"] = {
            cam: {str(b): v for b, v in per.items()}
            for cam, per in compare_rois(read_roi(compare), read_roi(out)).items()
        }
    return summary


@dataclass
class _RoiBlock:
    """One block of an imported ROI, in the shape the ROI writer stores."""

    block: int
    pixels: np.ndarray
    source: np.ndarray
    cloudy: np.ndarray
    obscured: np.ndarray
    clear_fraction: np.ndarray
    chosen: int
