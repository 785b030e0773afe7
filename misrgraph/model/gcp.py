"""Ground control point database (seed section 3.3).

About 120 GCPs: ~60 in the USA, ~50 equally across Russia, Africa and South America, the rest
in Australia / New Zealand, all on land (``global-land-mask``). Each has a geodetic position
(WGS84 lat/lon in degrees, ellipsoidal height in m) with 30 m (1 sigma) accuracy per ENU axis and
optionally nine 64 x 64 image chips (one per camera). Saved as HDF5 kind ``gcp_database``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from misrgraph.model.dem import Geoid, SyntheticTerrain, land_mask
from misrgraph.errors import FileFormatError, InputError
from misrgraph.model.frames import enu_basis, geodetic_to_ecef
from misrgraph.io.h5 import atomic_h5, create_dataset, open_h5, read_dataset, write_dataset

__all__ = ["GcpDatabase", "GCP_REGIONS", "generate_gcp_database"]

Array = NDArray[np.float64]

#: (name, weight of the ~120 points, list of (lat_min, lat_max, lon_min, lon_max) boxes)
GCP_REGIONS: list[tuple[str, int, list[tuple[float, float, float, float]]]] = [
    ("USA", 60, [(25.0, 49.0, -124.5, -67.0)]),
    ("Russia", 17, [(45.0, 68.0, 30.0, 140.0)]),
    ("Africa", 17, [(-34.0, 35.0, -17.0, 50.0)]),
    ("South America", 16, [(-54.0, 11.0, -80.0, -35.0)]),
    ("Australia/New Zealand", 10, [(-39.0, -12.0, 114.0, 153.0), (-46.5, -35.0, 167.0, 178.5)]),
]


@dataclass
class GcpDatabase:
    """GCPs: ``id (G,)``, ``lat, lon (G,)`` deg, ``height (G,)`` m ellipsoidal, ``sigma_m (G,)``
    (1 sigma per ENU axis), ``region (G,)`` names, optional ``chips (G, 9, 64, 64)`` uint8 and
    optional ``truth_ecef (G, 3)`` (simulated data only)."""

    id: NDArray[np.int64]
    lat: Array
    lon: Array
    height: Array
    sigma_m: Array
    region: NDArray[np.str_]
    chips: NDArray[np.uint8] | None = None
    truth_ecef: Array | None = None

    def __post_init__(self) -> None:
        g = np.asarray(self.id).size
        for name in ("lat", "lon", "height", "sigma_m"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (g,):
                raise InputError(f"gcp.{name}", arr.shape, f"shape ({g},)")
            setattr(self, name, arr)
        if np.any(np.abs(self.lat) > 90):
            raise InputError("gcp.lat", float(self.lat[np.abs(self.lat) > 90][0]), "latitudes within -90..90 deg")
        if np.any(self.sigma_m <= 0):
            raise InputError("gcp.sigma_m", float(self.sigma_m.min()), "positive metres")
        self.id = np.asarray(self.id, dtype=np.int64)
        self.region = np.asarray(self.region).astype(str)
        if self.chips is not None and self.chips.shape[:2] != (g, 9):
            raise InputError("gcp.chips", self.chips.shape, f"shape ({g}, 9, 64, 64)")

    def __len__(self) -> int:
        return int(self.id.size)

    def ecef(self) -> Array:
        """Database positions in ECEF (m), ``(G, 3)``."""
        return geodetic_to_ecef(self.lat, self.lon, self.height)

    def covariance_ecef(self) -> Array:
        """Full ECEF covariance ``(G, 3, 3)`` from sigma per ENU axis: ``R diag(s^2) R^T``."""
        r = enu_basis(self.lat, self.lon)
        s2 = self.sigma_m**2
        return np.einsum("gij,g,gkj->gik", r, s2, r)

    def save(self, path: str | os.PathLike[str]) -> None:
        with atomic_h5(path, "gcp_database") as f:
            g = f.create_group("gcp")
            write_dataset(g, "id", self.id)
            write_dataset(g, "lat", self.lat, units="deg", datum="WGS84")
            write_dataset(g, "lon", self.lon, units="deg", datum="WGS84")
            write_dataset(g, "height", self.height, units="m", reference="WGS84 ellipsoid")
            write_dataset(g, "sigma_m", self.sigma_m, units="m", meaning="1 sigma per ENU axis")
            g.create_dataset("region", data=np.asarray(self.region, dtype=object), dtype=__import__("h5py").string_dtype())
            if self.chips is not None:
                create_dataset(g, "chips", self.chips, compression="gzip")
                g["chips"].attrs["cameras"] = "Df,Cf,Bf,Af,An,Aa,Ba,Ca,Da"
            if self.truth_ecef is not None:
                t = f.create_group("truth")
                write_dataset(t, "ecef", self.truth_ecef, units="m", frame="ECEF")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "GcpDatabase":
        with open_h5(path, "gcp_database") as f:
            if "gcp" not in f:
                raise FileFormatError(path, "missing group /gcp")
            g = f["gcp"]
            ids = read_dataset(g, "id", (None,), dtype=np.int64)
            n = ids.size
            region = read_dataset(g, "region", (n,), dtype=None)
            region = np.array([r.decode() if isinstance(r, bytes) else str(r) for r in region])
            chips = read_dataset(g, "chips", (n, 9, None, None), dtype=np.uint8) if "chips" in g else None
            truth = read_dataset(f["truth"], "ecef", (n, 3)) if "truth" in f else None
            return cls(
                ids,
                read_dataset(g, "lat", (n,)),
                read_dataset(g, "lon", (n,)),
                read_dataset(g, "height", (n,)),
                read_dataset(g, "sigma_m", (n,)),
                region,
                chips,
                truth,
            )


def generate_gcp_database(
    rng: np.random.Generator,
    terrain: SyntheticTerrain,
    n_total: int = 120,
    sigma_m: float = 30.0,
    geoid: Geoid | None = None,
    with_chips: bool = False,
) -> GcpDatabase:
    """Draw GCPs on land in the seed's regions; database position = truth + N(0, sigma) per ENU axis."""
    if n_total < len(GCP_REGIONS):
        raise InputError("n_gcps", n_total, f"at least {len(GCP_REGIONS)}")
    geoid = geoid or Geoid("zero")
    weights = np.array([w for _, w, _ in GCP_REGIONS], float)
    counts = np.floor(weights / weights.sum() * n_total).astype(int)
    counts[0] += n_total - counts.sum()
    lats, lons, regions = [], [], []
    for (name, _, boxes), count in zip(GCP_REGIONS, counts):
        got = 0
        while got < count:
            box = boxes[rng.integers(len(boxes))]
            la = rng.uniform(box[0], box[1], 64)
            lo = rng.uniform(box[2], box[3], 64)
            ok = land_mask(la, lo)
            take = min(count - got, int(ok.sum()))
            lats += la[ok][:take].tolist()
            lons += lo[ok][:take].tolist()
            regions += [name] * take
            got += take
    lat = np.array(lats)
    lon = np.array(lons)
    h = terrain.height(lat, lon) + geoid.undulation(lat, lon)
    truth = geodetic_to_ecef(lat, lon, h)
    sig = np.full(lat.size, sigma_m)
    enu = enu_basis(lat, lon)
    measured = truth + np.einsum("gij,gj->gi", enu, rng.standard_normal((lat.size, 3)) * sigma_m)
    from misrgraph.model.frames import ecef_to_geodetic

    mlat, mlon, mh = ecef_to_geodetic(measured)
    chips = None
    if with_chips:
        # stand-in chips: textured patterns unique per GCP and camera (no real imagery offline)
        yy, xx = np.mgrid[0:64, 0:64]
        chips = np.empty((lat.size, 9, 64, 64), np.uint8)
        for i in range(lat.size):
            f = rng.uniform(0.05, 0.3, (9, 2))
            ph = rng.uniform(0, 6.3, (9, 1, 1))
            chips[i] = (127 + 100 * np.sin(f[:, 0, None, None] * xx + f[:, 1, None, None] * yy + ph)).astype(np.uint8)
    return GcpDatabase(np.arange(lat.size, dtype=np.int64), mlat, mlon, mh, sig, np.array(regions), chips, truth)
