"""Reference Orbit Imagery files: HDF5 (kind ``reference_orbit_imagery``), Cloud-Optimised GeoTIFF
export in the path's ``misrsom`` CRS, and quick-look PNGs. How the ROI is made:
:mod:`misrgraph.products.roi`.

HDF5 layout (written block by block into a temporary file, renamed into place when complete)::

    attrs: path, resolution_m (275), band, cameras ("Df,Cf,..."), pass_ids ("P037_O0000,..."),
           full_scale_dn
    blocks (B,)                      block numbers
    pixels (C, B, 512, 2048) uint16  counts (0: no pass images the point)
    source (C, B, 512, 2048) int8    index into pass_ids of each pixel's pass (-1: none)
    cloudy (C, B, 512, 2048) uint8   1 where no pass images the point clear of cloud
    obscured (C, B, 512, 2048) uint8 1 where terrain hides the point in every pass that would
                                     image it (the pixel is then empty, source -1)
    clear_fraction (B, P)            clear share of each pass's pixels per block
    chosen (B,)                      the clearest pass of each block (index into pass_ids)

GeoTIFF: one mosaic per camera over all blocks on the path's SOM grid (x along the path, y
across it; blocks placed by their offsets), north-up in SOM coordinates (rows from the largest
SOM y down), 0 as no-data, written through rasterio's COG driver. GeoTIFF's keys cannot encode
the Space Oblique Mercator, so GDAL keeps the ``misrsom`` CRS in the ``.tif.aux.xml`` beside each
file: keep the two together (rasterio, QGIS and gdalinfo read it from there).
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from numpy.typing import NDArray

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_file, atomic_h5, open_h5, read_attr, read_dataset, write_dataset
from misrgraph.misr.som import BLOCK1_CORNER_SOM, SomGrid
from misrgraph.model.constants import CAMERAS

__all__ = ["RoiFile", "roi_writer", "read_roi", "export_roi_geotiff", "write_quicklooks"]


@dataclass
class RoiFile:
    """A ROI file's contents (arrays as in the module docstring)."""

    path: int
    band: str
    cameras: tuple[str, ...]
    pass_ids: tuple[str, ...]
    blocks: NDArray[np.int64]
    pixels: NDArray[np.uint16]
    source: NDArray[np.int8]
    cloudy: NDArray[np.bool_]
    obscured: NDArray[np.bool_]
    clear_fraction: NDArray[np.float64]
    chosen: NDArray[np.int64]
    full_scale_dn: int
    resolution_m: int = 275


class _Writer:
    def __init__(self, f: Any, blocks: NDArray[np.int64], n_cam: int, n_pass: int, nline: int, nsample: int) -> None:
        self.f, self.blocks = f, blocks
        shape = (n_cam, blocks.size, nline, nsample)
        chunks = (1, 1, min(128, nline), min(512, nsample))
        opts = dict(chunks=chunks, compression="gzip", compression_opts=4, shuffle=True, fletcher32=True)
        self.pixels = f.create_dataset("pixels", shape=shape, dtype=np.uint16, fillvalue=0, **opts)
        self.pixels.attrs["units"] = "counts (14 bit)"
        self.source = f.create_dataset("source", shape=shape, dtype=np.int8, fillvalue=-1, **opts)
        self.source.attrs["meaning"] = "index into the pass_ids attribute; -1: no pass images the point"
        self.cloudy = f.create_dataset("cloudy", shape=shape, dtype=np.uint8, fillvalue=0, **opts)
        self.obscured = f.create_dataset("obscured", shape=shape, dtype=np.uint8, fillvalue=0, **opts)
        self.obscured.attrs["meaning"] = "1: terrain hides the point from the camera in every pass that would image it"
        self.clear = np.zeros((blocks.size, n_pass))
        self.chosen = np.full(blocks.size, -1, np.int64)
        self.written = np.zeros(blocks.size, bool)

    def write(self, block: Any) -> None:
        """Store one :class:`misrgraph.products.roi.RoiBlock`."""
        hit = np.flatnonzero(self.blocks == block.block)
        if hit.size == 0:
            raise InputError("block", block.block, f"one of {self.blocks.tolist()}")
        k = int(hit[0])
        self.pixels[:, k] = block.pixels
        self.source[:, k] = block.source
        self.cloudy[:, k] = block.cloudy.astype(np.uint8)
        self.obscured[:, k] = block.obscured.astype(np.uint8)
        self.clear[k] = block.clear_fraction
        self.chosen[k] = block.chosen
        self.written[k] = True


