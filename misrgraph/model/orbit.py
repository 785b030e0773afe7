"""Orbit and attitude time series: a Terra-like sun-synchronous orbit, TLE propagation, interpolation.

* :class:`Ephemeris` holds inertial (J2000) position (m) and velocity (m/s) sampled every
  1.024 s like the GN&CS navigation data, with times in seconds from a UTC epoch. Between samples
  it interpolates with a cubic Hermite spline on position and velocity.
* :class:`AttitudeSeries` holds roll, pitch, yaw (rad, relative to the orbital frame, eq. 5) and
  their rates (rad/s), interpolated the same way.
* :func:`terra_like_orbit` makes a circular sun-synchronous orbit (~705 km, 98.2 deg, 16-day /
  233-path repeat, 10:30 descending node) for a WRS-2 path; :func:`orbit_from_tle` propagates a
  two-line element set with ``sgp4`` and converts TEME -> J2000 with ``pyerfa``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import erfa
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import CubicHermiteSpline

from factors.geometry import rot_z
from misrgraph.errors import InputError
from misrgraph.model.constants import NAV_SAMPLE_S, NODAL_PERIOD_S, ORBIT_INCLINATION_DEG, REPEAT_PATHS
from misrgraph.model.frames import GM_EARTH, WGS84_A, EarthOrientation, geodetic_to_ecef, parse_epoch

__all__ = [
    "Ephemeris",
    "AttitudeSeries",
    "terra_like_orbit",
    "orbit_from_tle",
    "path_node_longitude",
    "TERRA_TLE",
]

Array = NDArray[np.float64]

#: A valid Terra two-line element set (2017-05-11), from the foundation issue.
TERRA_TLE = (
    "1 25994U 99068A   17131.81002569  .00000307  00000-0  78120-4 0  9997",
    "2 25994  98.2120 207.3714 0001359 116.9424 243.1898 14.57112580925377",
)

#: Longitude (deg) of the descending node of WRS-2 path 1; each later path is 360/233 deg west.
PATH1_NODE_LON_DEG = -64.6


def _check_series(name: str, t: Array, *arrays: Array) -> None:
    if t.ndim != 1 or t.size < 2:
        raise InputError(f"{name}.t", t.shape, "a 1-D array of at least two times")
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{name}.t[{i}]", float(t[i]), "finite seconds")
    step = np.diff(t) <= 0
    if step.any():
        i = int(np.flatnonzero(step)[0]) + 1
        raise InputError(f"{name}.t[{i}]", float(t[i]), f"strictly increasing seconds (after {float(t[i - 1])})")
    for a in arrays:
        if a.shape != (t.size, 3):
            raise InputError(name, a.shape, f"shape ({t.size}, 3)")
        bad_rows = ~np.all(np.isfinite(a), axis=1)
        if bad_rows.any():
            i = int(np.flatnonzero(bad_rows)[0])
            raise InputError(f"{name}[{i}]", a[i].tolist(), "finite values")


@dataclass
class Ephemeris:
    """Inertial (J2000) position/velocity samples. ``t (N,)`` s from ``epoch_utc``;
    ``position, velocity (N, 3)`` in m and m/s."""

    epoch_utc: str
    t: Array
    position: Array
    velocity: Array

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float)
        self.position = np.asarray(self.position, dtype=float)
        self.velocity = np.asarray(self.velocity, dtype=float)
        _check_series("ephemeris", self.t, self.position, self.velocity)
        self._spline = CubicHermiteSpline(self.t, self.position, self.velocity, axis=0)

    def interpolate(self, t: ArrayLike) -> tuple[Array, Array]:
        """Position (m) and velocity (m/s) at times ``t`` (s), each ``t.shape + (3,)``."""
        tt = np.asarray(t, dtype=float)
        self._check_range(tt)
        return self._spline(tt), self._spline(tt, 1)

    def _check_range(self, tt: Array) -> None:
        if tt.size and (tt.min() < self.t[0] - 1e-9 or tt.max() > self.t[-1] + 1e-9):
            raise InputError(
                "t", f"[{tt.min():.3f}, {tt.max():.3f}] s", f"times within [{self.t[0]:.3f}, {self.t[-1]:.3f}] s"
            )

    @property
    def span(self) -> tuple[float, float]:
        """First and last sample time (s)."""
        return float(self.t[0]), float(self.t[-1])


@dataclass
class AttitudeSeries:
    """Roll/pitch/yaw (rad) relative to the orbital frame and their rates (rad/s), ``(N, 3)``."""

    t: Array
    angles: Array
    rates: Array

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float)
        self.angles = np.asarray(self.angles, dtype=float)
        self.rates = np.asarray(self.rates, dtype=float)
        _check_series("attitude", self.t, self.angles, self.rates)
        self._spline = CubicHermiteSpline(self.t, self.angles, self.rates, axis=0)

    def interpolate(self, t: ArrayLike) -> Array:
        """Angles (rad) at times ``t`` (s), ``t.shape + (3,)`` in order roll, pitch, yaw."""
        return self._spline(np.asarray(t, dtype=float))

    @classmethod
    def zeros(cls, t: ArrayLike) -> "AttitudeSeries":
        """Perfect nadir pointing at the sample times ``t``."""
        tt = np.asarray(t, dtype=float)
        z = np.zeros((tt.size, 3))
        return cls(tt, z, z.copy())


def path_node_longitude(path: int) -> float:
    """Longitude (deg, in [-180, 180)) of the descending equator crossing of WRS-2 ``path``."""
    if not (1 <= int(path) <= REPEAT_PATHS):
        raise InputError("path", path, f"an integer in 1..{REPEAT_PATHS}")
    lon = PATH1_NODE_LON_DEG - (int(path) - 1) * 360.0 / REPEAT_PATHS
    return (lon + 180.0) % 360.0 - 180.0


def terra_like_orbit(
    epoch_date: str = "2001-06-15",
    path: int = 37,
    start_lat_deg: float = 75.0,
    duration_s: float = 2700.0,
    step_s: float = NAV_SAMPLE_S,
    inclination_deg: float = ORBIT_INCLINATION_DEG,
) -> Ephemeris:
    """A circular, sun-synchronous, Terra-like daylight (descending) pass over WRS-2 ``path``.

    The nodal period is the 16-day/233-orbit repeat (5932.4 s), the semi-major axis follows from
    it with Kepler's law (altitude ~700 km), the node drifts at the sun-synchronous rate, and the
    descending node crosses the path's longitude at 10:30 mean local solar time on
    ``epoch_date``. The pass starts when the descending track is at geocentric latitude ``start_lat_deg`` and lasts
    ``duration_s``; the epoch of the returned :class:`Ephemeris` is the pass start (UTC).
    """
    if not (-80.0 < start_lat_deg < 81.5):
        raise InputError("start_lat_deg", start_lat_deg, "a latitude the orbit reaches (-80..81.5 deg)")
    if duration_s <= 2 * step_s:
        raise InputError("duration_s", duration_s, f"more than {2 * step_s} s")
    inc = math.radians(inclination_deg)
    n = 2.0 * math.pi / NODAL_PERIOD_S
    a = (GM_EARTH / n**2) ** (1.0 / 3.0)
    raan_rate = 2.0 * math.pi / (365.2422 * 86400.0)
    node_lon = path_node_longitude(path)
    # UTC time of the descending node: mean local solar time 10:30 at the node longitude.
    node_hours = (10.5 - node_lon / 15.0) % 24.0
    node_epoch = f"{epoch_date}T00:00:00"
    eo = EarthOrientation(node_epoch)
    t_node = node_hours * 3600.0
    node_dir = geodetic_to_ecef(0.0, node_lon, 0.0)
    node_dir = eo.ecef_to_eci(t_node) @ (node_dir / np.linalg.norm(node_dir))
    # Descending node is at argument of latitude u = pi; its direction is -(cos raan, sin raan, 0).
    raan_node = math.atan2(-node_dir[1], -node_dir[0])
    # Argument of latitude at pass start (descending branch, u in (pi/2, 3pi/2)).
    s = math.sin(math.radians(start_lat_deg)) / math.sin(inc)
    u_start = math.pi - math.asin(s)
    t_start = t_node - (math.pi - u_start) / n
    t = np.arange(0.0, duration_s + 1e-9, step_s)
    tau = t + t_start - t_node  # seconds from the node
    u = math.pi + n * tau
    raan = raan_node + raan_rate * tau
    cu, su, co, so = np.cos(u), np.sin(u), np.cos(raan), np.sin(raan)
    ci, si = math.cos(inc), math.sin(inc)
    pos = a * np.stack([cu * co - su * ci * so, cu * so + su * ci * co, su * si], axis=-1)
    # d/dt with du/dt = n and draan/dt = raan_rate
    dpos_du = a * np.stack([-su * co - cu * ci * so, -su * so + cu * ci * co, cu * si], axis=-1)
    dpos_draan = a * np.stack([-cu * so - su * ci * co, cu * co - su * ci * so, np.zeros_like(cu)], axis=-1)
    vel = n * dpos_du + raan_rate * dpos_draan
    epoch = _shift_epoch(node_epoch, t_start)
    return Ephemeris(epoch, t, pos, vel)


def _shift_epoch(epoch_utc: str, seconds: float) -> str:
    import datetime as dt

    d = dt.datetime.fromisoformat(epoch_utc) + dt.timedelta(seconds=seconds)
    return d.strftime("%Y-%m-%dT%H:%M:%S.%f") + "Z"


def teme_to_j2000(epoch_utc: str, t: ArrayLike, r_teme: ArrayLike) -> Array:
    """Rotate TEME vectors to J2000/GCRS: ``r = NPB(TT)^T Rz_erfa(-EqEq) r_TEME``.

    TEME shares the true equator of date with the true-of-date frame but its x axis is the mean
    equinox; the two differ by the equation of the equinoxes about z.
    """
    u1, u2 = parse_epoch(epoch_utc)
    a1, a2 = erfa.utctai(u1, u2)
    t1, t2 = erfa.taitt(a1, a2)
    tt = np.asarray(t, dtype=float)
    t2s = t2 + tt / 86400.0
    ee = erfa.ee06a(t1, t2s)
    npb = erfa.pnm06a(t1, t2s)
    # erfa's R3(psi) is an active rotation by -psi; TOD = R3(-ee) TEME = active rot_z(ee)
    r_tod = np.einsum("...ij,...j->...i", rot_z(ee), np.asarray(r_teme, dtype=float))
    return np.einsum("...ji,...j->...i", npb, r_tod)


def orbit_from_tle(
    line1: str = TERRA_TLE[0],
    line2: str = TERRA_TLE[1],
    start_utc: str | None = None,
    duration_s: float = 2700.0,
    step_s: float = NAV_SAMPLE_S,
) -> Ephemeris:
    """Propagate a TLE with SGP4 and return an :class:`Ephemeris` in J2000.

    ``start_utc`` defaults to the TLE epoch. Errors from SGP4 (decayed orbit, bad elements) are
    reported as :class:`InputError`.
    """
    from sgp4.api import Satrec

    try:
        sat = Satrec.twoline2rv(line1, line2)
    except Exception as exc:  # sgp4 raises ValueError on malformed lines
        raise InputError("tle", (line1, line2), "a valid two-line element set") from exc
    if start_utc is None:
        y, mo, d, fd = erfa.jd2cal(sat.jdsatepoch, sat.jdsatepochF)
        hms = fd * 86400.0
        start_utc = f"{y:04d}-{mo:02d}-{d:02d}T{int(hms // 3600):02d}:{int(hms % 3600 // 60):02d}:{hms % 60:09.6f}Z"
    j1, j2 = parse_epoch(start_utc)
    t = np.arange(0.0, duration_s + 1e-9, step_s)
    err, r, v = sat.sgp4_array(np.full(t.shape, j1), j2 + t / 86400.0)
    if np.any(err != 0):
        raise InputError("tle", int(err[err != 0][0]), "elements SGP4 can propagate (error code 0)")
    pos = teme_to_j2000(start_utc, t, r * 1e3)
    vel = teme_to_j2000(start_utc, t, v * 1e3)
    return Ephemeris(start_utc, t, pos, vel)


def mean_altitude(eph: Ephemeris) -> float:
    """Mean geocentric radius minus the WGS84 equatorial radius (m): a quick sanity figure."""
    return float(np.mean(np.linalg.norm(eph.position, axis=-1)) - WGS84_A)
