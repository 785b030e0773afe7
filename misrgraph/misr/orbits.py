"""MISR's orbit numbering: orbit <-> path <-> UTC time.

Terra repeats its ground track every 16 days in 233 orbits, so consecutive orbits step 16 paths
east-to-west across the WRS-2 grid: ``path(orbit) = (orbit * 16 + 176) mod 233 + 1``. The
numbering is regular from orbit 995 (2000-02-24, the first orbit of the operational repeat
cycle); the earlier orbits, before Terra reached its final orbit, are not supported.

An orbit's start time is its reference start plus ``16/233`` day per orbit. The reference is the
measured start time of the nearest earlier thousandth orbit (:data:`ORBIT_START_JD`, orbits
1000..74000 as MISR's orbit records give them, and orbit 995), so that the slow drift of the real
orbit period does not accumulate. After orbit 74 000 (2013-11-15) the last reference is
extrapolated with the nominal period, as the MISR Toolkit does; the error then grows by the
period's drift (tens of seconds per year), which matters for orbit boundaries only.

Time -> orbit is the exact inverse of orbit -> time (``start <= t < end``). The MISR Toolkit
instead picks its reference from an orbit estimated with the nominal period since orbit 1000, so
in the orbit after each thousandth one its two directions disagree by up to two minutes (measured
over orbits 1000..80000); its own case 2006-09-24T10:35:00Z -> orbit 35999 lies 0.2 s after the
start of orbit 36000 in its table (10:34:59.8), and here gives 36000. Times are UTC; Julian dates
are UTC-based (no leap seconds), as in MISR's tables.
"""

from __future__ import annotations

import datetime as _dt
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from misrgraph.errors import InputError
from misrgraph.model.constants import REPEAT_DAYS, REPEAT_PATHS

__all__ = [
    "FIRST_ORBIT",
    "ORBIT_START_JD",
    "ORBIT_PERIOD_DAYS",
    "orbit_to_path",
    "orbit_time_range",
    "time_to_orbit",
    "parse_utc",
    "format_utc",
]

#: The first orbit of MISR's regular numbering.
FIRST_ORBIT = 995
#: Nominal orbit period in days (16 days / 233 orbits).
ORBIT_PERIOD_DAYS = REPEAT_DAYS / REPEAT_PATHS
_ORBITS_PER_DAY = REPEAT_PATHS / REPEAT_DAYS
_PATH_STEP = 16
_PATH_PHASE = 176

#: UTC Julian date of the start of orbit 995 and of every thousandth orbit 1000..74000.
_START_995_JD = 2451599.189583333
_START_THOUSANDS_JD = (
    2451599.51744,
    2451668.18819,
    2451736.85764,
    2451805.52639,
    2451874.19514,
    2451942.86389,
    2452011.53194,
    2452080.2,
    2452148.86875,
    2452217.53681,
    2452286.20486,
    2452354.87361,
    2452423.54306,
    2452492.2125,
    2452560.88194,
    2452629.55139,
    2452698.22083,
    2452766.88958,
    2452835.55903,
    2452904.22847,
    2452972.89861,
    2453041.56806,
    2453110.2375,
    2453178.90694,
    2453247.57569,
    2453316.24514,
    2453384.91528,
    2453453.58472,
    2453522.25417,
    2453590.92361,
    2453659.59306,
    2453728.2625,
    2453796.93194,
    2453865.60139,
    2453934.27152,
    2454002.94097,
    2454071.61042,
    2454140.28055,
    2454208.95,
    2454277.61944,
    2454346.28889,
    2454414.95833,
    2454483.62778,
    2454552.29722,
    2454620.96736,
    2454689.63681,
    2454758.306250,
    2454826.975694,
    2454895.645139,
    2454964.314583,
    2455032.984028,
    2455101.653472,
    2455170.322917,
    2455238.992361,
    2455307.662500,
    2455376.331944,
    2455445.001389,
    2455513.670833,
    2455582.340278,
    2455651.009722,
    2455719.679167,
    2455788.348611,
    2455857.018750,
    2455925.688194,
    2455994.357639,
    2456063.027083,
    2456131.696528,
    2456200.365972,
    2456269.035417,
    2456337.704861,
    2456406.375000,
    2456475.044444,
    2456543.713889,
    2456612.383333,
)
ORBIT_START_JD: dict[int, float] = {
    FIRST_ORBIT: _START_995_JD,
    **{1000 * (k + 1): jd for k, jd in enumerate(_START_THOUSANDS_JD)},
}

_JD_J2000 = 2451545.0
_J2000 = _dt.datetime(2000, 1, 1, 12, 0, 0, tzinfo=_dt.timezone.utc)