@contextmanager
def roi_writer(
    path: str | os.PathLike[str],
    sky_path: int,
    band: str,
    cameras: tuple[str, ...],
    pass_ids: list[str],
    blocks: NDArray[np.int64],
    full_scale_dn: int,
) -> Iterator[_Writer]:
    """A ROI file written block by block (``writer.write(roi_block)``); it appears at ``path`` only
    when every block has been written and the block completes."""
    grid = SomGrid(int(sky_path), 275)
    blocks = np.asarray(blocks, dtype=np.int64)
    with atomic_h5(path, "reference_orbit_imagery") as f:
        f.attrs["path"] = int(sky_path)
        f.attrs["resolution_m"] = 275
        f.attrs["band"] = band
        f.attrs["cameras"] = ",".join(cameras)
        f.attrs["pass_ids"] = ",".join(pass_ids)
        f.attrs["full_scale_dn"] = int(full_scale_dn)
        write_dataset(f, "blocks", blocks)
        w = _Writer(f, blocks, len(cameras), len(pass_ids), grid.nline, grid.nsample)
        yield w
        if not w.written.all():
            raise InputError("ROI blocks", blocks[~w.written].tolist(), "every block written before the file is closed")
        write_dataset(f, "clear_fraction", w.clear, units="1")
        write_dataset(f, "chosen", w.chosen)


def read_roi(path: str | os.PathLike[str]) -> RoiFile:
    """Read a ROI file, checking every array's shape."""
    with open_h5(path, "reference_orbit_imagery") as f:
        p, res = int(read_attr(f, "path")), int(read_attr(f, "resolution_m"))
        if res != 275:
            raise FileFormatError(path, f"resolution_m is {res}; expected 275")
        grid = SomGrid(p, res)
        cameras = tuple(str(read_attr(f, "cameras")).split(","))
        if any(c not in CAMERAS for c in cameras):
            raise FileFormatError(path, f"cameras attribute {cameras} holds names other than {', '.join(CAMERAS)}")
        pass_ids = tuple(str(read_attr(f, "pass_ids")).split(","))
        blocks = read_dataset(f, "blocks", (None,), dtype=np.int64)
        shape = (len(cameras), blocks.size, grid.nline, grid.nsample)
        return RoiFile(
            p,
            str(read_attr(f, "band")),
            cameras,
            pass_ids,
            blocks,
            read_dataset(f, "pixels", shape, dtype=np.uint16),
            read_dataset(f, "source", shape, dtype=np.int8),
            read_dataset(f, "cloudy", shape, dtype=np.uint8).astype(bool),
            read_dataset(f, "obscured", shape, dtype=np.uint8).astype(bool),
            read_dataset(f, "clear_fraction", (blocks.size, len(pass_ids))),
            read_dataset(f, "chosen", (blocks.size,), dtype=np.int64),
            int(read_attr(f, "full_scale_dn")),
        )


