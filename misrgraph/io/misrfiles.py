"""MISR's own files: Projection Parameters and Reference Orbit Imagery out, AGP and L1B2 in, as the
HDF-EOS2 grid files MISR's ground system writes (:mod:`misrgraph.io.hdfeos` does the HDF-EOS2).

**The SOM grid in the files.** Every grid is one path's Space Oblique Mercator grid at one
resolution ``r`` (m), with the MISR Toolkit's conventions:

* dimensions ``("SOMBlockDim", "XDim", "YDim")`` = ``(180, 128 * 1100 / r, 512 * 1100 / r)``:
  all 180 blocks are in every file (blocks outside ``Start_block``..``End block`` hold the fill
  value), ``XDim`` runs along the track (line), ``YDim`` across it (sample);
* ``UpperLeftPointMtrs = (7460750, 1090650)``, ``LowerRightMtrs = (7460750 + 128 * 1100,
  527450)`` m: block 1's corners (MISR stores the upper-left y as the larger value; the grid's
  sample 0 is at SOM y = 527450 + r/2);
* ``Projection=GCTP_SOM`` (GCTP code 22), ``SphereCode=12`` (WGS84) and the 13 ``ProjParams``
  (:func:`som_proj_params`): semi-major axis 6378137 m, ``-0.006694348`` (minus the
  eccentricity squared), inclination 98 deg 18' 13.752" and the path's longitude of the ascending
  node in GCTP's packed degrees-minutes-seconds (``DDDMMMSSS.SS``), the period 98.88 min, and
  180 blocks in the 12th parameter (which tells HDF-EOS2 that the grid is a block SOM);
* the grid attribute ``_BLKSOM:<grid>`` (179 float32): each block's shift across the track
  against the one before, in pixels of ``r`` (:data:`misrgraph.misr.som.RELATIVE_OFFSETS_1100`
  scaled);
* grid attributes ``Block_size.resolution_x``/``_y`` (m) and ``Block_size.size_x``/``_y``
  (lines, samples); file attributes ``Path_number``, ``AM1_orbitnumber``, ``Start_block``,
  ``End block``, ``Origin_block.ulc.x``/``.y``, ``Origin_block.lrc.x``/``.y`` and the ECS
  ``coremetadata`` (``LOCALGRANULEID`` = the file's name, ``ORBITNUMBER``), and a per-block Vdata
  ``PerBlockMetadataCommon`` (``Block_number``, ``Ocean_flag``, ``Block_coor_ulc_som_meter.x``/
  ``.y``, ``Block_coor_lrc_som_meter.x``/``.y``).

**File names** (:func:`misr_file_name`):
``MISR_AM1_<product>_P<path:03d>[_O<orbit:06d>][_<camera>]_F<format:02d>_<version:04d>.hdf``.

**Projection Parameters** (:func:`write_pp_misr`): one file per camera,
``MISR_AM1_PP_P<path>_O<orbit>_<camera>_F01_0001.hdf``, grid ``Projection_Parameters`` at 1.1 km
with our fields as float32 (fill -9999): ``line0``, ``dline_dh``, ``d2line_dh2``, ``sample0``,
``dsample_dh``, ``d2sample_dh2`` (image line and sample of the grid point at ellipsoidal height
``h``: ``line0 + dline_dh h + d2line_dh2 h^2``, pixels, pixels/m, pixels/m^2) and their
uncertainty ``sigma_line``, ``sigma_sample`` (pixels), ``correlation`` (1), ``sigma_m`` (m).

**Reference Orbit Imagery** (:func:`write_roi_misr`): one L1B2-style file per camera,
``MISR_AM1_ROI_P<path>_<camera>_F01_0001.hdf``, grid ``<Band>Band`` (``RedBand`` for the red
band) at 275 m with ``<Band> Radiance/RDQI`` (uint16; the upper 14 bits the counts, the lower 2
bits the radiometric data quality indicator: 0 within specification, 1 from a cloudy pass;
``65515`` fill where no pass images the point, ``65511`` where terrain hides it) and the grid
attribute ``Scale factor`` (radiance per count, 1.0: the simulator's counts carry no radiometric
calibration), and beside MISR's own field ours: ``ROI Source Pass`` (int8, index into the file
attribute ``ROI_pass_ids``, -1 none).

**AGP in** (:func:`read_agp`, :func:`agp_to_dem`): grid ``Standard`` at 1.1 km,
``AveSceneElev`` (the mean height of each 1.1 km sample, m above the WGS84 ellipsoid),
``StdDevSceneElev`` (m) and ``PtElev`` where present; fill values from the file.

**L1B2 in** (:func:`read_l1b2`): one band grid's ``<Band> Radiance/RDQI`` unpacked: radiance =
``(value >> 2) * Scale factor`` where ``value`` is below the fill value (the fill value less 4 in
terrain-projected files, whose ``fill - 4`` flags terrain-obscured pixels), RDQI = ``value & 3``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.hdfeos import EosField, EosGrid, read_eos_field, read_eos_file, write_eos_file
from misrgraph.io.products import PP_COEFFICIENTS, PP_SIGMAS, PP_UNITS, ProjectionParameters
from misrgraph.io.roi import RoiFile
from misrgraph.misr.som import (
    BLOCK1_CORNER_SOM,
    N_BLOCKS,
    N_PATHS,
    RELATIVE_OFFSETS_1100,
    SomGrid,
)

__all__ = [
    "PP_FILL",
    "RDQI_FILL",
    "RDQI_OBSCURED",
    "AgpFile",
    "L1b2Band",
    "deg_to_packed_dms",
    "packed_dms_to_deg",
    "som_proj_params",
    "misr_file_name",
    "write_pp_misr",
    "write_roi_misr",
    "read_agp",
    "agp_to_dem",
    "read_l1b2",
    "camera_of_file_name",
    "orbit_of_file_name",
    "orbit_of_pass_id",
]

Array = NDArray[np.float64]

#: Fill value of the PP fields.
PP_FILL = -9999.0
#: Radiance/RDQI value where no pass images the point (the field's fill value).
RDQI_FILL = 65515
#: Radiance/RDQI value of a point terrain hides (fill - 4, as MISR's terrain-projected files).
RDQI_OBSCURED = 65511
#: The largest 14-bit count a Radiance/RDQI value can carry below the special values.
_MAX_COUNT = (RDQI_OBSCURED >> 2) - 1

_SEMI_MAJOR = 6378137.0
_MINUS_E2 = -0.006694348
_INCLINATION_DMS = 98018013.752
_PERIOD_MIN = 98.88
#: Longitude of the ascending node of path 1 (packed DMS), as the MISR Toolkit's projection table.
_PATH1_ASCENDING_DMS = 127045037.92824034
_BANDS = {"blue": "Blue", "green": "Green", "red": "Red", "nir": "NIR"}
_DIMS = ("SOMBlockDim", "XDim", "YDim")


def deg_to_packed_dms(deg: float) -> float:
    """Degrees as GCTP's packed ``DDDMMMSSS.SS`` (sign on the whole)."""
    sign = -1.0 if deg < 0 else 1.0
    a = abs(float(deg))
    d = int(a)
    m = int((a - d) * 60.0)
    s = (a - d - m / 60.0) * 3600.0
    if s >= 60.0 - 1e-9:
        s, m = s - 60.0, m + 1
    if m >= 60:
        m, d = m - 60, d + 1
    return sign * (d * 1e6 + m * 1e3 + s)


