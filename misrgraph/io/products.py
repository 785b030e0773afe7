"""Projection Parameters: the data (:class:`ProjectionParameters`) and their HDF5 file (kind
``projection_parameters``; written atomically, validated on read). How they are computed and what
each field means: :mod:`misrgraph.products.pp`."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates

from misrgraph.errors import FileFormatError, InputError
from misrgraph.io.h5 import atomic_h5, open_h5, read_attr, read_dataset, require_group, write_dataset
from misrgraph.misr.som import N_BLOCKS, SomGrid
from misrgraph.model.constants import N_PIXELS

__all__ = ["ProjectionParameters", "PP_COEFFICIENTS", "PP_SIGMAS", "PP_UNITS", "save_pp", "read_pp"]

Array = NDArray[np.float64]

#: The height quadratic's coefficient grids: image line and sample at height 0 (pixels), and their
#: first (pixels/m) and second (pixels/m^2) derivatives with respect to ellipsoidal height.
PP_COEFFICIENTS = ("line0", "dline_dh", "d2line_dh2", "sample0", "dsample_dh", "d2sample_dh2")
#: The uncertainty grids: 1-sigma of line and sample (pixels), their correlation, and the
#: horizontal geolocation 1-sigma (m, radial RMS).
PP_SIGMAS = ("sigma_line", "sigma_sample", "correlation", "sigma_m")
#: Each grid's unit.
PP_UNITS: dict[str, str] = {
    "line0": "pixel",
    "dline_dh": "pixel/m",
    "d2line_dh2": "pixel/m^2",
    "sample0": "pixel",
    "dsample_dh": "pixel/m",
    "d2sample_dh2": "pixel/m^2",
    "sigma_line": "pixel",
    "sigma_sample": "pixel",
    "correlation": "1",
    "sigma_m": "m",
}


@dataclass
class ProjectionParameters:
    """PP of one pass on one path's 1.1 km SOM grid. Arrays are ``(camera, block, line, sample)``
    over :attr:`cameras` x :attr:`blocks` x 128 x 512; they extend a margin beyond the array's
    edges (:meth:`seen` says which points the array images) and are NaN beyond it. Units: pixels,
    pixels/m, pixels/m^2; ``sigma_*`` pixels, ``sigma_m`` metres."""

    path: int
    blocks: NDArray[np.int64]
    cameras: tuple[str, ...]
    band: str
    pass_id: str
    line0: Array
    dline_dh: Array
    d2line_dh2: Array
    sample0: Array
    dsample_dh: Array
    d2sample_dh2: Array
    sigma_line: Array
    sigma_sample: Array
    correlation: Array
    sigma_m: Array
    resolution_m: int = 1100
    provenance: dict[str, str] = field(default_factory=dict)

    @property
    def grid(self) -> SomGrid:
        return SomGrid(self.path, self.resolution_m)

    def coefficient(self, name: str) -> Array:
        if name not in PP_COEFFICIENTS:
            raise InputError("coefficient", name, PP_COEFFICIENTS)
        return getattr(self, name)

    def image_coords(
        self, camera: str, block: int, line: Array, sample: Array, height: Array, resolution_m: int = 1100
    ) -> tuple[Array, Array]:
        """Image (line, sample) in ``camera`` of block points given at ``resolution_m`` (1100 or
        275: fractional block line/sample of that grid) at ellipsoidal ``height`` (m), by
        bilinear interpolation of the coefficient grids. NaN outside the camera's view."""
        if camera not in self.cameras:
            raise InputError("camera", camera, self.cameras)
        hit = np.flatnonzero(self.blocks == block)
        if hit.size == 0:
            raise InputError("block", block, f"one of the PP's blocks {self.blocks.min()}..{self.blocks.max()}")
        if resolution_m not in (275, 1100):
            raise InputError("resolution_m", resolution_m, (275, 1100))
        c, b = self.cameras.index(camera), int(hit[0])
        scale = self.resolution_m / resolution_m
        ln = (np.asarray(line, dtype=float) + 0.5) / scale - 0.5
        sm = (np.asarray(sample, dtype=float) + 0.5) / scale - 0.5
        h = np.asarray(height, dtype=float)
        nl, ns = self.line0.shape[2:]
        ln, sm = np.broadcast_arrays(np.clip(ln, 0, nl - 1), np.clip(sm, 0, ns - 1))
        coords = np.stack([ln.ravel(), sm.ravel()])
        # bilinear between grid points (order 1: a NaN corner makes the point NaN)
        v = {
            k: map_coordinates(self.coefficient(k)[c, b], coords, order=1, mode="nearest", prefilter=False).reshape(
                ln.shape
            )
            for k in PP_COEFFICIENTS
        }
        line_h = v["line0"] + v["dline_dh"] * h + v["d2line_dh2"] * h**2
        sample_h = v["sample0"] + v["dsample_dh"] * h + v["d2sample_dh2"] * h**2
        off = ~((sample_h >= -0.5) & (sample_h <= N_PIXELS - 0.5))  # beyond the array: not imaged
        return np.where(off, np.nan, line_h), np.where(off, np.nan, sample_h)

    def seen(self) -> NDArray[np.bool_]:
        """Which grid points (camera, block, line, sample) the array images at height 0."""
        return np.isfinite(self.line0) & (self.sample0 >= -0.5) & (self.sample0 <= N_PIXELS - 0.5)

    def coverage(self) -> dict[str, dict[str, float | None]]:
        """Per camera, the fraction of grid points the array images (``fraction_seen``) and the
        median horizontal 1-sigma in metres (``sigma_m_median``; None where there is none)."""
        seen = self.seen()
        return {
            "fraction_seen": {c: float(np.mean(seen[i])) for i, c in enumerate(self.cameras)},
            "sigma_m_median": {
                c: float(np.nanmedian(self.sigma_m[i])) if np.isfinite(self.sigma_m[i]).any() else None
                for i, c in enumerate(self.cameras)
            },
        }


