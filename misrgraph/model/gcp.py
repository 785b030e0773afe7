"""Ground control point database (seed section 3.3).

About 120 GCPs: ~60 in the USA, ~50 equally across Russia, Africa and South America, the rest
in Australia / New Zealand, all on land. Each has a geodetic position (WGS84 lat/lon in degrees,
ellipsoidal height in m) with 30 m (1 sigma) accuracy per ENU axis and optionally nine 64 x 64
image chips (one per camera).

A catalogue built from imagery (the MISR GCPs come from Landsat scenes) has errors that the GCPs
of one source scene share: the scene's own registration error. ``scene`` names each GCP's source
(-1: none known) and ``scene_sigma_m`` the shared part of ``sigma_m`` (1 sigma per ENU axis, m);
the pass adjustment then gives each source scene one offset variable (prior ``scene_sigma_m``) and
each GCP its own part ``sqrt(sigma_m^2 - scene_sigma_m^2)``, so that averaging GCPs of one scene
cannot beat the scene's registration (:func:`factors.priors.gcp_scene_prior`).

Files: :mod:`misrgraph.io.gcp` (HDF5 kind ``gcp_database``); the
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
    optional ``chips (G, 9, 64, 64)`` uint8; optional ``scene (G,)`` int, the source scene of each
    GCP (-1: none), with ``scene_sigma_m (G,)`` m, the share of ``sigma_m`` (per ENU axis) common to
    the GCPs of that scene (module docstring)."""

    id: NDArray[np.int64]
    lat: Array
    lon: Array
    height: Array
    sigma_m: Array
    region: NDArray[np.str_]
    chips: NDArray[np.uint8] | None = None
    scene: NDArray[np.int64] | None = None
    scene_sigma_m: Array | None = None

    def __post_init__(self) -> None:
        g = np.asarray(self.id).size
        for name in ("lat", "lon", "height", "sigma_m"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (g,) and not (name == "sigma_m" and arr.shape == (g, 3)):
                raise InputError(
                    f"gcp.{name}", arr.shape, f"shape ({g},)" + (f" or ({g}, 3)" if name == "sigma_m" else "")
                )
            setattr(self, name, arr)
        if np.any(np.abs(self.lat) > 90):
            raise InputError("gcp.lat", float(self.lat[np.abs(self.lat) > 90][0]), "latitudes within -90..90 deg")
        if not np.all(self.sigma_m > 0):  # NaN fails too
            raise InputError("gcp.sigma_m", float(self.sigma_m.min()), "positive metres")
        self.id = np.asarray(self.id, dtype=np.int64)
        self.region = np.asarray(self.region).astype(str)
        if self.chips is not None and self.chips.shape[:2] != (g, 9):
            raise InputError("gcp.chips", self.chips.shape, f"shape ({g}, 9, 64, 64)")
        if (self.scene is None) != (self.scene_sigma_m is None):
            raise InputError(
                "gcp.scene_sigma_m",
                None if self.scene_sigma_m is None else "given",
                "scene and scene_sigma_m together (the source scene of each GCP and its shared sigma)",
            )
        if self.scene is not None:
            sc = np.asarray(self.scene)
            if sc.shape != (g,) or not np.all(sc == np.round(sc)) or np.any(sc < -1):
                raise InputError(
                    "gcp.scene",
                    sc.shape if sc.shape != (g,) else sc[(sc != np.round(sc)) | (sc < -1)][:1].tolist(),
                    f"shape ({g},) whole numbers >= -1 (-1: no source scene)",
                )
            self.scene = sc.astype(np.int64)
            ss = np.asarray(self.scene_sigma_m, dtype=float)
            if ss.shape != (g,):
                raise InputError("gcp.scene_sigma_m", ss.shape, f"shape ({g},)")
            smin = self.sigma_m if self.sigma_m.ndim == 1 else self.sigma_m.min(axis=1)
            bad = np.flatnonzero(~((ss >= 0) & ((ss < smin) | (self.scene < 0))))
            if bad.size:
                raise InputError(
                    f"gcp.scene_sigma_m[{bad[0]}]",
                    float(ss[bad[0]]),
                    f">= 0 and below the GCP's sigma_m ({float(smin[bad[0]])} m): the shared part of it",
                )
            self.scene_sigma_m = np.where(self.scene >= 0, ss, 0.0)
            for sc_id in np.unique(self.scene[self.scene >= 0]):
                vals = self.scene_sigma_m[self.scene == sc_id]
                if np.ptp(vals) > 1e-9 * max(1.0, float(vals.max())):
                    raise InputError(
                        f"gcp.scene_sigma_m of scene {int(sc_id)}",
                        vals.tolist()[:4],
                        "one value for all the GCPs of a source scene",
                    )

    def __len__(self) -> int:
        return int(self.id.size)

    def ecef(self) -> Array:
        """Database positions in ECEF (m), ``(G, 3)``."""
        return geodetic_to_ecef(self.lat, self.lon, self.height)

    def covariance_ecef(self) -> Array:
        """Full ECEF covariance ``(G, 3, 3)`` from sigma per ENU axis: ``R diag(s^2) R^T``."""
        return enu_covariance(
            np.radians(self.lat),
            np.radians(self.lon),
            self.sigma_m if self.sigma_m.ndim == 2 else self.sigma_m[:, None],
        )

    def own_covariance_ecef(self) -> Array:
        """ECEF covariance ``(G, 3, 3)`` of each GCP's own error: ``sigma_m^2 - scene_sigma_m^2``
        per ENU axis (the whole of it where no source scene is known)."""
        s = self.sigma_m if self.sigma_m.ndim == 2 else self.sigma_m[:, None]
        shared = np.zeros((len(self), 1)) if self.scene_sigma_m is None else self.scene_sigma_m[:, None]
        return enu_covariance(np.radians(self.lat), np.radians(self.lon), np.sqrt(s**2 - shared**2))

    def scenes(self) -> dict[int, NDArray[np.int64]]:
        """Source scene -> the rows of its GCPs (scenes with a shared sigma > 0 only)."""
        if self.scene is None or self.scene_sigma_m is None:
            return {}
        ok = (self.scene >= 0) & (self.scene_sigma_m > 0)
        return {int(s): np.flatnonzero(ok & (self.scene == s)) for s in np.unique(self.scene[ok])}
