"""Reference frames and time: WGS84 geodetic <-> ECEF, ECEF <-> ECI (J2000), local ENU.

Conventions (docs/explanation/conventions.md):

* ECEF is the conventional terrestrial frame (ITRF), metres.
* ECI is J2000 / GCRS ("GCI" in the seed), metres. ECEF <-> ECI uses the IAU 2006/2000A
  celestial-to-terrestrial matrix of ``pyerfa`` (CIO based): ``r_ecef = W @ R3(ERA) @ Q @ r_eci``
  with ``Q = c2i06a(TT)``, ``ERA = era00(UT1)`` and the polar-motion matrix ``W = pom00(xp, yp, s')``.
  UT1-UTC and polar motion are optional inputs (default 0).
* Times are float64 seconds from a per-pass epoch given as a UTC ISO-8601 string. Leap seconds
  inside a pass are not modelled (a pass is under two hours).
* Geodetic -> ECEF is WGS84 through ``pyproj`` (eq. 9); ECEF -> geodetic is the numpy iteration
  of :func:`factors.geometry.geodetic_from_ecef` (the one the DEM factor differentiates; tested
  against pyproj to 1e-9 m). Latitude/longitude in degrees at this interface, ellipsoidal height
  in metres. The WGS84 constants are defined once, in :mod:`factors.geometry`.

Performance: ``Q`` (precession-nutation) changes by less than 1e-10 rad in a minute, so it is
computed on a 60 s grid and interpolated linearly; ERA is evaluated exactly at every time. The
error of this against a direct ``erfa.c2t06a`` call is below 0.1 mm at the Earth's surface
(tested).
"""

from __future__ import annotations

import datetime as _dt
import functools
from dataclasses import dataclass

import erfa
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import Transformer

from factors.geometry import WGS84_A, WGS84_B, WGS84_E2, WGS84_F, geodetic_from_ecef, rot_z
from factors.geometry import enu_basis as _enu_basis
from misrgraph.errors import InputError

__all__ = [
    "WGS84_A",
    "WGS84_F",
    "WGS84_B",
    "WGS84_E2",
    "OMEGA_EARTH",
    "GM_EARTH",
    "geodetic_to_ecef",
    "ecef_to_geodetic",
    "enu_basis",
    "EarthOrientation",
    "parse_epoch",
]

Array = NDArray[np.float64]

OMEGA_EARTH = 7.292115e-5  # rad/s
GM_EARTH = 3.986004418e14  # m^3/s^2


@functools.lru_cache(maxsize=1)
def _to_ecef() -> Transformer:
    return Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def geodetic_to_ecef(lat_deg: ArrayLike, lon_deg: ArrayLike, h_m: ArrayLike = 0.0) -> Array:
    """WGS84 geodetic (deg, deg, m ellipsoidal) -> ECEF (m), shape ``broadcast + (3,)`` (eq. 9)."""
    lat, lon, h = np.broadcast_arrays(
        np.asarray(lat_deg, dtype=float), np.asarray(lon_deg, dtype=float), np.asarray(h_m, dtype=float)
    )
    x, y, z = _to_ecef().transform(lon.ravel(), lat.ravel(), h.ravel())
    return np.stack([x, y, z], axis=-1).reshape(lat.shape + (3,))


def ecef_to_geodetic(xyz: ArrayLike) -> tuple[Array, Array, Array]:
    """ECEF (m), shape ``(..., 3)`` -> WGS84 (lat deg, lon deg, ellipsoidal height m)."""
    p = np.asarray(xyz, dtype=float)
    if p.shape[-1:] != (3,):
        raise InputError("xyz", p.shape, "an array of shape (..., 3)")
    lat, lon, h = geodetic_from_ecef(p)
    return np.degrees(lat), np.degrees(lon), h


def enu_basis(lat_deg: ArrayLike, lon_deg: ArrayLike) -> Array:
    """Local East-North-Up unit vectors in ECEF; returns ``(..., 3, 3)`` with columns E, N, U."""
    return _enu_basis(np.radians(np.asarray(lat_deg, dtype=float)), np.radians(np.asarray(lon_deg, dtype=float)))