def mosaic(roi: RoiFile, camera: str) -> tuple[NDArray[np.uint16], tuple[float, float]]:
    """One camera's blocks on a common SOM canvas ``(lines, samples)`` (block offsets applied; 0
    where no block is) and the SOM (x, y) in metres of the canvas's outer corner (line -0.5,
    sample -0.5)."""
    if camera not in roi.cameras:
        raise InputError("camera", camera, roi.cameras)
    grid = SomGrid(roi.path, roi.resolution_m)
    c = roi.cameras.index(camera)
    off = grid.block_offsets[roi.blocks - 1]
    b0 = int(roi.blocks.min())
    lines = (int(roi.blocks.max()) - b0 + 1) * grid.nline
    s_lo, s_hi = int(off.min()), int(off.max()) + grid.nsample
    canvas = np.zeros((lines, s_hi - s_lo), np.uint16)
    for k, b in enumerate(roi.blocks):
        r0 = (int(b) - b0) * grid.nline
        c0 = int(off[k]) - s_lo
        canvas[r0 : r0 + grid.nline, c0 : c0 + grid.nsample] = roi.pixels[c, k]
    r = float(roi.resolution_m)
    x0 = BLOCK1_CORNER_SOM[0] + (b0 - 1) * grid.nline * r
    y0 = BLOCK1_CORNER_SOM[1] + s_lo * r
    return canvas, (x0, y0)


def export_roi_geotiff(roi: RoiFile, out_dir: str | os.PathLike[str]) -> dict[str, str]:
    """Write ``ROI_<path>_<camera>.tif`` (Cloud-Optimised GeoTIFF, ``misrsom`` CRS) per camera
    into ``out_dir``; returns camera -> file name. Needs rasterio (the ``real`` extra)."""
    try:
        import rasterio
        from rasterio.transform import Affine
    except ImportError as exc:  # pragma: no cover - the 'real' extra is part of 'all'
        raise InputError("--geotiff", "rasterio", "rasterio installed (pip install 'misrgraph[real]')") from exc
    from misrgraph.misr.som import som_crs

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    crs = rasterio.crs.CRS.from_wkt(som_crs(roi.path).to_wkt())
    files = {}
    r = float(roi.resolution_m)
    for cam in roi.cameras:
        canvas, (x0, y0) = mosaic(roi, cam)
        # GIS orientation: columns along SOM x (the canvas's lines), rows down SOM y (samples reversed)
        img = canvas.T[::-1]
        transform = Affine(r, 0.0, x0, 0.0, -r, y0 + canvas.shape[1] * r)
        name = out / f"ROI_P{roi.path:03d}_{cam}.tif"
        tmp = out / f".tmp.{name.name}"
        aux, tmp_aux = Path(f"{name}.aux.xml"), Path(f"{tmp}.aux.xml")
        try:
            with rasterio.open(
                tmp,
                "w",
                driver="COG",
                width=img.shape[1],
                height=img.shape[0],
                count=1,
                dtype="uint16",
                crs=crs,
                transform=transform,
                nodata=0,
                compress="deflate",
            ) as dst:
                dst.write(img, 1)
                dst.update_tags(camera=cam, band=roi.band, path=str(roi.path), units="counts (14 bit)")
            if tmp_aux.exists():
                os.replace(tmp_aux, aux)
            os.replace(tmp, name)
        finally:
            tmp.unlink(missing_ok=True)
            tmp_aux.unlink(missing_ok=True)
        files[cam] = str(name)
    return files


def write_quicklooks(roi: RoiFile, out_dir: str | os.PathLike[str], step: int = 4) -> dict[str, str]:
    """``ROI_<path>_<camera>.png``: every ``step``-th pixel of each camera's mosaic, 8-bit, the
    display range from its 1st and 99th percentiles; returns camera -> file name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.image as mpimg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {}
    for cam in roi.cameras:
        canvas, _ = mosaic(roi, cam)
        small = canvas[::step, ::step].astype(float)
        valid = small > 0
        lo, hi = np.percentile(small[valid], [1, 99]) if valid.any() else (0.0, 1.0)
        img = np.clip((small - lo) / max(hi - lo, 1.0), 0, 1)
        img[~valid] = 0
        name = out / f"ROI_P{roi.path:03d}_{cam}.png"
        with atomic_file(name, binary=True) as fh:
            mpimg.imsave(fh, img, cmap="gray", vmin=0, vmax=1, format="png")
        files[cam] = str(name)
    return files