def _check_orbits(orbit: ArrayLike, name: str = "orbit") -> NDArray[np.int64]:
    o = np.asarray(orbit)
    if o.dtype == bool or not (np.issubdtype(o.dtype, np.integer) or np.issubdtype(o.dtype, np.floating)):
        raise InputError(name, orbit, f"an integer orbit number >= {FIRST_ORBIT}")
    of = o.astype(float)
    bad = ~np.isfinite(of) | (of != np.round(of)) | (of < FIRST_ORBIT)
    if np.any(bad):
        v = of.ravel()[int(np.flatnonzero(bad.ravel())[0])]
        raise InputError(
            name,
            int(v) if np.isfinite(v) and v == round(v) else float(v),
            f"an integer orbit number >= {FIRST_ORBIT} (MISR's regular numbering starts on 2000-02-24)",
        )
    return of.astype(np.int64)


def orbit_to_path(orbit: ArrayLike) -> NDArray[np.int64]:
    """Path (1..233) of each orbit number (>= 995); the shape of ``orbit``."""
    o = _check_orbits(orbit)
    return (_PATH_PHASE + o * _PATH_STEP) % REPEAT_PATHS + 1


def _reference(orbit: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """(reference orbit, its start JD) used for each orbit."""
    k = np.clip(orbit // 1000, 0, len(_START_THOUSANDS_JD))
    ref = np.where(k == 0, FIRST_ORBIT, k * 1000)
    jd = np.where(k == 0, _START_995_JD, np.asarray((0.0,) + _START_THOUSANDS_JD)[k])
    return ref, jd


def _orbit_start_jd(orbit: NDArray[np.int64]) -> NDArray[np.float64]:
    ref, jd = _reference(orbit)
    return jd + ORBIT_PERIOD_DAYS * (orbit - ref)


def _jd_to_datetime(jd: float) -> _dt.datetime:
    return _J2000 + _dt.timedelta(days=float(jd) - _JD_J2000)


def _datetime_to_jd(t: _dt.datetime) -> float:
    return _JD_J2000 + (t - _J2000) / _dt.timedelta(days=1)


def orbit_time_range(orbit: int) -> tuple[_dt.datetime, _dt.datetime]:
    """UTC start and end (the next orbit's start) of ``orbit`` as timezone-aware datetimes."""
    o = _check_orbits(orbit)
    if o.ndim:
        raise InputError("orbit", orbit, "one orbit number")
    start = _orbit_start_jd(o)
    end = _orbit_start_jd(o + 1)
    return _jd_to_datetime(float(start)), _jd_to_datetime(float(end))


def parse_utc(time: str | _dt.datetime, name: str = "time") -> _dt.datetime:
    """A timezone-aware UTC datetime from an ISO-8601 string (``Z``, an offset, or none = UTC)
    or a datetime (naive = UTC)."""
    if isinstance(time, _dt.datetime):
        t = time
    else:
        try:
            t = _dt.datetime.fromisoformat(str(time).strip().replace("Z", "+00:00"))
        except ValueError as exc:
            raise InputError(name, time, "an ISO-8601 UTC time such as 2005-08-08T10:10:00Z") from exc
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.timezone.utc)
    return t.astimezone(_dt.timezone.utc)


def format_utc(t: _dt.datetime) -> str:
    """ISO-8601 UTC to the nearest second with a ``Z`` (MISR's orbit-time format)."""
    whole = (t + _dt.timedelta(microseconds=500_000)).replace(microsecond=0)
    return whole.astimezone(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def time_to_orbit(time: str | _dt.datetime) -> int:
    """The orbit (>= 995) flying at UTC ``time``: the exact inverse of :func:`orbit_time_range`
    (``start <= time < end``)."""
    t = parse_utc(time)
    jd = _datetime_to_jd(t)
    if jd < _START_995_JD:
        raise InputError(
            "time",
            format_utc(t),
            f"a UTC time at or after {format_utc(_jd_to_datetime(_START_995_JD))}, the start of orbit {FIRST_ORBIT}",
        )
    # first guess with the nominal period from orbit 995, then step to the orbit whose range holds it
    orbit = max(FIRST_ORBIT, int(math.floor(_ORBITS_PER_DAY * (jd - _START_995_JD))) + FIRST_ORBIT)
    while orbit > FIRST_ORBIT and _orbit_start_jd(np.int64(orbit)) > jd:
        orbit -= 1
    while _orbit_start_jd(np.int64(orbit + 1)) <= jd:
        orbit += 1
    return orbit