def parse_epoch(epoch_utc: str) -> tuple[float, float]:
    """UTC ISO-8601 string -> two-part Julian date (erfa convention, UTC quasi-JD)."""
    try:
        d = _dt.datetime.fromisoformat(epoch_utc.replace("Z", "+00:00"))
    except (ValueError, AttributeError) as exc:
        raise InputError("epoch_utc", epoch_utc, "an ISO-8601 UTC time such as 2001-06-15T17:00:00Z") from exc
    if d.tzinfo is not None:
        d = d.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    sec = d.second + d.microsecond * 1e-6
    jd1, jd2 = erfa.dtf2d("UTC", d.year, d.month, d.day, d.hour, d.minute, sec)
    return float(jd1), float(jd2)


@dataclass(frozen=True)
class EarthOrientation:
    """ECEF <-> ECI (J2000) rotation for times in seconds from a UTC epoch.

    Parameters
    ----------
    epoch_utc:
        ISO-8601 UTC epoch of the time axis.
    dut1:
        UT1 - UTC in seconds (default 0).
    xp, yp:
        Polar motion in arcseconds (default 0).
    """

    epoch_utc: str
    dut1: float = 0.0
    xp: float = 0.0
    yp: float = 0.0

    @functools.cached_property
    def _jd(self) -> tuple[float, float, float, float]:
        u1, u2 = parse_epoch(self.epoch_utc)
        a1, a2 = erfa.utctai(u1, u2)
        t1, t2 = erfa.taitt(a1, a2)
        b1, b2 = erfa.utcut1(u1, u2, self.dut1)
        return float(t1), float(t2), float(b1), float(b2)

    @functools.cached_property
    def _pom(self) -> Array:
        t1, t2, _, _ = self._jd
        arcsec = np.pi / 180.0 / 3600.0
        return np.asarray(erfa.pom00(self.xp * arcsec, self.yp * arcsec, erfa.sp00(t1, t2)))

    def _q(self, t: Array) -> Array:
        t1, t2, _, _ = self._jd
        step = 60.0
        lo = np.floor(t.min() / step) * step if t.size else 0.0
        hi = np.ceil(t.max() / step) * step if t.size else 0.0
        grid = np.arange(lo, hi + step, step)
        qg = erfa.c2i06a(t1, t2 + grid / 86400.0)
        idx = np.clip(((t - lo) / step).astype(int), 0, len(grid) - 2) if len(grid) > 1 else np.zeros(t.shape, int)
        if len(grid) == 1:
            return np.broadcast_to(qg[0], t.shape + (3, 3)).copy()
        w = ((t - grid[idx]) / step)[..., None, None]
        return qg[idx] * (1 - w) + qg[idx + 1] * w

    def era(self, t: ArrayLike) -> Array:
        """Earth rotation angle (rad) at times ``t`` (s from epoch)."""
        _, _, b1, b2 = self._jd
        return np.asarray(erfa.era00(b1, b2 + np.asarray(t, dtype=float) / 86400.0))

    def eci_to_ecef(self, t: ArrayLike) -> Array:
        """Rotation matrices ECI(J2000) -> ECEF at times ``t`` (s from epoch): ``(..., 3, 3)``."""
        tt = np.asarray(t, dtype=float)
        flat = tt.ravel()
        m = self._pom @ rot_z(-self.era(flat)) @ self._q(flat)
        return m.reshape(tt.shape + (3, 3))

    def ecef_to_eci(self, t: ArrayLike) -> Array:
        """Rotation matrices ECEF -> ECI(J2000) at times ``t``: ``(..., 3, 3)``."""
        return np.swapaxes(self.eci_to_ecef(t), -1, -2)

    def direct_c2t(self, t: ArrayLike) -> Array:
        """Reference: ``erfa.c2t06a`` evaluated at every time (slow; used by tests)."""
        t1, t2, b1, b2 = self._jd
        arcsec = np.pi / 180.0 / 3600.0
        tt = np.asarray(t, dtype=float) / 86400.0
        return np.asarray(erfa.c2t06a(t1, t2 + tt, b1, b2 + tt, self.xp * arcsec, self.yp * arcsec))
