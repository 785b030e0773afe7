"""Ground control point database (seed section 3.3).

About 120 GCPs: ~60 in the USA, ~50 equally across Russia, Africa and South America, the rest
in Australia / New Zealand, all on land. Each has a geodetic position (WGS84 lat/lon in degrees,
ellipsoidal height in m) with 30 m (1 sigma) accuracy per ENU axis and optionally nine 64 x 64
image chips (one per camera). Files: :mod:`misrgraph.io.gcp` (HDF5 kind ``gcp_database``); the
simulated database: :mod:`misrgraph.sim.gcps`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from factors.geometry import enu_covariance
from misrgraph.errors import InputError
from misrgraph.model.frames import geodetic_to_ecef

__all__ = ["GcpDatabase", "GCP_REGIONS"]

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
    """GCPs: ``id (G,)``, ``lat, lon (G,)`` deg, ``height (G,)`` m ellipsoidal, ``sigma_m`` m: 1 sigma
    on every ENU axis ``(G,)`` or per axis (east, north, up) ``(G, 3)``, ``region (G,)`` names,
    optional ``chips (G, 9, 64, 64)`` uint8."""

    id: NDArray[np.int64]
    lat: Array
    lon: Array
    height: Array
    sigma_m: Array
    region: NDArray[np.str_]
    chips: NDArray[np.uint8] | None = None

    def __post_init__(self) -> None:
        g = np.asarray(self.id).size
        for name in ("lat", "lon", "height", "sigma_m"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (g,) and not (name == "sigma_m" and arr.shape == (g, 3)):
                raise InputError(f"gcp.{name}", arr.shape, f"shape ({g},)" + (f" or ({g}, 3)" if name == "sigma_m" else ""))
            setattr(self, name, arr)
        if np.any(np.abs(self.lat) > 90):
            raise InputError("gcp.lat", float(self.lat[np.abs(self.lat) > 90][0]), "latitudes within -90..90 deg")
        if not np.all(self.sigma_m > 0):  # NaN fails too
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
        return enu_covariance(np.radians(self.lat), np.radians(self.lon), self.sigma_m if self.sigma_m.ndim == 2 else self.sigma_m[:, None])
