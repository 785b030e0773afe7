"""Real inputs a calibration scientist brings: GCP lists (CSV, GeoJSON), DEM rasters and geoid
grids (any raster GDAL reads, through rasterio).

**GCP lists** (:func:`read_gcp_table`) become a :class:`~misrgraph.model.gcp.GcpDatabase`:

* CSV with a header row. Columns (case-insensitive; the first alias found is used):
  ``lat``/``latitude`` and ``lon``/``long``/``longitude`` (deg, WGS84); the height either as
  ``height``/``height_m``/``ellipsoid_height`` (m above the WGS84 ellipsoid) or as
  ``height_msl``/``elevation``/``orthometric_height`` (m above the geoid; needs ``geoid``);
  the 1-sigma (m) as ``sigma_m`` (every ENU axis), ``sigma_h_m`` + ``sigma_v_m`` (horizontal on
  east and north, vertical) or ``sigma_e_m`` + ``sigma_n_m`` + ``sigma_u_m``; optional ``id``
  (whole numbers, unique; default the row number from 0) and ``region``. Without a sigma column
  ``default_sigma_m`` applies (m, every axis); without either the import stops. Optional
  ``scene`` (the source scene a GCP was measured in: a whole number, empty or -1 for none) with
  ``scene_sigma_m`` (m per ENU axis, the part of the sigma the scene's GCPs share; one value
  per scene), which the adjustment turns into one shared offset per scene.
* GeoJSON (RFC 7946): a FeatureCollection of Point features; ``coordinates`` are
  ``[lon, lat]`` or ``[lon, lat, h]`` with ``h`` the height above the WGS84 ellipsoid (RFC 7946
  section 4); ``properties`` may give ``id``, ``region``, the sigma columns above and a height
  column (which wins over the third coordinate).

**DEM rasters** (:func:`read_raster_dem`, needs rasterio): one or more rasters in any CRS are
resampled (each posting transformed into the raster's CRS by PROJ, then bilinear in its pixel
grid; a posting that falls on a raster posting takes its value) onto a geographic
WGS84 grid of ``posting_arcsec`` postings aligned to whole multiples of the posting, so that a
3" DTED or SRTM raster keeps its own postings and values, and cut into square tiles of
``tile_postings`` postings overlapping by :data:`TILE_OVERLAP` (every point at least 3 postings
inside one tile, as :meth:`~misrgraph.model.dem.DemTiles.tile_of` needs). Tiles with a no-data
posting are left out: points there are "not covered". Heights above a geoid become ellipsoidal
with ``geoid`` (``h = H + N``); the estimator's tools then use the zero geoid on the result.

**Geoid grids** (:func:`read_geoid_grid`): a global raster of the undulation ``N`` (m) on a
geographic grid, e.g. PROJ's ``us_nga_egm96_15.tif`` (EGM96 on a 15' grid, from
https://cdn.proj.org), interpolated bilinearly (longitude wraps). No package on PyPI ships
EGM96 data: ``egm96`` 0.1.0 is an empty placeholder.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.model.dem import DemTiles, Geoid, bilinear, wrap_deg
from misrgraph.model.gcp import GcpDatabase

__all__ = ["GeoidGrid", "read_gcp_table", "read_geoid_grid", "read_raster_dem", "TILE_OVERLAP"]

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

#: postings shared by neighbouring imported tiles (>= 2 x 3 + 1, tile_of's margin on both sides)
TILE_OVERLAP = 8

_ALIASES: dict[str, tuple[str, ...]] = {
    "id": ("id", "gcp_id", "name_id"),
    "lat": ("lat", "latitude"),
    "lon": ("lon", "long", "longitude"),
    "height": ("height", "height_m", "ellipsoid_height", "h"),
    "height_msl": ("height_msl", "elevation", "orthometric_height"),
    "sigma_m": ("sigma_m", "sigma"),
    "sigma_h_m": ("sigma_h_m",),
    "sigma_v_m": ("sigma_v_m",),
    "sigma_e_m": ("sigma_e_m",),
    "sigma_n_m": ("sigma_n_m",),
    "sigma_u_m": ("sigma_u_m",),
    "region": ("region",),
    "scene": ("scene", "source_scene"),
    "scene_sigma_m": ("scene_sigma_m",),
}


def _rasterio() -> Any:
    try:
        import rasterio
    except ImportError as exc:  # pragma: no cover - rasterio is in the 'real' extra
        raise InputError("rasterio", None, "the rasterio package: pip install 'misrgraph[real]'") from exc
    return rasterio


# ---------------------------------------------------------------------------------- GCP lists
def _records_csv(path: Path) -> list[dict[str, Any]]:
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(row for row in fh if row.strip() and not row.lstrip().startswith("#"))
            if reader.fieldnames is None:
                raise FileFormatError(path, "no header row (expected columns lat, lon, height, sigma_m, ...)")
            return [
                {(k or "").strip().lower(): (v.strip() if isinstance(v, str) else v) for k, v in row.items()}
                for row in reader
            ]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise FileFormatError(path, f"cannot read as CSV: {exc}") from exc


def _records_geojson(path: Path) -> list[dict[str, Any]]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FileFormatError(path, f"cannot read as GeoJSON: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("type") != "FeatureCollection" or not isinstance(doc.get("features"), list):
        raise FileFormatError(path, "expected a GeoJSON FeatureCollection with a 'features' list")
    out = []
    for i, feat in enumerate(doc["features"]):
        geom = feat.get("geometry") if isinstance(feat, dict) else None
        if not isinstance(geom, dict) or geom.get("type") != "Point":
            raise InputError(f"{path.name}: features[{i}].geometry", geom and geom.get("type"), "a Point")
        coords = geom.get("coordinates")
        if not isinstance(coords, list) or len(coords) not in (2, 3):
            raise InputError(f"{path.name}: features[{i}].geometry.coordinates", coords, "[lon, lat] or [lon, lat, h]")
        rec = {str(k).lower(): v for k, v in (feat.get("properties") or {}).items()}
        rec.setdefault("lon", coords[0])
        rec.setdefault("lat", coords[1])
        if len(coords) == 3 and not any(a in rec for a in _ALIASES["height"] + _ALIASES["height_msl"]):
            rec["height"] = coords[2]  # RFC 7946: height above the WGS84 ellipsoid
        out.append(rec)
    return out


def _column(records: list[dict[str, Any]], name: str) -> str | None:
    """The first alias of ``name`` that some record fills (None when none does); a record that
    lacks it is reported by :func:`_numbers`."""
    for alias in _ALIASES[name]:
        if any(alias in r and r[alias] not in (None, "") for r in records):
            return alias
    return None


def _numbers(records: list[dict[str, Any]], alias: str, where: str, what: str, empty: Array | None = None) -> Array:
    """Column ``alias`` as floats; every bad value is reported with its row. ``empty`` (one per
    row): the value of an empty cell, where finite (NaN: the cell is required)."""
    out = np.empty(len(records))
    for i, r in enumerate(records):
        v = r.get(alias)
        if v in (None, "") and empty is not None and math.isfinite(empty[i]):
            out[i] = empty[i]
            continue
        try:
            out[i] = float(v)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            out[i] = np.nan
        if not math.isfinite(out[i]):
            ident = f"id {r['id']}, " if r.get("id") not in (None, "") else ""
            raise InputError(f"{where}: row {i} ({ident}column {alias})", v, what)
    return out


def _whole_numbers(
    records: list[dict[str, Any]], alias: str, where: str, what: str, empty: Array | None = None
) -> NDArray[np.int64]:
    """:func:`_numbers` that must be whole numbers."""
    raw = _numbers(records, alias, where, what, empty)
    if not np.all(raw == np.round(raw)):
        i = int(np.flatnonzero(raw != np.round(raw))[0])
        raise InputError(f"{where}: row {i} (column {alias})", float(raw[i]), "a whole number")
    return raw.astype(np.int64)


def read_gcp_table(
    path: str | os.PathLike[str], default_sigma_m: float | None = None, geoid: Geoid | None = None
) -> GcpDatabase:
    """A GCP database from a CSV or GeoJSON list (module docstring for the columns).

    ``default_sigma_m`` (m): the 1-sigma on every ENU axis where the file has no sigma column.
    ``geoid``: needed when heights are given above the geoid (``height_msl``). Every bad value
    is reported with its row and column.
    """
    p = Path(path)
    if not p.is_file():
        raise FileFormatError(p, "no such file")
    suffix = p.suffix.lower()
    if suffix == ".csv":
        records = _records_csv(p)
    elif suffix in (".geojson", ".json"):
        records = _records_geojson(p)
    else:
        raise InputError("GCP list", p.name, "a .csv or .geojson (.json) file")
    if not records:
        raise InputError(f"{p.name}", "no rows", "at least one GCP")
    where = p.name
    cols = {k: _column(records, k) for k in _ALIASES}
    for need in ("lat", "lon"):
        if cols[need] is None:
            raise InputError(
                f"{where}: column {need}", sorted(records[0]), f"a column named one of {', '.join(_ALIASES[need])}"
            )
    lat = _numbers(records, cols["lat"], where, "a latitude in degrees")  # type: ignore[arg-type]
    lon = _numbers(records, cols["lon"], where, "a longitude in degrees")  # type: ignore[arg-type]
    bad = np.flatnonzero(np.abs(lat) > 90)
    if bad.size:
        raise InputError(
            f"{where}: row {bad[0]} (column {cols['lat']})", float(lat[bad[0]]), "a latitude within -90..90 deg"
        )
    lon = wrap_deg(lon)
    if cols["height"] is not None:
        height = _numbers(records, cols["height"], where, "a height in metres above the WGS84 ellipsoid")
    elif cols["height_msl"] is not None:
        if geoid is None:
            raise InputError(
                f"{where}: column {cols['height_msl']}",
                "heights above the geoid",
                "a geoid to make them ellipsoidal (--geoid GRID), or an ellipsoidal 'height' column",
            )
        height = _numbers(records, cols["height_msl"], where, "a height in metres above the geoid")
        height = height + geoid.undulation(lat, lon)
    else:
        raise InputError(
            f"{where}: column height",
            sorted(records[0]),
            "a height column (height: m above the WGS84 ellipsoid, or height_msl with a geoid)",
        )
    n = lat.size
    if cols["sigma_e_m"] and cols["sigma_n_m"] and cols["sigma_u_m"]:
        sigma = np.stack(
            [
                _numbers(records, cols[c], where, "a positive 1-sigma in metres")  # type: ignore[arg-type]
                for c in ("sigma_e_m", "sigma_n_m", "sigma_u_m")
            ],
            axis=1,
        )
    elif cols["sigma_h_m"] and cols["sigma_v_m"]:
        h = _numbers(records, cols["sigma_h_m"], where, "a positive 1-sigma in metres")
        v = _numbers(records, cols["sigma_v_m"], where, "a positive 1-sigma in metres")
        sigma = np.stack([h, h, v], axis=1)
    elif cols["sigma_m"]:
        sigma = _numbers(records, cols["sigma_m"], where, "a positive 1-sigma in metres")
    elif default_sigma_m is not None:
        if not (default_sigma_m > 0 and math.isfinite(default_sigma_m)):
            raise InputError("default_sigma_m", default_sigma_m, "a positive number of metres")
        sigma = np.full(n, float(default_sigma_m))
    else:
        raise InputError(
            f"{where}: column sigma_m",
            sorted(records[0]),
            "a sigma column (sigma_m, sigma_h_m + sigma_v_m or sigma_e_m + sigma_n_m + sigma_u_m) "
            "or a default sigma (--sigma-m)",
        )
    bad = np.flatnonzero(~np.all(np.reshape(sigma, (n, -1)) > 0, axis=1))
    if bad.size:
        raise InputError(
            f"{where}: row {bad[0]} (sigma)", np.reshape(sigma, (n, -1))[bad[0]].tolist(), "positive metres"
        )
    if cols["id"] is not None:
        ids = _whole_numbers(records, cols["id"], where, "a whole number")
        u, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            raise InputError(f"{where}: column {cols['id']}", int(u[counts > 1][0]), "unique ids (this one repeats)")
    else:
        ids = np.arange(n, dtype=np.int64)
    region = np.array([str(r.get(cols["region"], "") or "") if cols["region"] else "" for r in records])
    scene, scene_sigma = None, None
    if (cols["scene"] is None) != (cols["scene_sigma_m"] is None):
        have, need = ("scene", "scene_sigma_m") if cols["scene"] else ("scene_sigma_m", "scene")
        raise InputError(f"{where}: column {need}", f"only {have}", "scene and scene_sigma_m together (or neither)")
    if cols["scene"] is not None:
        scene = _whole_numbers(
            records,
            cols["scene"],
            where,
            "a whole number (the source scene; empty or -1: none)",
            empty=np.full(n, -1.0),
        )
        scene_sigma = _numbers(
            records,
            cols["scene_sigma_m"],
            where,
            "metres (the sigma the scene's GCPs share)",
            empty=np.where(scene < 0, 0.0, np.nan),
        )  # required where the GCP has a scene
    log.info("%s: %d GCPs", where, n)
    return GcpDatabase(ids, lat, lon, height, sigma, region, scene=scene, scene_sigma_m=scene_sigma)


# -------------------------------------------------------------------------------- geoid grids
@dataclass
class GeoidGrid:
    """Bilinear interpolation of a global geographic grid of geoid undulation ``N`` (m):
    ``lat (R,)`` ascending deg, ``lon (C,)`` ascending deg covering 360 deg (the first column is
    repeated 360 deg east internally), ``values (R, C)`` m. Callable as ``N(lat, lon)``."""

    lat: Array
    lon: Array
    values: Array

    def __call__(self, lat: ArrayLike, lon: ArrayLike) -> Array:
        la, lo = np.broadcast_arrays(np.asarray(lat, float), np.asarray(lon, float))
        lon_ext = np.r_[self.lon, self.lon[0] + 360.0]
        # fractional grid indices (latitude clamped to the grid's first and last rows)
        r = np.interp(la, self.lat, np.arange(self.lat.size))
        c = np.interp((lo - self.lon[0]) % 360.0 + self.lon[0], lon_ext, np.arange(lon_ext.size))
        return bilinear(np.c_[self.values, self.values[:, :1]], r, c)


def read_geoid_grid(path: str | os.PathLike[str]) -> Geoid:
    """A :class:`~misrgraph.model.dem.Geoid` from a global raster of undulation (m) on a
    geographic grid covering every longitude (e.g. ``us_nga_egm96_15.tif``; module docstring)."""
    rio = _rasterio()
    p = Path(path)
    if not p.is_file():
        raise FileFormatError(p, "no such file (a geoid grid, e.g. us_nga_egm96_15.tif from https://cdn.proj.org)")
    try:
        with rio.open(p) as ds:
            if ds.crs is None or not ds.crs.is_geographic:
                raise InputError(f"{p.name}: CRS", str(ds.crs), "a geographic (lat/lon) CRS for a geoid grid")
            z = ds.read(1, masked=True).astype(float).filled(np.nan)
            t = ds.transform
            if t.b != 0 or t.d != 0:
                raise InputError(f"{p.name}: transform", tuple(t)[:6], "a north-up grid (no rotation)")
            cols = t.c + (np.arange(ds.width) + 0.5) * t.a
            rows = t.f + (np.arange(ds.height) + 0.5) * t.e
            span = ds.width * abs(t.a)
            point = str(ds.tags().get("AREA_OR_POINT", "Area")).lower() == "point"
    except rio.errors.RasterioIOError as exc:
        raise FileFormatError(p, f"cannot read as a raster: {exc}") from exc
    if not np.all(np.isfinite(z)):
        raise InputError(f"{p.name}: values", "no-data postings", "a complete grid")
    if span < 360.0 - 1e-6:
        raise InputError(f"{p.name}: longitude span", round(span, 6), "a global grid covering 360 deg of longitude")
    # pixel-is-point grids (GDAL marks them AREA_OR_POINT=Point) put postings on the cell corners
    if point:
        cols, rows = cols - 0.5 * t.a, rows - 0.5 * t.e
    order = np.argsort(rows)
    lon = wrap_deg(cols)
    lo = np.argsort(lon)
    keep = np.r_[True, np.diff(lon[lo]) > 1e-9]  # a grid with both -180 and 180 holds one column twice
    grid = GeoidGrid(rows[order], lon[lo][keep], z[order][:, lo[keep]])
    return Geoid("function", function=grid)


# -------------------------------------------------------------------------------- DEM rasters
def _tile_starts(n: int, size: int) -> list[int]:
    """First postings of tiles of ``size`` covering ``n`` postings, overlapping by at least
    :data:`TILE_OVERLAP` (the last tile ends on the last posting)."""
    starts = list(range(0, n - size + 1, size - TILE_OVERLAP))
    if starts[-1] != n - size:
        starts.append(n - size)
    return starts


def read_raster_dem(
    paths: Sequence[str | os.PathLike[str]],
    posting_arcsec: float = 3.0,
    tile_postings: int = 1201,
    quality: int = 1,
    geoid: Geoid | None = None,
) -> DemTiles:
    """DEM tiles from rasters of height (m) in any CRS GDAL reads (module docstring).

    ``posting_arcsec``: the output grid's posting in latitude and longitude (arc seconds);
    ``tile_postings``: postings per tile side (>= 32); ``quality``: the DEM's accuracy class for
    every tile (:data:`misrgraph.model.dem.QUALITY_SIGMA_M`); ``geoid``: makes heights above the
    geoid ellipsoidal (None: the raster's heights are used as they are).
    """
    rio = _rasterio()
    from pyproj import Transformer
    from rasterio.warp import transform_bounds

    if not paths:
        raise InputError("DEM rasters", [], "at least one raster file")
    if not (posting_arcsec > 0 and math.isfinite(posting_arcsec)):
        raise InputError("posting_arcsec", posting_arcsec, "a positive number of arc seconds")
    if not (isinstance(tile_postings, int) and tile_postings >= 32):
        raise InputError("tile_postings", tile_postings, "a whole number of postings >= 32")
    post = posting_arcsec / 3600.0
    lat0s, lon0s, tiles = [], [], []
    dropped = 0
    for path in paths:
        p = Path(path)
        if not p.is_file():
            raise FileFormatError(p, "no such file")
        try:
            ds = rio.open(p)
        except rio.errors.RasterioIOError as exc:
            raise FileFormatError(p, f"cannot read as a raster: {exc}") from exc
        with ds:
            if ds.crs is None:
                raise InputError(f"{p.name}: CRS", None, "a raster with a coordinate reference system")
            west, south, east, north = transform_bounds(ds.crs, "EPSG:4326", *ds.bounds, densify_pts=21)
            if east < west:
                raise InputError(f"{p.name}: bounds", (west, east), "a raster that does not cross the antimeridian")
            z = ds.read(1, masked=True).astype(np.float64).filled(np.nan)
            inverse = ~ds.transform
            crs = ds.crs
        # postings on whole multiples of the posting inside the raster's bounds
        i0, i1 = math.ceil(south / post - 1e-6), math.floor(north / post + 1e-6)
        j0, j1 = math.ceil(west / post - 1e-6), math.floor(east / post + 1e-6)
        n_rows, n_cols = i1 - i0 + 1, j1 - j0 + 1
        if n_rows < tile_postings or n_cols < tile_postings:
            raise InputError(
                f'{p.name}: size on the {posting_arcsec:g}" grid',
                (n_rows, n_cols),
                f"at least {tile_postings} x {tile_postings} postings (tile_postings)",
            )
        lat_axis = np.arange(i0, i1 + 1) * post
        lon_axis = np.arange(j0, j1 + 1) * post
        # each posting in the raster's CRS (PROJ, exact), then bilinear in its pixel grid
        lon_g, lat_g = np.meshgrid(lon_axis, lat_axis)
        if crs.to_epsg() == 4326:
            x, y = lon_g, lat_g
        else:
            x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon_g, lat_g)
        ia, ib, ic, id_, ie, if_ = tuple(inverse)[:6]
        col = ia * np.asarray(x) + ib * np.asarray(y) + ic
        row = id_ * np.asarray(x) + ie * np.asarray(y) + if_
        grid = bilinear(z, np.asarray(row) - 0.5, np.asarray(col) - 0.5)
        if geoid is not None:
            grid = grid + geoid.undulation(lat_axis[:, None], lon_axis[None, :])
        for r in _tile_starts(n_rows, tile_postings):
            for c in _tile_starts(n_cols, tile_postings):
                t = grid[r : r + tile_postings, c : c + tile_postings]
                if not np.all(np.isfinite(t)):
                    dropped += 1
                    continue
                lat0s.append(lat_axis[r])
                lon0s.append(lon_axis[c])
                tiles.append(t)
        log.info('%s: %d x %d postings at %g"', p.name, n_rows, n_cols, posting_arcsec)
    if dropped:
        log.warning("%d DEM tiles with no-data postings left out (points there are not covered)", dropped)
    if not tiles:
        raise InputError("DEM rasters", [str(p) for p in paths], "a tile of postings without no-data values")
    heights = np.stack(tiles)
    return DemTiles(
        np.array(lat0s),
        wrap_deg(np.array(lon0s)),
        heights,
        np.ones(heights.shape, np.uint8),
        np.full(len(tiles), int(quality), np.int64),
        post,
    )