def save_pp(pp: ProjectionParameters, path: str | os.PathLike[str]) -> None:
    """Write ``pp`` as an HDF5 file of kind ``projection_parameters`` (atomically; float32 grids,
    chunked per block and compressed)."""
    with atomic_h5(path, "projection_parameters") as f:
        f.attrs["path"] = pp.path
        f.attrs["resolution_m"] = pp.resolution_m
        f.attrs["band"] = pp.band
        f.attrs["pass_id"] = pp.pass_id
        f.attrs["cameras"] = ",".join(pp.cameras)
        prov = f.create_group("provenance")
        for k, v in pp.provenance.items():
            prov.attrs[k] = str(v)
        write_dataset(f, "blocks", pp.blocks.astype(np.int64))
        g = f.create_group("grids")
        g.attrs["order"] = "camera, block, line, sample"
        for name in PP_COEFFICIENTS + PP_SIGMAS:
            a = np.asarray(getattr(pp, name))
            ds = g.create_dataset(
                name,
                data=a.astype(np.float64 if name in ("line0", "sample0") else np.float32),
                chunks=(1, 1) + a.shape[2:],
                compression="gzip",
                compression_opts=4,
                shuffle=True,
                fletcher32=True,
            )
            ds.attrs["units"] = PP_UNITS[name]


def read_pp(path: str | os.PathLike[str]) -> ProjectionParameters:
    """Read a ``projection_parameters`` file, checking every grid's shape."""
    with open_h5(path, "projection_parameters") as f:
        blocks = read_dataset(f, "blocks", (None,), dtype=np.int64)
        cameras = tuple(str(read_attr(f, "cameras")).split(","))
        path_ = int(read_attr(f, "path"))
        res = int(read_attr(f, "resolution_m"))
        grid = SomGrid(path_, res)
        g = require_group(f, "grids")
        shape = (len(cameras), blocks.size, grid.nline, grid.nsample)
        arrays = {name: read_dataset(g, name, shape) for name in PP_COEFFICIENTS + PP_SIGMAS}
        prov = {k: str(v) for k, v in f["provenance"].attrs.items()} if "provenance" in f else {}
        if np.any((blocks < 1) | (blocks > N_BLOCKS)):
            raise FileFormatError(path, f"/blocks holds {blocks.tolist()}; expected block numbers in 1..{N_BLOCKS}")
        return ProjectionParameters(
            path=path_,
            blocks=blocks,
            cameras=cameras,
            band=str(read_attr(f, "band")),
            pass_id=str(read_attr(f, "pass_id")),
            resolution_m=res,
            provenance=prov,
            **arrays,
        )