def packed_dms_to_deg(dms: float) -> float:
    """GCTP's packed ``DDDMMMSSS.SS`` as degrees."""
    sign = -1.0 if dms < 0 else 1.0
    a = abs(float(dms))
    d = int(a // 1e6)
    m = int((a - d * 1e6) // 1e3)
    s = a - d * 1e6 - m * 1e3
    return sign * (d + m / 60.0 + s / 3600.0)


def som_proj_params(path: int) -> tuple[float, ...]:
    """The 13 GCTP SOM parameters of ``path`` as MISR's files carry them (module docstring)."""
    if isinstance(path, bool) or not isinstance(path, (int, np.integer)) or not 1 <= int(path) <= N_PATHS:
        raise InputError("path", path, f"an integer in 1..{N_PATHS}")
    asc = packed_dms_to_deg(_PATH1_ASCENDING_DMS) - 360.0 / N_PATHS * (int(path) - 1)
    return (
        _SEMI_MAJOR,
        _MINUS_E2,
        0.0,
        _INCLINATION_DMS,
        deg_to_packed_dms(asc),
        0.0,
        0.0,
        0.0,
        _PERIOD_MIN,
        0.0,
        0.0,
        float(N_BLOCKS),
        0.0,
    )


_CAMERA_IN_NAME = re.compile(r"_(DF|CF|BF|AF|AN|AA|BA|CA|DA)_F\d\d_", re.IGNORECASE)
_ORBIT_IN_NAME = re.compile(r"_O(\d{6})_")


def camera_of_file_name(name: str) -> str | None:
    """The camera a MISR file name names (``..._AN_F03_...`` -> ``"An"``), or None."""
    m = _CAMERA_IN_NAME.search(name)
    return None if m is None else m.group(1)[0].upper() + m.group(1)[1].lower()


def orbit_of_file_name(name: str) -> int | None:
    """The orbit a MISR file name names (``..._O012345_...`` -> 12345), or None."""
    m = _ORBIT_IN_NAME.search(name)
    return None if m is None else int(m.group(1))


def misr_file_name(
    product: str,
    path: int,
    orbit: int | None = None,
    camera: str | None = None,
    format_version: int = 1,
    version: int = 1,
) -> str:
    """``MISR_AM1_<product>_P<path>[_O<orbit>][_<camera>]_F<format>_<version>.hdf``."""
    parts = [f"MISR_AM1_{product}", f"P{int(path):03d}"]
    if orbit is not None:
        parts.append(f"O{int(orbit):06d}")
    if camera is not None:
        parts.append(camera.upper())
    parts += [f"F{int(format_version):02d}", f"{int(version):04d}"]
    return "_".join(parts) + ".hdf"


def _core_metadata(local_granule_id: str, orbit: int | None) -> str:
    orbit_part = (
        [
            "  GROUP = ORBITCALCULATEDSPATIALDOMAIN",
            "    OBJECT = ORBITCALCULATEDSPATIALDOMAINCONTAINER",
            '      CLASS = "1"',
            "      OBJECT = ORBITNUMBER",
            "        NUM_VAL = 1",
            '        CLASS = "1"',
            f"        VALUE = {int(orbit)}",
            "      END_OBJECT = ORBITNUMBER",
            "    END_OBJECT = ORBITCALCULATEDSPATIALDOMAINCONTAINER",
            "  END_GROUP = ORBITCALCULATEDSPATIALDOMAIN",
        ]
        if orbit is not None
        else []
    )
    return "\n".join(
        [
            "GROUP = INVENTORYMETADATA",
            "  GROUPTYPE = MASTERGROUP",
            "  GROUP = ECSDATAGRANULE",
            "    OBJECT = LOCALGRANULEID",
            "      NUM_VAL = 1",
            f'      VALUE = "{local_granule_id}"',
            "    END_OBJECT = LOCALGRANULEID",
            "  END_GROUP = ECSDATAGRANULE",
            *orbit_part,
            "END_GROUP = INVENTORYMETADATA",
            "END",
            "",
        ]
    )


def _som_grid(name: str, grid: SomGrid, fields: list[EosField], attributes: dict[str, Any] | None = None) -> EosGrid:
    r = grid.resolution_m
    x0, y0 = BLOCK1_CORNER_SOM
    rel = np.asarray(RELATIVE_OFFSETS_1100, dtype=np.float32) * np.float32(1100 / r)
    return EosGrid(
        name=name,
        xdim=grid.nline,
        ydim=grid.nsample,
        upper_left_m=(x0, y0 + grid.nsample * r),
        lower_right_m=(x0 + grid.nline * r, y0),
        projection="GCTP_SOM",
        proj_params=som_proj_params(grid.path),
        sphere_code=12,
        dimensions={"SOMBlockDim": N_BLOCKS},
        fields=fields,
        attributes={
            "Block_size.resolution_x": np.int32(r),
            "Block_size.resolution_y": np.int32(r),
            "Block_size.size_x": np.int32(grid.nline),
            "Block_size.size_y": np.int32(grid.nsample),
            **(attributes or {}),
            f"_BLKSOM:{name}": rel.astype(np.float32),
        },
    )


def _file_attributes(grid: SomGrid, blocks: NDArray[np.int64], orbit: int | None, name: str) -> dict[str, Any]:
    x0, y0 = BLOCK1_CORNER_SOM
    r = grid.resolution_m
    attrs: dict[str, Any] = {
        "Path_number": np.int32(grid.path),
        "Start_block": np.int32(int(blocks.min())),
        "End block": np.int32(int(blocks.max())),
        "Origin_block.ulc.x": float(x0),
        "Origin_block.ulc.y": float(y0 + grid.nsample * r),
        "Origin_block.lrc.x": float(x0 + grid.nline * r),
        "Origin_block.lrc.y": float(y0),
        "coremetadata": _core_metadata(name, orbit),
    }
    if orbit is not None:
        attrs["AM1_orbitnumber"] = np.int32(orbit)
    return attrs


def _block_metadata(grid: SomGrid, blocks: NDArray[np.int64]) -> dict[str, tuple[str, dict[str, Any]]]:
    r = grid.resolution_m
    b = np.arange(1, N_BLOCKS + 1)
    ulc_x = BLOCK1_CORNER_SOM[0] + (b - 1) * grid.nline * r
    ulc_y = BLOCK1_CORNER_SOM[1] + grid.block_offsets * r + grid.nsample * r
    present = np.isin(b, blocks)
    return {
        "PerBlockMetadataCommon": (
            "Blockmetadata",
            {
                "Block_number": b.astype(np.int32),
                "Ocean_flag": np.zeros(N_BLOCKS, np.uint8),
                "Block_coor_ulc_som_meter.x": ulc_x.astype(np.float64),
                "Block_coor_ulc_som_meter.y": ulc_y.astype(np.float64),
                "Block_coor_lrc_som_meter.x": (ulc_x + grid.nline * r).astype(np.float64),
                "Block_coor_lrc_som_meter.y": (ulc_y - grid.nsample * r).astype(np.float64),
                "Data_flag": present.astype(np.uint8),
            },
        )
    }


def orbit_of_pass_id(pass_id: str, orbit: int | None = None) -> int | None:
    """``orbit`` if given, else the ``O<orbit>`` part of a pass id (``P037_O1234`` -> 1234), or None."""
    if orbit is not None:
        return int(orbit)
    for part in pass_id.split("_"):
        if part.startswith("O") and part[1:].isdigit():
            return int(part[1:])
    return None


def write_pp_misr(
    pp: ProjectionParameters, out_dir: str | os.PathLike[str], orbit: int | None = None
) -> dict[str, Path]:
    """Write ``pp`` as MISR PP files, one per camera, into ``out_dir``; return ``{camera: path}``.
    ``orbit`` defaults to the ``O<orbit>`` part of the pass id (none: no orbit in the name)."""
    grid = SomGrid(pp.path, 1100)
    blocks = np.asarray(pp.blocks, dtype=np.int64)
    orbit = orbit_of_pass_id(pp.pass_id, orbit)
    out = Path(out_dir)
    files = {}
    for c, cam in enumerate(pp.cameras):
        fields = []
        for name in PP_COEFFICIENTS + PP_SIGMAS:
            a = np.asarray(getattr(pp, name)[c], dtype=np.float32)
            fields.append(
                EosField(
                    name,
                    np.where(np.isfinite(a), a, np.float32(PP_FILL)),
                    _DIMS,
                    PP_FILL,
                    {"units": PP_UNITS[name]},
                    index=list(blocks - 1),
                )
            )
        fname = misr_file_name("PP", pp.path, orbit, cam)
        eos = _som_grid("Projection_Parameters", grid, fields)
        attrs = _file_attributes(grid, blocks, orbit, fname)
        attrs.update({"Camera": cam, "Band": pp.band, "Pass_id": pp.pass_id})
        files[cam] = write_eos_file(out / fname, [eos], attrs, _block_metadata(grid, blocks))
    return files


def pack_radiance_rdqi(
    counts: NDArray[Any], rdqi: NDArray[Any], fill: NDArray[np.bool_], obscured: NDArray[np.bool_]
) -> NDArray[np.uint16]:
    """MISR's 14+2-bit packing: ``counts << 2 | rdqi``, with the fill and obscured values."""
    c = np.clip(np.asarray(counts, dtype=np.int64), 0, _MAX_COUNT)
    v = (c << 2) | (np.asarray(rdqi, dtype=np.int64) & 3)
    v = np.where(obscured, RDQI_OBSCURED, np.where(fill, RDQI_FILL, v))
    return v.astype(np.uint16)


def write_roi_misr(roi: RoiFile, out_dir: str | os.PathLike[str]) -> dict[str, Path]:
    """Write ``roi`` as L1B2-style files, one per camera, into ``out_dir``; return
    ``{camera: path}`` (layout in the module docstring)."""
    band = _BANDS.get(roi.band.lower())
    if band is None:
        raise InputError("ROI band", roi.band, tuple(_BANDS))
    grid = SomGrid(roi.path, roi.resolution_m)
    blocks = np.asarray(roi.blocks, dtype=np.int64)
    out = Path(out_dir)
    files = {}
    for c, cam in enumerate(roi.cameras):
        empty = roi.source[c] < 0
        packed = pack_radiance_rdqi(
            roi.pixels[c], roi.cloudy[c].astype(np.int64), empty & ~roi.obscured[c], roi.obscured[c]
        )
        fields = [
            EosField(f"{band} Radiance/RDQI", packed, _DIMS, RDQI_FILL, index=list(blocks - 1)),
            EosField("ROI Source Pass", np.asarray(roi.source[c], np.int8), _DIMS, -1, index=list(blocks - 1)),
        ]
        fname = misr_file_name("ROI", roi.path, None, cam)
        eos = _som_grid(f"{band}Band", grid, fields, {"Scale factor": 1.0, "std_solar_wgted_height": 0.0})
        attrs = _file_attributes(grid, blocks, None, fname)
        attrs.update(
            {"Camera": cam, "ROI_pass_ids": ",".join(roi.pass_ids), "Full_scale_dn": np.int32(roi.full_scale_dn)}
        )
        files[cam] = write_eos_file(out / fname, [eos], attrs, _block_metadata(grid, blocks))
    return files


# ------------------------------------------------------------------------------------------ in


def _check_som_grid(path: Path, name: str, g: dict[str, Any], resolution: int | None) -> SomGrid:
    if str(g.get("Projection", "")) != "GCTP_SOM":
        raise FileFormatError(path, f"grid {name}: projection {g.get('Projection')!r}; expected GCTP_SOM")
    params = g.get("ProjParams")
    if not isinstance(params, tuple) or len(params) < 5:
        raise FileFormatError(path, f"grid {name}: ProjParams {params!r}; expected the 13 GCTP SOM parameters")
    asc = packed_dms_to_deg(float(params[4]))
    k = (packed_dms_to_deg(_PATH1_ASCENDING_DMS) - asc) / (360.0 / N_PATHS)
    sky_path = int(round(k)) + 1
    if abs(k - round(k)) > 1e-4 or not 1 <= sky_path <= N_PATHS:
        raise FileFormatError(path, f"grid {name}: ascending node {asc:.6f} deg is not a MISR path's")
    xdim, ydim = int(g["XDim"]), int(g["YDim"])
    res = int(round(128 * 1100 / xdim))
    if resolution is not None and res != resolution:
        raise FileFormatError(path, f"grid {name}: {res} m pixels ({xdim} x {ydim}); expected {resolution} m")
    try:
        grid = SomGrid(sky_path, res)
    except InputError as exc:
        raise FileFormatError(path, f"grid {name}: {exc}") from None
    if (grid.nline, grid.nsample) != (xdim, ydim):
        raise FileFormatError(path, f"grid {name}: XDim x YDim {xdim} x {ydim}; expected {grid.nline} x {grid.nsample}")
    return grid


@dataclass(frozen=True)
class AgpFile:
    """An AGP's heights on its path's 1.1 km grid: ``(block, line, sample)`` over :attr:`blocks`;
    NaN where the file holds its fill value. Heights and sigmas in metres."""

    path: int
    blocks: NDArray[np.int64]
    ave_scene_elev: Array
    std_dev_scene_elev: Array
    pt_elev: Array | None
    source: Path


def _field(path: Path, e: Any, grid: str, name: str, blocks: NDArray[np.int64]) -> Array:
    fields = e.grids[grid]["fields"]
    if name not in fields:
        raise FileFormatError(path, f"grid {grid}: no field {name!r} (has {', '.join(fields)})")
    a = read_eos_field(path, name, list(blocks - 1)).astype(np.float64)
    fv = e.grid_attributes.get(grid, {}).get(f"_FV_{name}")
    if fv is not None:
        a[a == float(fv)] = np.nan
    return a


def read_agp(path: str | os.PathLike[str], blocks: Sequence[int] | None = None) -> AgpFile:
    """Read an AGP file's ``Standard`` grid (``AveSceneElev``, ``StdDevSceneElev``, ``PtElev`` where
    present) over ``blocks`` (default: ``Start_block``..``End block``, or all 180)."""
    p = Path(path)
    e = read_eos_file(p)
    if "Standard" not in e.grids:
        raise FileFormatError(p, f"no grid 'Standard' (grids: {', '.join(e.grids) or 'none'}); not an AGP")
    grid = _check_som_grid(p, "Standard", e.grids["Standard"], 1100)
    if blocks is None:
        start, end = e.attributes.get("Start_block", 1), e.attributes.get("End block", N_BLOCKS)
        chosen = np.arange(int(start), int(end) + 1)
    else:
        chosen = np.asarray(list(blocks), dtype=np.int64)
    if chosen.size == 0 or chosen.min() < 1 or chosen.max() > N_BLOCKS:
        raise InputError("blocks", chosen.tolist()[:3], f"blocks in 1..{N_BLOCKS}")
    fields = e.grids["Standard"]["fields"]
    return AgpFile(
        path=grid.path,
        blocks=chosen,
        ave_scene_elev=_field(p, e, "Standard", "AveSceneElev", chosen),
        std_dev_scene_elev=_field(p, e, "Standard", "StdDevSceneElev", chosen),
        pt_elev=_field(p, e, "Standard", "PtElev", chosen) if "PtElev" in fields else None,
        source=p,
    )


def agp_to_dem(agp: AgpFile, posting_arcsec: float = 30.0, tile_postings: int = 64, quality: int = 1) -> Any:
    """The AGP's heights as square geographic DEM tiles (:class:`~misrgraph.model.dem.DemTiles`)
    with each posting's 1-sigma from ``StdDevSceneElev``.

    Each posting of a ``posting_arcsec`` geographic grid over the blocks takes the bilinear
    interpolation of ``AveSceneElev`` at its (block, line, sample) (edges clamped inside the
    block); postings off the blocks or on fill make their tile drop out."""
    from scipy.ndimage import map_coordinates

    from misrgraph.io.external import _tile_starts
    from misrgraph.model.dem import DemTiles, wrap_deg

    if not (posting_arcsec > 0 and np.isfinite(posting_arcsec)):
        raise InputError("posting_arcsec", posting_arcsec, "a positive number of arc seconds")
    if not (isinstance(tile_postings, int) and tile_postings >= 32):
        raise InputError("tile_postings", tile_postings, "a whole number of postings >= 32")
    grid = SomGrid(agp.path, 1100)
    post = posting_arcsec / 3600.0
    # the blocks' footprint in latitude/longitude
    lats, lons = [], []
    for b in agp.blocks:
        ln, s = np.meshgrid(np.linspace(-0.5, grid.nline - 0.5, 9), np.linspace(-0.5, grid.nsample - 0.5, 33))
        la, lo = grid.bls_to_latlon(np.full(ln.shape, int(b)), ln, s)
        lats.append(la.ravel())
        lons.append(lo.ravel())
    lat_all, lon_all = np.concatenate(lats), np.concatenate(lons)
    ref = float(lon_all[0])
    lon_rel = wrap_deg(lon_all - ref)
    i0, i1 = int(np.floor(lat_all.min() / post)), int(np.ceil(lat_all.max() / post))
    j0 = int(np.floor((ref + lon_rel.min()) / post))
    j1 = int(np.ceil((ref + lon_rel.max()) / post))
    lat_axis = np.arange(i0, i1 + 1) * post
    lon_axis = np.arange(j0, j1 + 1) * post
    lon_g, lat_g = np.meshgrid(lon_axis, lat_axis)
    blk, line, sample = grid.latlon_to_bls(lat_g, wrap_deg(lon_g), strict=False)
    height = np.full(lat_g.shape, np.nan)
    sigma = np.full(lat_g.shape, np.nan)
    for k, b in enumerate(agp.blocks):
        m = blk == b
        if not m.any():
            continue
        coords = np.stack([np.clip(line[m], 0, grid.nline - 1), np.clip(sample[m], 0, grid.nsample - 1)])
        h = agp.ave_scene_elev[k]
        sd = agp.std_dev_scene_elev[k]
        hv = map_coordinates(h, coords, order=1, mode="nearest", prefilter=False)
        nan_near = map_coordinates(np.isnan(h).astype(float), coords, order=1, mode="nearest", prefilter=False) > 0
        height[m] = np.where(nan_near, np.nan, hv)
        sigma[m] = map_coordinates(np.nan_to_num(sd), coords, order=1, mode="nearest", prefilter=False)
    n_rows, n_cols = height.shape
    if n_rows < tile_postings or n_cols < tile_postings:
        raise InputError(
            f'AGP blocks on the {posting_arcsec:g}" grid', (n_rows, n_cols), f"at least {tile_postings} postings a side"
        )
    lat0s, lon0s, hs, ss = [], [], [], []
    for starts_r in _tile_starts(n_rows, tile_postings):
        for starts_c in _tile_starts(n_cols, tile_postings):
            t = height[starts_r : starts_r + tile_postings, starts_c : starts_c + tile_postings]
            if not np.all(np.isfinite(t)):
                continue
            lat0s.append(lat_axis[starts_r])
            lon0s.append(lon_axis[starts_c])
            hs.append(t)
            ss.append(sigma[starts_r : starts_r + tile_postings, starts_c : starts_c + tile_postings])
    if not hs:
        raise InputError("AGP", str(agp.source), "a tile of postings without fill values")
    heights = np.stack(hs)
    return DemTiles(
        np.array(lat0s),
        wrap_deg(np.array(lon0s)),
        heights,
        np.ones(heights.shape, np.uint8),
        np.full(len(hs), int(quality), np.int64),
        post,
        sigma_m=np.stack(ss),
    )


@dataclass(frozen=True)
class L1b2Band:
    """One band of an L1B2 file over :attr:`blocks`: ``radiance (block, line, sample)`` (the file's
    units; NaN where fill or obscured), ``rdqi`` (0..3; 3 where fill), ``fill`` and ``obscured``
    masks."""

    path: int
    camera: str | None
    band: str
    resolution_m: int
    blocks: NDArray[np.int64]
    radiance: Array
    rdqi: NDArray[np.uint8]
    fill: NDArray[np.bool_]
    obscured: NDArray[np.bool_]
    scale_factor: float


def read_l1b2(path: str | os.PathLike[str], band: str = "red", blocks: Sequence[int] | None = None) -> L1b2Band:
    """Read one band of an L1B2 (terrain or ellipsoid) or ROI file: grid ``<Band>Band``, field
    ``<Band> Radiance/RDQI`` unpacked (module docstring)."""
    name = _BANDS.get(band.lower())
    if name is None:
        raise InputError("band", band, tuple(_BANDS))
    p = Path(path)
    e = read_eos_file(p)
    gname, fname = f"{name}Band", f"{name} Radiance/RDQI"
    if gname not in e.grids:
        raise FileFormatError(p, f"no grid {gname!r} (grids: {', '.join(e.grids) or 'none'})")
    grid = _check_som_grid(p, gname, e.grids[gname], None)
    if fname not in e.grids[gname]["fields"]:
        raise FileFormatError(p, f"grid {gname}: no field {fname!r}")
    if blocks is None:
        chosen = np.arange(int(e.attributes.get("Start_block", 1)), int(e.attributes.get("End block", N_BLOCKS)) + 1)
    else:
        chosen = np.asarray(list(blocks), dtype=np.int64)
    raw = read_eos_field(p, fname, list(chosen - 1)).astype(np.int64)
    gattrs = e.grid_attributes.get(gname, {})
    fill_value = int(gattrs.get(f"_FV_{fname}", RDQI_FILL))
    terrain = "TERRAIN" in p.name.upper() or "_ROI_" in p.name.upper()
    threshold = fill_value - 4 if terrain else fill_value
    scale = gattrs.get("Scale factor")
    if scale is None:
        raise FileFormatError(p, f"grid {gname}: no 'Scale factor' attribute")
    fill = raw >= fill_value
    obscured = (raw >= threshold) & ~fill
    good = raw < threshold
    return L1b2Band(
        path=grid.path,
        camera=str(e.attributes["Camera"]) if "Camera" in e.attributes else camera_of_file_name(p.name),
        band=band.lower(),
        resolution_m=grid.resolution_m,
        blocks=chosen,
        radiance=np.where(good, (raw >> 2) * float(scale), np.nan),
        rdqi=np.where(good, raw & 3, 3).astype(np.uint8),
        fill=fill,
        obscured=obscured,
        scale_factor=float(scale),
    )
